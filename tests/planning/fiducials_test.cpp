// Tests of planning/fiducials: beads rendered into a synthetic CT with partial volume (anisotropic,
// oblique grid, noise, bone below the threshold, a wire and an implant that must be ignored) are
// found at their true centres to a fraction of a voxel; registering them to the board layout
// recovers the known transform within 0.2 mm / 0.1 degree, also with a bead missing and an extra
// one; Slicer markups in LPS and RAS read to the same LPS points.
#include "planning/imaging/fiducials.hpp"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <random>
#include <string>
#include <vector>

#include "calibration/calibration_files.hpp"
#include "calibration/registration.hpp"
#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"
#include "planning/imaging/volume_io.hpp"

namespace crepuscular::planning {
namespace {

using test::expect_error_containing;

constexpr double kPi = 3.14159265358979323846;

// Board-frame bead layout (mm), asymmetric and not coplanar (some beads on posts).
std::vector<Eigen::Vector3d> board_layout() {
  return {{0, 0, 0}, {120, 0, 5}, {10, 85, 0}, {95, 70, 25}, {55, 30, 40}, {140, 95, 10}};
}

Eigen::Isometry3d T_ct_patient_truth() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(0.4, Eigen::Vector3d(0.2, 0.3, 1.0).normalized()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(-60.3, -48.7, 21.9);
  return T;
}

// A CT of soft tissue (40 HU, noise 15 HU) on an oblique, anisotropic grid.
Volume<int16_t> empty_ct() {
  ImageGeometry g;
  g.dims = {230, 200, 70};
  g.spacing = Eigen::Vector3d(0.85, 0.85, 1.5);
  g.direction = Eigen::AngleAxisd(8.0 * kPi / 180.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  g.origin = Eigen::Vector3d(-90.0, -80.0, -30.0);
  Volume<int16_t> ct(g, 40);
  std::mt19937 rng(3);
  std::normal_distribution<double> noise(0.0, 15.0);
  for (auto& v : ct.values()) v = int16_t(std::lround(40.0 + noise(rng)));
  return ct;
}

// Adds a ball of `value` above the background with partial volume: each voxel gets the fraction
// of its 6 x 6 x 6 sub-samples inside the ball.
void add_ball(Volume<int16_t>& ct, const Eigen::Vector3d& centre, double radius_mm, double value) {
  const ImageGeometry& g = ct.geometry();
  const Eigen::Vector3d c = g.physical_to_index(centre);
  const Eigen::Matrix3d M = g.index_to_physical_matrix();
  const int reach = int(std::ceil(radius_mm / g.spacing.minCoeff())) + 1;
  for (int64_t k = int64_t(c.z()) - reach; k <= int64_t(c.z()) + reach; ++k) {
    for (int64_t j = int64_t(c.y()) - reach; j <= int64_t(c.y()) + reach; ++j) {
      for (int64_t i = int64_t(c.x()) - reach; i <= int64_t(c.x()) + reach; ++i) {
        if (!g.contains(i, j, k)) continue;
        int inside = 0;
        for (int a = 0; a < 6; ++a) {
          for (int b = 0; b < 6; ++b) {
            for (int d = 0; d < 6; ++d) {
              const Eigen::Vector3d sub(i - 0.5 + (a + 0.5) / 6.0, j - 0.5 + (b + 0.5) / 6.0,
                                        k - 0.5 + (d + 0.5) / 6.0);
              inside += (M * (sub - c)).norm() <= radius_mm ? 1 : 0;
            }
          }
        }
        ct(i, j, k) = int16_t(std::lround(ct(i, j, k) + value * inside / 216.0));
      }
    }
  }
}

// A bone slab (below the bead threshold), a thin bright wire and a large implant (both above it).
void add_distractors(Volume<int16_t>& ct) {
  for (int64_t k = 5; k < 15; ++k) {
    for (int64_t j = 0; j < ct.dims()[1]; ++j) {
      for (int64_t i = 0; i < ct.dims()[0]; ++i) ct(i, j, k) = 1400;
    }
  }
  for (int64_t i = 20; i < 80; ++i) ct(i, 180, 60) = 3000;  // wire: 60 voxels in a row
  for (int64_t k = 55; k < 65; ++k) {
    for (int64_t j = 150; j < 170; ++j) {
      for (int64_t i = 180; i < 200; ++i) ct(i, j, k) = 3000;  // implant: 3000 voxels
    }
  }
}

TEST(Fiducials, FindsBeadsAtTheirCentresToAFractionOfAVoxel) {
  Volume<int16_t> ct = empty_ct();
  add_distractors(ct);
  const auto layout = board_layout();
  std::vector<Eigen::Vector3d> truth;
  for (const auto& p : layout) {
    truth.push_back(T_ct_patient_truth() * p);
    add_ball(ct, truth.back(), 1.5, 6000.0);  // 3 mm metal-like bead
  }
  const auto found = detect_fiducials(ct);
  ASSERT_EQ(found.size(), truth.size());
  double worst = 0;
  for (const auto& t : truth) {
    double nearest = 1e9;
    for (const auto& f : found) nearest = std::min(nearest, (f.position - t).norm());
    worst = std::max(worst, nearest);
  }
  // Voxels of 0.85 x 0.85 x 1.5 mm: a tenth of the largest spacing.
  EXPECT_LT(worst, 0.15);
  for (const auto& f : found) {
    EXPECT_NEAR(f.volume_mm3, 4.0 / 3.0 * kPi * 1.5 * 1.5 * 1.5, 8.0) << f.label;
  }
  std::printf("largest bead localisation error %.3f mm\n", worst);
}

TEST(Fiducials, SyntheticCtRegistrationRecoversTransform) {
  Volume<int16_t> ct = empty_ct();
  add_distractors(ct);
  const auto layout = board_layout();
  // Bead 2 missing from the CT (e.g. outside the scanned range); an extra bead-like spot (a clip).
  for (size_t i = 0; i < layout.size(); ++i) {
    if (i != 2) add_ball(ct, T_ct_patient_truth() * layout[i], 1.5, 6000.0);
  }
  add_ball(ct, T_ct_patient_truth() * Eigen::Vector3d(60, 120, -20), 1.5, 6000.0);
  const auto found = detect_fiducials(ct);
  ASSERT_EQ(found.size(), 6u);
  std::vector<Eigen::Vector3d> ct_points;
  for (const auto& f : found) ct_points.push_back(f.position);
  const auto r = calibration::register_fiducials(layout, ct_points);
  EXPECT_EQ(r.matched, 5);
  EXPECT_EQ(r.match[2], -1);
  EXPECT_EQ(r.unmatched_ct.size(), 1u);
  const Eigen::Isometry3d truth = T_ct_patient_truth();
  const double t_err = (r.T_ct_patient.translation() - truth.translation()).norm();
  const double r_err =
      Eigen::AngleAxisd(r.T_ct_patient.linear().transpose() * truth.linear()).angle() * 180.0 / kPi;
  EXPECT_LT(t_err, 0.2);
  EXPECT_LT(r_err, 0.1);
  // Points far from the beads (a tumor 150 mm away) land within half a millimetre as well.
  const Eigen::Vector3d tumor_board(70, 60, -150);
  EXPECT_LT((r.T_ct_patient * tumor_board - truth * tumor_board).norm(), 0.5);
  std::printf("registration from detected beads: %.3f mm, %.4f deg, FRE RMS %.3f mm\n", t_err,
              r_err, r.fre_rms_mm);
}

// `crepuscular register --ct CT.nii.gz --boards B.json` end to end: beads found in the CT file
// (read as float), paired with the board definition's fiducials, registration.yaml written.
TEST(Fiducials, RegisterCommandFindsBeadsInCtFile) {
  namespace fs = std::filesystem;
  const test::TemporaryFolder dir;
  Volume<int16_t> ct = empty_ct();
  add_distractors(ct);
  const auto layout = board_layout();
  for (const auto& p : layout) add_ball(ct, T_ct_patient_truth() * p, 1.5, 6000.0);
  write_volume(ct, (dir / "ct.nii.gz").string());
  std::ofstream(dir / "boards.json")
      << R"({"boards": [{"name": "patient", "grid": {"rows": 2, "cols": 3, "tag_size_mm": 40,
         "gap_mm": 10, "first_id": 0}, "fiducials": [)"
      << "[0,0,0],[120,0,5],[10,85,0],[95,70,25],[55,30,40],[140,95,10]]}]}";
  const std::string out = (dir / "registration.yaml").string();
  const std::string cmd = std::string(CREPUSCULAR_BINARY) + " register --ct " +
                          (dir / "ct.nii.gz").string() + " --boards " +
                          (dir / "boards.json").string() + " --save-ct-fiducials " +
                          (dir / "beads.mrk.json").string() + " --out " + out + " > " +
                          (dir / "log.txt").string() + " 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  const calibration::RegistrationRecord r = calibration::read_registration(out);
  const Eigen::Isometry3d truth = T_ct_patient_truth();
  EXPECT_LT((r.T_ct_patient.translation() - truth.translation()).norm(), 0.2);
  EXPECT_LT(Eigen::AngleAxisd(r.T_ct_patient.linear().transpose() * truth.linear()).angle() * 180.0 /
                kPi,
            0.1);
  EXPECT_EQ(r.fre_mm.size(), 6u);
  EXPECT_EQ(read_fiducial_markups((dir / "beads.mrk.json").string()).size(), 6u);
}

TEST(Fiducials, NothingAboveThresholdGivesNoBeads) {
  const Volume<int16_t> ct = empty_ct();
  EXPECT_TRUE(detect_fiducials(ct).empty());
}

class MarkupsFile : public ::testing::Test {
 protected:
  std::string write(const std::string& name, const std::string& text) {
    const std::string path = dir_.file(name);
    std::ofstream(path) << text;
    return path;
  }
  test::TemporaryFolder dir_;
};

TEST_F(MarkupsFile, RasAndLpsFilesReadToTheSameLpsPoints) {
  const std::string lps = write("lps.mrk.json", R"({"markups": [{"type": "Fiducial",
      "coordinateSystem": "LPS", "controlPoints": [
      {"label": "F-1", "position": [10.5, -20.25, 30.0]},
      {"label": "F-2", "position": [-1.0, 2.0, -3.0]}]}]})");
  const std::string ras = write("ras.mrk.json", R"({"markups": [{"type": "Fiducial",
      "coordinateSystem": "RAS", "controlPoints": [
      {"label": "F-1", "position": [-10.5, 20.25, 30.0]},
      {"label": "F-2", "position": [1.0, -2.0, -3.0]}]}]})");
  const auto a = read_fiducial_markups(lps);
  const auto b = read_fiducial_markups(ras);
  ASSERT_EQ(a.size(), 2u);
  ASSERT_EQ(b.size(), 2u);
  for (size_t i = 0; i < 2; ++i) {
    EXPECT_LT((a[i].position - b[i].position).norm(), 1e-12);
    EXPECT_EQ(a[i].label, b[i].label);
  }
  EXPECT_LT((a[0].position - Eigen::Vector3d(10.5, -20.25, 30.0)).norm(), 1e-12);
  // Round trip through our writer in RAS.
  const std::string out = (dir_ / "out.mrk.json").string();
  write_fiducial_markups(out, a, "RAS");
  const auto c = read_fiducial_markups(out);
  ASSERT_EQ(c.size(), 2u);
  EXPECT_LT((c[1].position - a[1].position).norm(), 1e-12);
}

