// Live needle safety on an analytic plan: a needle through empty space to the tumor is safe with
// a zero line integral and known distances; through a vessel column it is dangerous with the
// vessel at its depth; the angle to the nearest safe direction is 0 along a safe vertex direction
// and the rotation angle when turned away from it; a needle pointing away or beside the tumor
// misses it by a known distance.
#include "planning/trajectories/needle_guidance.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <random>
#include <set>

#include <Eigen/Geometry>

#include "foundation/error.hpp"
#include "pipelines/plan.hpp"
#include "planning/imaging/volume_io.hpp"
#include "tests/support/grids.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

using pipelines::PlanRequest;
using pipelines::run_plan;
using test::cube_grid;

// A needle frame that is not the CT frame: rotation about a skewed axis plus a translation.
Eigen::Isometry3d needle_pose() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, -2, 0.5).normalized()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(13, -7, 40);
  return T;
}

// Evaluates a needle given in CT (tip, axis) through needle_pose(): the tip and axis are mapped
// into needle coordinates first (the axis scaled, it need not be unit).
NeedleState in_ct(const NeedleGuide& guide, const Eigen::Vector3d& tip, const Eigen::Vector3d& axis) {
  const Eigen::Isometry3d T = needle_pose();
  return guide.evaluate(T, T.inverse() * tip, 3.0 * (T.linear().transpose() * axis));
}

// The plan of a 24^3 grid of 2 mm voxels: a tumor block on voxels 10..12, a vessel column
// (label 2, impassable) at i = 16, j = 9..13, every k; fat (no blocking) elsewhere; R = 16 mm.
class NeedleGuidanceTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TemporaryFolder;
    const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(*dir_);
    grid_ = inputs.grid;
    PlanRequest r = inputs.request((*dir_ / "plan").string());
    r.margin.fwhm_mm = 0.0;
    run_plan(r);
    guide_ = new NeedleGuide((*dir_ / "plan").string());
  }
  static void TearDownTestSuite() {
    delete guide_;
    delete dir_;
  }
  static test::TemporaryFolder* dir_;
  static ImageGeometry grid_;
  static NeedleGuide* guide_;
};
test::TemporaryFolder* NeedleGuidanceTest::dir_ = nullptr;
ImageGeometry NeedleGuidanceTest::grid_;
NeedleGuide* NeedleGuidanceTest::guide_ = nullptr;

// line_safety() against evaluate() on lines around the tumor (fixed seed): tips 3 to 25 mm from
// the tumor centre (in the body and in the air), aimed within 6 mm of it or anywhere (some point
// away: kUnknown then). Returns the classes of the lines that do not point away; every line must
// agree.
std::set<NeedleSafety> expect_line_safety_equals_evaluate(const NeedleGuide& guide) {
  std::mt19937 rng(20261124);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  const auto random_unit = [&] {
    Eigen::Vector3d d;
    do d = Eigen::Vector3d(unit(rng), unit(rng), unit(rng));
    while (d.norm() > 1.0 || d.norm() < 0.1);
    return Eigen::Vector3d(d.normalized());
  };
  const Eigen::Vector3d c = guide.plan().tumor_centre;
  std::set<NeedleSafety> seen;
  for (int i = 0; i < 400; ++i) {
    const Eigen::Vector3d tip = c + (14.0 + 11.0 * unit(rng)) * random_unit();
    const Eigen::Vector3d axis =
        i % 5 == 4 ? random_unit() : Eigen::Vector3d(c + 6.0 * unit(rng) * random_unit() - tip);
    const NeedleState s = guide.evaluate(Eigen::Isometry3d::Identity(), tip, axis);
    // One rule set: a needle pointing away is never safe, and both give the same class.
    if (s.points_away) EXPECT_NE(s.safety, NeedleSafety::kSafe) << "line " << i;
    EXPECT_EQ(guide.line_safety(tip, axis), s.safety)
        << "line " << i << ": tip " << tip.transpose() << ", axis " << axis.transpose()
        << ", line integral " << s.evaluation.line_integral << ", tip class " << s.tip_class;
    if (!s.points_away) seen.insert(s.safety);
  }
  return seen;
}

