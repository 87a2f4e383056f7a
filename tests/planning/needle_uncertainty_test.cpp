// The needle line's uncertainty: analytic cases (a registration error moves every point alike; a
// tip error moves the line by itself, or tilts it too when the axis follows the tip), coverage
// of simulated recordings (tracking noise of known covariance through the tracker's filter, a
// registration and a tip calibration drawn from their stated errors once per recording: the true
// line inside the predicted 95 % region in 90-98 % of the frames, the spread at the tumor within
// 30 % of the predicted), and a line beside a vessel that is safe only while exact.
#include "planning/trajectories/needle_uncertainty.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "pipelines/plan.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::planning {
namespace {

Eigen::Isometry3d pose(const Eigen::Vector3d& rotation_axis, double angle, const Eigen::Vector3d& t) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(angle, rotation_axis.normalized()).toRotationMatrix();
  T.translation() = t;
  return T;
}

// A scene: the camera above the patient, the patient board on the skin, the needle board 150 mm
// behind its tip, the tumor 80 mm beyond the tip along the needle and 2 mm beside it.
struct Scene {
  Eigen::Isometry3d T_ct_patient = pose({0.2, 1, 0.3}, 2.5, {-40, 120, -300});
  Eigen::Isometry3d T_cam_patient = pose({1, 0.1, 0}, 2.9, {-30, 40, 450});
  Eigen::Isometry3d T_cam_needle = pose({0.9, -0.4, 0.2}, 2.6, {50, -20, 380});
  Eigen::Vector3d tip_in_needle{2, -1, 150};
  Eigen::Vector3d tumor;
  Scene() {
    const Eigen::Isometry3d T = T_ct_patient * T_cam_patient.inverse() * T_cam_needle;
    const Eigen::Vector3d axis = (T.linear() * tip_in_needle).normalized();
    tumor = T * tip_in_needle + 80.0 * axis + 2.0 * axis.unitOrthogonal();
  }
  LineUncertainty line(const NeedleUncertaintySources& s) const {
    return needle_line_uncertainty(T_ct_patient, T_cam_patient, T_cam_needle, tip_in_needle,
                                   tip_in_needle, tumor, s);
  }
};

TEST(NeedleUncertainty, RegistrationErrorMovesTheLineAsAWhole) {
  const Scene scene;
  NeedleUncertaintySources s;
  s.registration_tre_mm = 1.5;
  const LineUncertainty u = scene.line(s);
  ASSERT_TRUE(u.valid);
  const double var = 1.5 * 1.5 / 3.0;
  EXPECT_NEAR(u.tumor_depth_mm, 80.0, 1e-6);
  EXPECT_TRUE(u.at_tumor.isApprox(var * Eigen::Matrix2d::Identity(), 1e-5)) << u.at_tumor;
  Eigen::Matrix4d expected;
  expected << var, 0, var, 0, 0, var, 0, var, var, 0, var, 0, 0, var, 0, var;
  EXPECT_TRUE(u.covariance.isApprox(expected, 1e-5)) << u.covariance;
  EXPECT_NEAR(u.major95_mm, std::sqrt(kChi2_95_2dof * var), 1e-5);
  EXPECT_NEAR(u.minor95_mm, std::sqrt(kChi2_95_2dof * var), 1e-5);
  // The ellipse is a circle of that radius about the nominal crossing.
  for (const auto& p : u.ellipse_at_tumor(12)) {
    EXPECT_NEAR((p - u.tumor_crossing).norm(), u.major95_mm, 1e-6);
    EXPECT_NEAR((p - u.tumor_crossing).dot(u.axis), 0.0, 1e-9);
  }
  // A line moved by the ellipse's radius across the axis lies on the 2-dof boundary; moved by
  // the 4-dof boundary's radius along e1, on the region's boundary.
  const double r4 = std::sqrt(kChi2_95_4dof * var);
  EXPECT_NEAR(u.distance2(u.tip + r4 * u.e1, u.axis), kChi2_95_4dof, 1e-3);
  EXPECT_TRUE(u.inside95(u.tip + 0.99 * r4 * u.e2, u.axis));
  EXPECT_FALSE(u.inside95(u.tip + 1.01 * r4 * u.e2, u.axis));
  EXPECT_FALSE(u.inside95(u.tip, (u.tumor_crossing + 0.5 * u.e1 - u.tip).normalized()))
      << "a tilt, which a translation cannot explain, is far outside";
}