TEST_F(MarkupsFile, BadFilesNameTheProblem) {
  expect_error_containing([&] { read_fiducial_markups((dir_ / "missing.mrk.json").string()); },
                          {"missing.mrk.json", "cannot be opened"});
  const std::string notjson = write("bad.mrk.json", "{ not json");
  expect_error_containing([&] { read_fiducial_markups(notjson); }, {"bad.mrk.json", "JSON"});
  const std::string line = write("line.mrk.json", R"({"markups": [{"type": "Line",
      "controlPoints": [{"position": [0, 0, 0]}, {"position": [1, 1, 1]}]}]})");
  expect_error_containing([&] { read_fiducial_markups(line); }, {"line.mrk.json", "Fiducial"});
  const std::string badpos = write("pos.mrk.json", R"({"markups": [{"type": "Fiducial",
      "controlPoints": [{"position": [0, "a", 0]}]}]})");
  expect_error_containing([&] { read_fiducial_markups(badpos); },
                          {"controlPoints[0].position", "three numbers"});
  const std::string badcs = write("cs.mrk.json", R"({"markups": [{"type": "Fiducial",
      "coordinateSystem": "XYZ", "controlPoints": []}]})");
  expect_error_containing([&] { read_fiducial_markups(badcs); }, {"coordinateSystem", "XYZ"});
}

}  // namespace
}  // namespace crepuscular::planning