TEST_F(NeedleGuidanceTest, NeedleThroughEmptySpaceToTheTumorIsSafe) {
  const Eigen::Vector3d c = grid_.index_to_physical(11, 11, 11);
  ASSERT_LT((guide_->plan().tumor_centre - c).norm(), 1e-6);
  const Eigen::Vector3d tip = grid_.index_to_physical(5, 11, 11);  // 12 mm on the -x side
  const NeedleState s = in_ct(*guide_, tip, Eigen::Vector3d::UnitX());
  EXPECT_LT((s.tip - tip).norm(), 1e-9);
  EXPECT_LT((s.axis - Eigen::Vector3d::UnitX()).norm(), 1e-9);
  EXPECT_NEAR(s.tip_to_centroid_mm, 12.0, 1e-9);
  EXPECT_NEAR(s.along_axis_mm, 12.0, 1e-9);
  EXPECT_NEAR(s.miss_distance_mm, 0.0, 1e-9);
  EXPECT_LT((s.target - c).norm(), 1e-9);
  EXPECT_FALSE(s.points_away);
  EXPECT_TRUE(s.hits_tumor);
  // Tumor voxels 10..12 start at index 9.5: 4.5 voxels = 9 mm from the tip.
  EXPECT_NEAR(s.tumor_depth_mm, 9.0, s.evaluation.structure_step_mm + 1e-9);
  EXPECT_NEAR(s.evaluation.line_integral, 0.0, 1e-9);
  EXPECT_TRUE(s.clear);
  for (const auto& h : s.evaluation.structures) EXPECT_NE(h.name, "vessel");
  // Every ray from the -x side to the tumor surface is clear: SVV 100 %, safe.
  EXPECT_EQ(s.tip_class, "safe");
  EXPECT_EQ(s.safety, NeedleSafety::kSafe);
  EXPECT_STREQ(needle_safety_name(s.safety), "safe");

  // The one-off function gives the same answer from the same plan.
  const Eigen::Isometry3d T = needle_pose();
  const NeedleState f = needle_guidance(guide_->plan(), T, T.inverse() * tip,
                                        T.linear().transpose() * Eigen::Vector3d::UnitX());
  EXPECT_DOUBLE_EQ(f.evaluation.line_integral, s.evaluation.line_integral);
  EXPECT_DOUBLE_EQ(f.along_axis_mm, s.along_axis_mm);
}

TEST_F(NeedleGuidanceTest, NeedleThroughTheVesselIsDangerousWithTheVesselAtItsDepth) {
  const Eigen::Vector3d tip = grid_.index_to_physical(18, 11, 11);  // 14 mm on the +x side
  const NeedleState s = in_ct(*guide_, tip, -Eigen::Vector3d::UnitX());
  EXPECT_NEAR(s.along_axis_mm, 14.0, 1e-9);
  EXPECT_TRUE(s.hits_tumor);
  // The vessel voxel (2 mm at 10 per mm): the trilinear interpolant integrates to 20, within one
  // 1 mm step times the jump of 10.
  EXPECT_NEAR(s.evaluation.line_integral, 20.0, 10.0 * s.evaluation.step_mm + 1e-6);
  EXPECT_GT(s.evaluation.line_integral, s.eps);
  EXPECT_FALSE(s.clear);
  EXPECT_EQ(s.safety, NeedleSafety::kDangerous);
  bool vessel = false;
  for (const auto& h : s.evaluation.structures) {
    if (h.name != "vessel") continue;
    vessel = true;
    EXPECT_EQ(h.level, 3);
    // Voxel 16 covers index [15.5, 16.5]: entered 1.5 voxels = 3 mm from the tip, 2 mm long.
    EXPECT_NEAR(h.depth_mm, 3.0, s.evaluation.structure_step_mm + 1e-9);
    EXPECT_NEAR(h.length_mm, 2.0, s.evaluation.structure_step_mm + 1e-9);
  }
  EXPECT_TRUE(vessel);
}