TEST(NeedleUncertainty, TipErrorMovesTheLineAndTiltsAnAxisThatFollowsTheTip) {
  const Scene scene;
  NeedleUncertaintySources s;
  const double sigma = 0.4;
  s.tip_mm2 = sigma * sigma * Eigen::Matrix3d::Identity();
  s.axis_stddev_rad = 0;
  LineUncertainty fixed_axis = scene.line(s);
  // A spin-calibrated axis: the line moves with the tip's error across it, alike at every depth.
  EXPECT_TRUE(fixed_axis.at_tumor.isApprox(sigma * sigma * Eigen::Matrix2d::Identity(), 1e-5))
      << fixed_axis.at_tumor;
  // The axis from the board origin to the tip (150 mm): the line pivots about the origin, so an
  // error d at the tip is d (150 + 80) / 150 at the tumor.
  s.axis_from_tip = true;
  const LineUncertainty pivoting = scene.line(s);
  const double L = scene.tip_in_needle.norm(), k = (L + 80.0) / L;
  EXPECT_TRUE(pivoting.at_tumor.isApprox(k * k * sigma * sigma * Eigen::Matrix2d::Identity(), 1e-4))
      << pivoting.at_tumor;
  // No source: no spread, no lines to sample.
  const LineUncertainty exact = scene.line({});
  EXPECT_TRUE(exact.valid);
  EXPECT_NEAR(exact.major95_mm, 0.0, 1e-9);
  EXPECT_TRUE(exact.region_lines().empty());
  // The pivoting line spreads in two directions only (a rank-2 covariance): both ways along each
  // and their four diagonals, at three scales. Every line lies inside the region.
  const auto lines = pivoting.region_lines();
  EXPECT_EQ(lines.size(), 24u);
  for (const auto& [tip, axis] : lines) EXPECT_LE(pivoting.distance2(tip, axis), kChi2_95_4dof * 1.001);
}

tracking::Matrix6d board_covariance(double rot_deg, double xy_mm, double z_mm, double corr) {
  // A board seen from the front: depth known worst, rotation and depth correlated.
  const double r = rot_deg * M_PI / 180.0;
  tracking::Matrix6d c = tracking::Matrix6d::Zero();
  c.diagonal() << r * r, r * r, 0.3 * r * r, xy_mm * xy_mm, xy_mm * xy_mm, z_mm * z_mm;
  c(0, 5) = c(5, 0) = corr * r * z_mm;
  c(1, 3) = c(3, 1) = -corr * r * xy_mm;
  return c;
}

// Draws a pose error [w, t] of covariance c and applies it as the tracker's covariance says.
Eigen::Isometry3d noisy(const Eigen::Isometry3d& T, const tracking::Matrix6d& c, std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  Eigen::Matrix<double, 6, 1> z;
  for (int i = 0; i < 6; ++i) z(i) = n(rng);
  const Eigen::Matrix<double, 6, 1> d = Eigen::LLT<tracking::Matrix6d>(c).matrixL() * z;
  Eigen::Isometry3d out = T;
  out.linear() = Eigen::AngleAxisd(d.head<3>().norm(), d.head<3>().normalized()).toRotationMatrix() *
                 T.linear();
  out.translation() += d.tail<3>();
  return out;
}

