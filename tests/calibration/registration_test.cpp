// Tests of calibration/registration: exact recovery of a known rigid transform, agreement of the
// closed form with Eigen::umeyama, correspondence search through shuffled, missing and extra CT
// fiducials, refusal of mirrored, collinear and symmetric configurations, and Fitzpatrick's TRE
// checked against a Monte Carlo simulation of localisation noise.
#include "calibration/registration.hpp"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include "calibration/calibration_files.hpp"
#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::calibration {
namespace {

using test::expect_error_containing;

constexpr double kPi = 3.14159265358979323846;

// An asymmetric layout of 6 beads on a board, some on posts (not coplanar), board frame mm.
std::vector<Eigen::Vector3d> board_layout() {
  return {{0, 0, 0},      {120, 0, 5},   {10, 85, 0},
          {95, 70, 25},   {55, 30, 40},  {140, 95, 10}};
}

Eigen::Isometry3d known_transform() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(0.7, Eigen::Vector3d(0.3, -1.0, 0.4).normalized()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(-35.0, 120.0, -260.0);
  return T;
}

std::vector<Eigen::Vector3d> transformed(const std::vector<Eigen::Vector3d>& p,
                                         const Eigen::Isometry3d& T, double noise_mm,
                                         unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> n(0.0, noise_mm);
  std::vector<Eigen::Vector3d> out;
  for (const auto& x : p) out.push_back(T * x + Eigen::Vector3d(n(rng), n(rng), n(rng)));
  return out;
}

double rotation_error_deg(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b) {
  return Eigen::AngleAxisd(a.linear().transpose() * b.linear()).angle() * 180.0 / kPi;
}

TEST(Registration, ExactPairsGiveExactTransform) {
  const auto board = board_layout();
  const auto ct = transformed(board, known_transform(), 0.0, 1);
  const RegistrationResult r = register_paired_points(board, ct);
  EXPECT_LT((r.T_ct_patient.translation() - known_transform().translation()).norm(), 1e-9);
  EXPECT_LT(rotation_error_deg(r.T_ct_patient, known_transform()), 1e-7);
  EXPECT_LT(r.fre_rms_mm, 1e-9);
}

TEST(Registration, ClosedFormAgreesWithEigenUmeyama) {
  const auto board = board_layout();
  const auto ct = transformed(board, known_transform(), 0.3, 2);
  const Eigen::Isometry3d T = rigid_fit_closed_form(board, ct);
  Eigen::Matrix3Xd src(3, board.size()), dst(3, board.size());
  for (size_t i = 0; i < board.size(); ++i) {
    src.col(Eigen::Index(i)) = board[i];
    dst.col(Eigen::Index(i)) = ct[i];
  }
  const Eigen::Matrix4d U = Eigen::umeyama(src, dst, false);
  EXPECT_LT((T.matrix() - U).cwiseAbs().maxCoeff(), 1e-9);
}

TEST(Registration, FindsCorrespondenceOfShuffledFiducials) {
  const auto board = board_layout();
  auto ct = transformed(board, known_transform(), 0.1, 3);
  const std::vector<int> order = {4, 2, 5, 0, 3, 1};  // ct_shuffled[k] = ct[order[k]]
  std::vector<Eigen::Vector3d> shuffled;
  for (int k : order) shuffled.push_back(ct[size_t(k)]);
  const RegistrationResult r = register_fiducials(board, shuffled);
  ASSERT_EQ(r.matched, 6);
  for (size_t i = 0; i < board.size(); ++i) {
    EXPECT_EQ(order[size_t(r.match[i])], int(i)) << "board fiducial " << i;
  }
  EXPECT_LT((r.T_ct_patient.translation() - known_transform().translation()).norm(), 0.2);
  EXPECT_LT(rotation_error_deg(r.T_ct_patient, known_transform()), 0.1);
  EXPECT_TRUE(r.unmatched_ct.empty());
  // FRE of 0.1 mm noise per axis: about 0.1 * sqrt(3 (1 - 2/6)) = 0.14 mm RMS.
  EXPECT_LT(r.fre_rms_mm, 0.3);
}

TEST(Registration, HandlesMissingAndExtraFiducials) {
  const auto board = board_layout();
  auto ct = transformed(board, known_transform(), 0.1, 4);
  ct.erase(ct.begin() + 3);                                          // bead 3 not found in the CT
  ct.push_back(known_transform() * Eigen::Vector3d(60, -40, 15));    // a calcification
  ct.push_back(known_transform() * Eigen::Vector3d(200, 150, -30));  // a clip
  std::reverse(ct.begin(), ct.end());
  const RegistrationResult r = register_fiducials(board, ct);
  EXPECT_EQ(r.matched, 5);
  EXPECT_EQ(r.match[3], -1);
  EXPECT_DOUBLE_EQ(r.fre_mm[3], -1.0);
  EXPECT_EQ(r.unmatched_ct.size(), 2u);
  EXPECT_LT((r.T_ct_patient.translation() - known_transform().translation()).norm(), 0.2);
  EXPECT_LT(rotation_error_deg(r.T_ct_patient, known_transform()), 0.1);
}

TEST(Registration, RefusesMirroredConfiguration) {
  const auto board = board_layout();
  auto ct = transformed(board, known_transform(), 0.1, 5);
  for (auto& p : ct) p.x() = -p.x();  // e.g. RAS read as LPS along one axis
  expect_error_containing([&] { register_fiducials(board, ct); }, {"mirror image", "LPS vs RAS"});
  expect_error_containing([&] { rigid_fit_closed_form(board, ct); }, {"mirror image"});
}

TEST(Registration, RefusesCollinearFiducials) {
  const std::vector<Eigen::Vector3d> line = {{0, 0, 0}, {40, 0, 0}, {100, 0, 0}, {170, 0, 0}};
  const auto ct = transformed(line, known_transform(), 0.0, 6);
  expect_error_containing([&] { register_paired_points(line, ct); }, {"collinear"});
  expect_error_containing([&] { register_fiducials(line, ct); }, {"could be paired"});
}

TEST(Registration, RefusesSymmetricLayout) {
  // A rectangle: turning it by 180 degrees maps it onto itself.
  const std::vector<Eigen::Vector3d> rect = {{0, 0, 0}, {100, 0, 0}, {100, 60, 0}, {0, 60, 0}};
  const auto ct = transformed(rect, known_transform(), 0.0, 7);
  expect_error_containing([&] { register_fiducials(rect, ct); }, {"symmetric"});
}

TEST(Registration, RefusesUnrelatedPoints) {
  const auto board = board_layout();
  const std::vector<Eigen::Vector3d> ct = {{0, 0, 0}, {7, 0, 0}, {0, 9, 0}, {3, 3, 300}};
  expect_error_containing([&] { register_fiducials(board, ct); }, {"could be paired", "6"});
}

// Fitzpatrick's TRE against a Monte Carlo simulation: isotropic FLE, many registrations.
TEST(Registration, ExpectedTreMatchesMonteCarlo) {
  const auto board = board_layout();
  const Eigen::Isometry3d T = known_transform();
  const Eigen::Vector3d target_board(70, 200, -120);  // off the board, like a tumor
  const Eigen::Vector3d target_ct = T * target_board;
  const double fle = 0.5;
  std::vector<Eigen::Vector3d> ct_exact = transformed(board, T, 0.0, 0);
  const double predicted = expected_tre_mm(ct_exact, target_ct, fle);
  std::mt19937 rng(8);
  std::normal_distribution<double> n(0.0, fle / std::sqrt(3.0));  // FLE is the 3D RMS
  double sum_tre2 = 0, sum_fle_est2 = 0;
  const int trials = 2000;
  for (int t = 0; t < trials; ++t) {
    std::vector<Eigen::Vector3d> a, b;
    for (size_t i = 0; i < board.size(); ++i) {
      a.push_back(board[i] + Eigen::Vector3d(n(rng), n(rng), n(rng)));
      b.push_back(ct_exact[i] + Eigen::Vector3d(n(rng), n(rng), n(rng)));
    }
    const Eigen::Isometry3d fit = rigid_fit_closed_form(a, b);
    sum_tre2 += (fit * target_board - target_ct).squaredNorm();
    double fre2 = 0;
    for (size_t i = 0; i < a.size(); ++i) fre2 += (fit * a[i] - b[i]).squaredNorm();
    sum_fle_est2 += fre2 / double(a.size()) * double(a.size()) / double(a.size() - 2);
  }
  // Noise on both sides: the effective FLE is sqrt(2) x fle.
  const double simulated = std::sqrt(sum_tre2 / trials);
  const double predicted_both = expected_tre_mm(ct_exact, target_ct, std::sqrt(2.0) * fle);
  EXPECT_NEAR(simulated, predicted_both, 0.1 * predicted_both);
  EXPECT_NEAR(std::sqrt(sum_fle_est2 / trials), std::sqrt(2.0) * fle, 0.05 * fle);
  EXPECT_GT(predicted, 0.0);
  // TRE grows with the distance from the fiducials' centroid.
  EXPECT_LT(expected_tre_mm(ct_exact, T * Eigen::Vector3d(70, 50, 10), fle), predicted);
  std::printf("TRE at target: Fitzpatrick %.3f mm, Monte Carlo %.3f mm\n", predicted_both,
              simulated);
}

// `crepuscular register --ct-fiducials F.mrk.json --boards B.json --target ...` end to end: CT
// fiducials in RAS, shuffled, one missing and one extra; a mirrored set is refused.
TEST(Registration, RegisterCommandWritesRegistrationFile) {
  namespace fs = std::filesystem;
  const test::TemporaryFolder dir;
  const auto board = board_layout();
  std::ofstream(dir / "boards.json")
      << R"({"boards": [{"name": "patient", "grid": {"rows": 2, "cols": 3, "tag_size_mm": 40,
         "gap_mm": 10, "first_id": 0}, "fiducials": [)"
      << "[0,0,0],[120,0,5],[10,85,0],[95,70,25],[55,30,40],[140,95,10]]}]}";
  auto write_markups = [&](const std::string& name, bool mirrored) {
    auto ct = transformed(board, known_transform(), 0.1, 30);
    ct.erase(ct.begin() + 1);
    ct.push_back(known_transform() * Eigen::Vector3d(-40, 60, 20));
    std::reverse(ct.begin(), ct.end());
    std::ofstream out(dir / name);
    out << R"({"markups": [{"type": "Fiducial", "coordinateSystem": "RAS", "controlPoints": [)";
    for (size_t i = 0; i < ct.size(); ++i) {
      const Eigen::Vector3d p = ct[i];
      const double x = mirrored ? p.x() : -p.x();  // RAS: -x, -y of LPS
      out << (i ? "," : "") << "{\"label\": \"F-" << i << "\", \"position\": [" << x << ","
          << -p.y() << "," << p.z() << "]}";
    }
    out << "]}]}";
  };
  write_markups("ct.mrk.json", false);
  write_markups("mirrored.mrk.json", true);
  const Eigen::Vector3d target = known_transform() * Eigen::Vector3d(70, 40, -120);
  const std::string out = (dir / "registration.yaml").string();
  auto command = [&](const std::string& markups, const std::string& result) {
    return std::string(CREPUSCULAR_BINARY) + " register --ct ct.nii.gz --boards " +
           (dir / "boards.json").string() + " --ct-fiducials " + (dir / markups).string() +
           " --target=" + std::to_string(target.x()) + "," + std::to_string(target.y()) + "," +
           std::to_string(target.z()) + " --out " + result + " > " + (dir / "log.txt").string() +
           " 2>&1";
  };
  ASSERT_EQ(std::system(command("ct.mrk.json", out).c_str()), 0);
  const RegistrationRecord r = read_registration(out);
  EXPECT_LT((r.T_ct_patient.translation() - known_transform().translation()).norm(), 0.2);
  EXPECT_LT(rotation_error_deg(r.T_ct_patient, known_transform()), 0.1);
  EXPECT_EQ(r.fre_mm.size(), 5u);
  EXPECT_EQ(r.fiducials_in_board, 6);
  EXPECT_EQ(r.fiducials_in_ct, 6);
  ASSERT_TRUE(r.target_ct.has_value());
  EXPECT_GT(r.expected_tre_mm, 0.0);
  EXPECT_LT(r.expected_tre_mm, 1.0);
  const std::string out2 = (dir / "mirrored.yaml").string();
  EXPECT_NE(std::system(command("mirrored.mrk.json", out2).c_str()), 0);
  EXPECT_FALSE(fs::exists(out2));
}

}  // namespace
}  // namespace crepuscular::calibration