TEST_F(NeedleGuidanceTest, NeedlePointingAwayOrBesideTheTumorMissesIt) {
  const Eigen::Vector3d c = guide_->plan().tumor_centre;
  const Eigen::Vector3d tip = grid_.index_to_physical(5, 11, 11);
  NeedleState s = in_ct(*guide_, tip, -Eigen::Vector3d::UnitX());  // away from the tumor
  EXPECT_TRUE(s.points_away);
  EXPECT_FALSE(s.hits_tumor);
  EXPECT_NEAR(s.miss_distance_mm, 12.0, 1e-9);
  EXPECT_NEAR(s.along_axis_mm, 0.0, 1e-12);
  EXPECT_EQ(s.evaluation.samples, 0);
  // In empty space (its tip safe, nothing on its line to cross) it is still no path to the
  // tumor: unknown, never safe; line_safety (the targeting view) says the same.
  EXPECT_EQ(s.tip_class, "safe");
  EXPECT_EQ(s.safety, NeedleSafety::kUnknown);
  EXPECT_EQ(guide_->line_safety(tip, -Eigen::Vector3d::UnitX()), NeedleSafety::kUnknown);
  // Pushed through the tumor, its tip 4 mm beyond the centre on the far side: the tumor's centre
  // lies behind the tip, so the needle has no line to it either.
  const NeedleState through = in_ct(*guide_, c + Eigen::Vector3d(4, 0, 0), Eigen::Vector3d::UnitX());
  EXPECT_TRUE(through.points_away);
  EXPECT_NE(through.safety, NeedleSafety::kSafe);

  // Parallel to the good needle, 8 mm beside it (the tumor block is 6 mm wide): misses by 8 mm.
  const Eigen::Vector3d beside = tip + Eigen::Vector3d(0, 8, 0);
  s = in_ct(*guide_, beside, Eigen::Vector3d::UnitX());
  EXPECT_FALSE(s.points_away);
  EXPECT_FALSE(s.hits_tumor);
  EXPECT_NEAR(s.miss_distance_mm, 8.0, 1e-9);
  EXPECT_NEAR(s.along_axis_mm, 12.0, 1e-9);
  EXPECT_NEAR(s.tip_to_centroid_mm, std::hypot(12.0, 8.0), 1e-9);
  EXPECT_LT(s.tumor_depth_mm, 0.0);
  // Tilted so that its line passes 1 mm from the centroid: inside the block, a hit.
  const Eigen::Vector3d towards = (c + Eigen::Vector3d(0, 0, 1) - tip).normalized();
  s = in_ct(*guide_, tip, towards);
  EXPECT_TRUE(s.hits_tumor);
  EXPECT_NEAR(s.miss_distance_mm, 1.0 * std::cos(std::asin(towards.z())), 1e-9);

  EXPECT_THROW(guide_->evaluate(Eigen::Isometry3d::Identity(), tip, Eigen::Vector3d::Zero()),
               Error);
}

TEST_F(NeedleGuidanceTest, AngleIsZeroAlongASafeDirectionAndMatchesBruteForce) {
  const auto& dirs = guide_->safe_directions();
  ASSERT_FALSE(dirs.empty());
  const AreaSafetyGeometry& a = *guide_->plan().area;
  const Eigen::Vector3d c = guide_->plan().tumor_centre;
  std::mt19937 rng(7);
  std::uniform_int_distribution<size_t> pick(0, dirs.size() - 1);
  for (int n = 0; n < 5; ++n) {
    const Eigen::Vector3d u = dirs[pick(rng)];
    const NeedleState s = in_ct(*guide_, c + 15.0 * u, -u);
    EXPECT_NEAR(s.angle_to_safe_deg, 0.0, 1e-5);
    EXPECT_GT(s.nearest_safe_direction.dot(u), 1.0 - 1e-12);
  }
  // Arbitrary axes against a brute-force reference straight from the mesh: the smallest angle
  // between the outward needle direction and (safe extruded vertex - centroid).
  std::normal_distribution<double> normal;
  for (int n = 0; n < 20; ++n) {
    const Eigen::Vector3d axis(normal(rng), normal(rng), normal(rng));
    const Eigen::Vector3d out = -axis.normalized();
    double best = 180;
    for (size_t i = 0; i < a.vertices.size(); ++i) {
      if (!a.safe[i]) continue;
      const Eigen::Vector3d d = a.vertices[i] - c;
      best = std::min(best, std::atan2(out.cross(d).norm(), out.dot(d)) * 180.0 / M_PI);
    }
    const NeedleState s = in_ct(*guide_, c - 20.0 * axis.normalized(), axis);
    EXPECT_NEAR(s.angle_to_safe_deg, best, 1e-5);
  }
}