// Coverage and spread of recordings of 40 frames each; tre: the registration's expected error.
void expect_coverage(double tre) {
  SCOPED_TRACE("registration TRE " + std::to_string(tre) + " mm");
  const Scene truth;
  const tracking::Matrix6d patient_cov = board_covariance(0.12, 0.05, 0.35, 0.5);
  const tracking::Matrix6d needle_cov = board_covariance(0.3, 0.1, 0.7, 0.6);
  const Eigen::Matrix3d tip_cov = Eigen::Vector3d(0.25, 0.25, 0.4).cwiseAbs2().asDiagonal();
  std::mt19937 rng(20261208);
  std::normal_distribution<double> n(0.0, 1.0);
  const Eigen::Isometry3d T_true = truth.T_ct_patient * truth.T_cam_patient.inverse() * truth.T_cam_needle;
  const Eigen::Vector3d true_tip = T_true * truth.tip_in_needle;
  const Eigen::Vector3d true_axis = (T_true.linear() * truth.tip_in_needle).normalized();
  int frames = 0, inside = 0;
  double measured2 = 0, predicted2 = 0;
  for (int recording = 0; recording < 150; ++recording) {
    // Systematic per recording: the registration and the needle's calibration.
    Scene estimate = truth;
    estimate.T_ct_patient.translation() += tre / std::sqrt(3.0) * Eigen::Vector3d(n(rng), n(rng), n(rng));
    estimate.tip_in_needle += Eigen::LLT<Eigen::Matrix3d>(tip_cov).matrixL() *
                              Eigen::Vector3d(n(rng), n(rng), n(rng));
    tracking::PoseFilter patient_filter, needle_filter;
    for (int i = 0; i < 40; ++i) {
      const int64_t t = int64_t(i) * 33'333'333;
      estimate.T_cam_patient =
          patient_filter.update(noisy(truth.T_cam_patient, patient_cov, rng), patient_cov, t, 100'000'000);
      estimate.T_cam_needle =
          needle_filter.update(noisy(truth.T_cam_needle, needle_cov, rng), needle_cov, t, 100'000'000);
      if (i < 5) continue;  // the filters settle
      NeedleUncertaintySources s;
      s.patient_pose = patient_filter.pose_covariance(patient_cov);
      s.needle_pose = needle_filter.pose_covariance(needle_cov);
      s.tip_mm2 = tip_cov;
      s.axis_from_tip = true;
      s.registration_tre_mm = tre;
      const LineUncertainty u = estimate.line(s);
      ASSERT_TRUE(u.valid);
      ++frames;
      if (u.inside95(true_tip, true_axis)) ++inside;
      // Where the true line crosses the estimate's tumor plane, against the estimate's crossing.
      const double depth = (u.tumor_crossing - true_tip).dot(u.axis) / true_axis.dot(u.axis);
      measured2 += (true_tip + depth * true_axis - u.tumor_crossing).squaredNorm();
      predicted2 += u.at_tumor.trace();
    }
  }
  const double coverage = double(inside) / frames;
  const double spread_ratio = std::sqrt(measured2 / predicted2);
  std::printf("TRE %.1f mm: coverage %.3f of %d frames; measured / predicted spread at the tumor %.3f\n",
              tre, coverage, frames, spread_ratio);
  EXPECT_GE(coverage, 0.90);
  EXPECT_LE(coverage, 0.98);
  EXPECT_NEAR(spread_ratio, 1.0, 0.3);
}

// The registration's error dominating (1.2 mm), and the tracking's (0.2 mm).
TEST(NeedleUncertainty, TrueLineIsInsideThe95PercentRegionOf90To98PercentOfFrames) {
  expect_coverage(1.2);
  expect_coverage(0.2);
}