// Six base vertices on the axes around c: +x, +y and -x safe, the rest unsafe.
AreaSafetyGeometry octahedron_area(const Eigen::Vector3d& c) {
  AreaSafetyGeometry a;
  a.ellipsoid.centre = c;
  a.ellipsoid.radii = Eigen::Vector3d::Constant(10);
  const Eigen::Vector3d axes[6] = {Eigen::Vector3d::UnitX(), -Eigen::Vector3d::UnitX(),
                                   Eigen::Vector3d::UnitY(), -Eigen::Vector3d::UnitY(),
                                   Eigen::Vector3d::UnitZ(), -Eigen::Vector3d::UnitZ()};
  const bool safe[6] = {true, true, true, false, false, false};
  for (int i = 0; i < 6; ++i) {
    a.base.push_back(c + 10 * axes[i]);
    a.normals.push_back(axes[i]);
    a.vertices.push_back(c + (safe[i] ? 60 : 22) * axes[i]);
    a.safe.push_back(safe[i]);
    a.region.push_back(safe[i] ? 0 : -1);
    a.leeway.push_back(safe[i] ? 1.0f : 0.0f);
  }
  return a;
}

TEST(NeedleGuidanceAngleTest, AngleToNearestSafeDirectionIsTheRotationAngle) {
  const Eigen::Vector3d c(40, 40, 40);
  PlanData plan;
  plan.dir = "(test plan)";
  plan.blocking = Volume<float>(cube_grid(40, 2.0), 0.0f);
  plan.gamma_mm = 1.0;
  plan.tumor_centre = c;
  plan.area = octahedron_area(c);
  const NeedleGuide guide(plan);
  ASSERT_EQ(guide.safe_directions().size(), 3u);
  // No mask: the hit is decided by the ellipsoid (a 10 mm sphere here).
  for (double deg : {0.0, 20.0, 35.0}) {
    const double th = deg * M_PI / 180.0;
    // Outward direction +x turned by deg towards +z (unsafe); +y stays 90 degrees away.
    const Eigen::Vector3d out(std::cos(th), 0, std::sin(th));
    const NeedleState s = guide.evaluate(Eigen::Isometry3d::Identity(), c + 30 * out, -out);
    EXPECT_NEAR(s.angle_to_safe_deg, deg, 1e-9) << deg;
    EXPECT_EQ(s.nearest_safe_vertex, 0);
    EXPECT_TRUE(s.hits_tumor);
    EXPECT_NEAR(s.evaluation.line_integral, 0.0, 1e-12);
    // -x turned by deg towards -z: nearest is vertex 1.
    const Eigen::Vector3d out2(-std::cos(th), 0, -std::sin(th));
    EXPECT_NEAR(guide.evaluate(Eigen::Isometry3d::Identity(), c + 30 * out2, -out2)
                    .angle_to_safe_deg,
                deg, 1e-9);
  }
  // Outward -y (unsafe): every safe direction is 90 degrees away.
  const NeedleState s = guide.evaluate(Eigen::Isometry3d::Identity(),
                                       c - 30 * Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitY());
  EXPECT_NEAR(s.angle_to_safe_deg, 90.0, 1e-9);
  // Beside the sphere by 12 mm: a miss without a mask.
  const NeedleState m = guide.evaluate(Eigen::Isometry3d::Identity(),
                                       c + Eigen::Vector3d(-30, 12, 0), Eigen::Vector3d::UnitX());
  EXPECT_FALSE(m.hits_tumor);
  EXPECT_NEAR(m.miss_distance_mm, 12.0, 1e-9);
}

}  // namespace
}  // namespace crepuscular::planning

namespace crepuscular::planning {
namespace {

// A plan folder moved together with its inputs still finds its label map and tumor mask (plan.json
// records their paths relative to the plan folder too).
// The class-only evaluation the targeting view's polar map uses gives evaluate()'s class on every
// line, safe and dangerous ones among them.
TEST_F(NeedleGuidanceTest, LineSafetyEqualsTheClassOfEvaluate) {
  const std::set<NeedleSafety> seen = expect_line_safety_equals_evaluate(*guide_);
  EXPECT_TRUE(seen.count(NeedleSafety::kSafe));
  EXPECT_TRUE(seen.count(NeedleSafety::kDangerous));
}

TEST_F(NeedleGuidanceTest, PlanMovedWithItsInputsFindsThem) {
  const fs::path moved = dir_->string() + "_moved";
  fs::remove_all(moved);
  fs::rename(*dir_, moved);
  PlanData plan;
  try {
    plan = load_plan((moved / "plan").string());
  } catch (...) {
    fs::rename(moved, *dir_);
    throw;
  }
  fs::rename(moved, *dir_);
  EXPECT_FALSE(plan.labels.empty());
  EXPECT_FALSE(plan.tumor.empty());
  EXPECT_EQ(fs::path(plan.labels_path).lexically_normal(), (moved / "labels.nii.gz").lexically_normal());
}

}  // namespace
}  // namespace crepuscular::planning

namespace crepuscular::planning {
namespace {

// The same needle as NeedleThroughEmptySpaceToTheTumorIsSafe (12 mm on the -x side, through empty
// space), but the scan (a CT) ends 9 mm from the tumor's centre on that side: the part of the
// needle's line beyond the scan is not known, so the needle is unknown, never safe.
TEST(NeedleGuidanceUnknown, NeedleWhoseLineLeavesTheScanIsUnknownNotSafe) {
  test::TemporaryFolder dir;
  const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(dir);
  ImageGeometry ct_grid = inputs.grid;
  ct_grid.origin = inputs.grid.index_to_physical(7, 0, 0);
  ct_grid.dims[0] -= 7;
  write_volume(Volume<float>(ct_grid, 40.0f), dir.file("ct.nii.gz"));
  PlanRequest r = inputs.request(dir.file("plan"));
  r.ct = dir.file("ct.nii.gz");
  r.margin.fwhm_mm = 0.0;
  run_plan(r);
  const NeedleGuide guide(dir.file("plan"));
  const ImageGeometry& g = inputs.grid;
  const NeedleState outside = in_ct(guide, g.index_to_physical(5, 11, 11), Eigen::Vector3d::UnitX());
  EXPECT_TRUE(outside.clear);  // nothing blocks inside the scan...
  EXPECT_TRUE(outside.evaluation.leaves_scan());
  EXPECT_EQ(outside.safety, NeedleSafety::kUnknown);  // ...but the part outside is unknown
  EXPECT_STREQ(needle_safety_name(outside.safety), "unknown");
  // From +z (inside the scan all the way) the same kind of needle stays safe.
  const NeedleState inside = in_ct(guide, g.index_to_physical(11, 11, 17), -Eigen::Vector3d::UnitZ());
  EXPECT_FALSE(inside.evaluation.leaves_scan());
  EXPECT_EQ(inside.safety, NeedleSafety::kSafe);
}

// The class-only evaluation on the plan whose scan ends beside the tumor: lines that leave the
// scan are unknown there too.
TEST(NeedleGuidanceUnknown, LineSafetyEqualsTheClassOfEvaluateWhereTheScanEnds) {
  test::TemporaryFolder dir;
  const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(dir);
  ImageGeometry ct_grid = inputs.grid;
  ct_grid.origin = inputs.grid.index_to_physical(7, 0, 0);
  ct_grid.dims[0] -= 7;
  write_volume(Volume<float>(ct_grid, 40.0f), dir.file("ct.nii.gz"));
  PlanRequest r = inputs.request(dir.file("plan"));
  r.ct = dir.file("ct.nii.gz");
  r.margin.fwhm_mm = 0.0;
  run_plan(r);
  const NeedleGuide guide(dir.file("plan"));
  const std::set<NeedleSafety> seen = expect_line_safety_equals_evaluate(guide);
  EXPECT_TRUE(seen.count(NeedleSafety::kUnknown));
  EXPECT_TRUE(seen.count(NeedleSafety::kDangerous));
}

}  // namespace
}  // namespace crepuscular::planning