// The mini plan (tests/support/plans.hpp): 2 mm voxels, the tumor on voxels 10..12, a vessel
// column (impassable) at i = 16, j = 9..13 along every k.
class NeedleUncertaintyPlanTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TemporaryFolder;
    const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(*dir_);
    pipelines::PlanRequest r = inputs.request((*dir_ / "plan").string());
    r.margin.fwhm_mm = 0.0;
    pipelines::run_plan(r);
    guide_ = new NeedleGuide((*dir_ / "plan").string());
  }
  static void TearDownTestSuite() {
    delete guide_;
    delete dir_;
  }
  static test::TemporaryFolder* dir_;
  static NeedleGuide* guide_;
};
test::TemporaryFolder* NeedleUncertaintyPlanTest::dir_ = nullptr;
NeedleGuide* NeedleUncertaintyPlanTest::guide_ = nullptr;

// Needles in the plane z = centre aimed at the tumor centre from tips 18 mm out on +x and y mm
// aside: they pass the vessel's side (y = +5 mm) at x = 9..11 mm. The first safe one passes just
// beside it; 1 mm farther out it is safe, and with the registration's 2 mm uncertainty (per axis)
// a line of its 95 % region crosses the vessel: UNCERTAIN, dangerous. Without noise, safe.
TEST_F(NeedleUncertaintyPlanTest, LineBesideAVesselWithTwoMillimetresUncertaintyIsUncertain) {
  const Eigen::Vector3d c = guide_->plan().tumor_centre;
  const auto tip_at = [&](double y) { return Eigen::Vector3d(c + Eigen::Vector3d(18.0, y, 0.0)); };
  double first_safe = -1;
  for (double y = 0; y <= 20; y += 0.25) {
    if (guide_->line_safety(tip_at(y), c - tip_at(y)) == NeedleSafety::kSafe) {
      first_safe = y;
      break;
    }
  }
  ASSERT_GT(first_safe, 5.0) << "lines through the vessel are dangerous";
  ASSERT_LT(first_safe, 14.0);
  const Eigen::Vector3d tip = tip_at(first_safe + 1.0);
  const Eigen::Vector3d axis = (c - tip).normalized();
  ASSERT_EQ(guide_->line_safety(tip, axis), NeedleSafety::kSafe);
  // A needle frame at the CT frame: the tip and axis as given.
  Eigen::Isometry3d T_cam = Eigen::Isometry3d::Identity();
  NeedleUncertaintySources s;
  s.registration_tre_mm = 2.0 * std::sqrt(3.0);
  const LineUncertainty u =
      needle_line_uncertainty(Eigen::Isometry3d::Identity(), T_cam, T_cam, tip, axis, c, s);
  const RegionSafety noisy = region_safety(*guide_, u, NeedleSafety::kSafe);
  EXPECT_EQ(noisy.nominal, NeedleSafety::kSafe);
  EXPECT_EQ(noisy.worst, NeedleSafety::kDangerous);
  EXPECT_TRUE(noisy.uncertain());
  EXPECT_GT(noisy.lines, 0);
  const LineUncertainty exact =
      needle_line_uncertainty(Eigen::Isometry3d::Identity(), T_cam, T_cam, tip, axis, c, {});
  const RegionSafety quiet = region_safety(*guide_, exact, NeedleSafety::kSafe);
  EXPECT_EQ(quiet.worst, NeedleSafety::kSafe);
  EXPECT_FALSE(quiet.uncertain());
  // Far from the vessel (the -x side, nothing in the way) the same uncertainty stays safe.
  const Eigen::Vector3d far_tip = c + Eigen::Vector3d(-16.0, 0.0, 0.0);
  const LineUncertainty clear = needle_line_uncertainty(
      Eigen::Isometry3d::Identity(), T_cam, T_cam, far_tip, (c - far_tip).normalized(), c, s);
  ASSERT_EQ(guide_->line_safety(far_tip, c - far_tip), NeedleSafety::kSafe);
  EXPECT_FALSE(region_safety(*guide_, clear, NeedleSafety::kSafe).uncertain());
}

}  // namespace
}  // namespace crepuscular::planning
