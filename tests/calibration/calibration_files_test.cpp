// Tests of calibration/calibration_files: needle.yaml and registration.yaml round trips, camera.yaml
// read back by CameraModel::read_yaml and by plain cv::FileStorage, errors naming file and field,
// and no temporary files left behind.
#include "calibration/calibration_files.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <iterator>
#include <string>

#include <opencv2/core.hpp>

#include "foundation/error.hpp"
#include "foundation/output_files.hpp"
#include "foundation/text.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::calibration {
namespace {

using test::expect_error_containing;

namespace fs = std::filesystem;

class CalibrationFiles : public ::testing::Test {
 protected:
  std::string path(const std::string& name) const { return dir_.file(name); }
  int file_count() const {
    int n = 0;
    for (const auto& e : fs::directory_iterator(dir_)) n += e.is_regular_file() ? 1 : 0;
    return n;
  }
  test::TemporaryFolder dir_;
};

TEST_F(CalibrationFiles, NeedleRoundTrip) {
  NeedleCalibration n;
  n.date = "2026-11-23T10:00:00Z";
  n.inputs = {"pivot.csv", "spin.csv"};
  n.board = "needle";
  n.tip_needle = Eigen::Vector3d(1.25, -0.5, 151.75);
  n.tip_stddev_mm = Eigen::Vector3d(0.1, 0.11, 0.2);
  n.pivot_rms_mm = 0.42;
  n.poses_used = 95;
  n.poses_total = 100;
  n.rotation_spread_deg = 61.5;
  n.tip_stddev_3d_mm = 0.25;
  n.pivot_cam = Eigen::Vector3d(30.5, -20.25, 500.125);
  n.pivot_rms_axis_mm = Eigen::Vector3d(0.25, 0.2, 0.27);
  n.pivot_rms_all_mm = 4.5;
  n.least_axis_tilt_deg = 21.5;
  n.outlier_frames = {17, 503, 3000000000LL};
  n.axis_needle = Eigen::Vector3d(0.01, -0.02, 1.0).normalized();
  n.axis_rms_deg = 0.3;
  n.tip_to_axis_mm = 0.2;
  write_needle_calibration(path("needle.yaml"), n);
  EXPECT_EQ(file_count(), 1);
  const NeedleCalibration r = read_needle_calibration(path("needle.yaml"));
  EXPECT_EQ(r.date, n.date);
  EXPECT_EQ(r.inputs, n.inputs);
  EXPECT_EQ(r.board, "needle");
  EXPECT_LT((r.tip_needle - n.tip_needle).norm(), 1e-12);
  EXPECT_LT((r.tip_stddev_mm - n.tip_stddev_mm).norm(), 1e-12);
  EXPECT_DOUBLE_EQ(r.pivot_rms_mm, 0.42);
  EXPECT_EQ(r.poses_used, 95);
  EXPECT_EQ(r.poses_total, 100);
  EXPECT_DOUBLE_EQ(r.tip_stddev_3d_mm, 0.25);
  EXPECT_LT((r.pivot_cam - n.pivot_cam).norm(), 1e-12);
  EXPECT_LT((r.pivot_rms_axis_mm - n.pivot_rms_axis_mm).norm(), 1e-12);
  EXPECT_DOUBLE_EQ(r.pivot_rms_all_mm, 4.5);
  EXPECT_DOUBLE_EQ(r.least_axis_tilt_deg, 21.5);
  EXPECT_EQ(r.outlier_frames, n.outlier_frames);
  ASSERT_TRUE(r.axis_needle.has_value());
  EXPECT_LT((*r.axis_needle - *n.axis_needle).norm(), 1e-12);
  // Without spin calibration there is no axis.
  n.axis_needle.reset();
  write_needle_calibration(path("needle2.yaml"), n);
  EXPECT_FALSE(read_needle_calibration(path("needle2.yaml")).axis_needle.has_value());
}

// needle.yaml as written before the tip's 3D uncertainty, the pivot point, the per-axis residuals
// and the outliers were recorded: still read, those fields zero and empty. A count of outliers
// that disagrees with the frames listed is refused by name.
TEST_F(CalibrationFiles, NeedleFileWithoutTheNewFieldsStillReads) {
  std::ofstream(path("old.yaml")) << R"(%YAML:1.0
---
calibration_date: "2026-11-24T07:48:33Z"
board: needle
inputs:
   - pivot.csv
tip_needle: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 1.5, -2., 150.25 ]
tip_stddev_mm: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0.1, 0.2, 0.3 ]
pivot_rms_mm: 0.5
poses_used: 90
poses_total: 100
rotation_spread_deg: 60.
)";
  const NeedleCalibration r = read_needle_calibration(path("old.yaml"));
  EXPECT_LT((r.tip_needle - Eigen::Vector3d(1.5, -2.0, 150.25)).norm(), 1e-12);
  EXPECT_LT((r.tip_stddev_mm - Eigen::Vector3d(0.1, 0.2, 0.3)).norm(), 1e-12);
  EXPECT_DOUBLE_EQ(r.pivot_rms_mm, 0.5);
  EXPECT_EQ(r.poses_used, 90);
  EXPECT_EQ(r.tip_stddev_3d_mm, 0.0);
  EXPECT_EQ(r.pivot_cam, Eigen::Vector3d::Zero());
  EXPECT_EQ(r.pivot_rms_axis_mm, Eigen::Vector3d::Zero());
  EXPECT_EQ(r.pivot_rms_all_mm, 0.0);
  EXPECT_EQ(r.least_axis_tilt_deg, 0.0);
  EXPECT_TRUE(r.outlier_frames.empty());
  EXPECT_FALSE(r.axis_needle.has_value());

  std::ofstream(path("mismatch.yaml")) << R"(%YAML:1.0
---
tip_needle: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0., 0., 150. ]
outliers: 3
outlier_frames: [ 4, 9 ]
)";
  expect_error_containing([&] { read_needle_calibration(path("mismatch.yaml")); },
                          {"mismatch.yaml", "'outliers' is 3", "lists 2"});
  std::ofstream(path("negative.yaml")) << R"(%YAML:1.0
---
tip_needle: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0., 0., 150. ]
outlier_frames: [ 4, -9 ]
)";
  expect_error_containing([&] { read_needle_calibration(path("negative.yaml")); },
                          {"negative.yaml", "'outlier_frames' holds -9", "whole numbers"});
}

TEST_F(CalibrationFiles, RegistrationRoundTrip) {
  RegistrationRecord rec;
  rec.date = utc_timestamp();
  rec.inputs = {"ct.nii.gz", "boards.json"};
  rec.board = "patient";
  rec.T_ct_patient.linear() =
      Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  rec.T_ct_patient.translation() = Eigen::Vector3d(-10, 20.5, 300);
  rec.board_fiducials = {{0, 0, 0}, {100, 0, 0}, {0, 80, 10}};
  rec.ct_fiducials = {rec.T_ct_patient * rec.board_fiducials[0],
                      rec.T_ct_patient * rec.board_fiducials[1],
                      rec.T_ct_patient * rec.board_fiducials[2]};
  rec.fre_mm = {0.1, 0.2, 0.15};
  rec.fre_rms_mm = 0.155;
  rec.fle_mm = 0.27;
  rec.fiducials_in_board = 4;
  rec.fiducials_in_ct = 3;
  rec.target_ct = Eigen::Vector3d(1, 2, 3);
  rec.expected_tre_mm = 0.8;
  write_registration(path("registration.yaml"), rec);
  const RegistrationRecord r = read_registration(path("registration.yaml"));
  EXPECT_EQ(r.date, rec.date);
  EXPECT_EQ(r.inputs, rec.inputs);
  EXPECT_LT((r.T_ct_patient.matrix() - rec.T_ct_patient.matrix()).cwiseAbs().maxCoeff(), 1e-12);
  ASSERT_EQ(r.ct_fiducials.size(), 3u);
  EXPECT_LT((r.ct_fiducials[2] - rec.ct_fiducials[2]).norm(), 1e-12);
  EXPECT_EQ(r.fre_mm, rec.fre_mm);
  EXPECT_EQ(r.fiducials_in_board, 4);
  ASSERT_TRUE(r.target_ct.has_value());
  EXPECT_DOUBLE_EQ(r.expected_tre_mm, 0.8);
  EXPECT_EQ(file_count(), 1);
}

TEST_F(CalibrationFiles, CameraFileReadsAsCameraModelAndOpenCv) {
  IntrinsicsResult r;
  r.camera.width = 1280;
  r.camera.height = 720;
  r.camera.fx = 910.5;
  r.camera.fy = 905.25;
  r.camera.cx = 652.0;
  r.camera.cy = 351.5;
  r.camera.distortion = {-0.2, 0.09, 0.001, -0.0009, -0.01};
  r.stddev = {0.8, 0.8, 0.5, 0.5, 0.001, 0.002, 0.0001, 0.0001, 0.003};
  r.rms_px = 0.28;
  r.views_used = 2;
  r.views = {ViewReport{"a.png", 70, 0.27, 20.0, false, Eigen::Isometry3d::Identity()},
             ViewReport{"b.png", 70, 3.1, 35.0, true, Eigen::Isometry3d::Identity()}};
  write_camera_calibration(path("camera.yaml"), r, "chessboard:9x6:25", {"shots/*.png"});
  const CameraModel cam = CameraModel::read_yaml(path("camera.yaml"));
  EXPECT_EQ(cam.width, 1280);
  EXPECT_EQ(cam.height, 720);
  EXPECT_DOUBLE_EQ(cam.fx, 910.5);
  EXPECT_DOUBLE_EQ(cam.cy, 351.5);
  for (size_t k = 0; k < 5; ++k) EXPECT_DOUBLE_EQ(cam.distortion[k], r.camera.distortion[k]);
  cv::FileStorage in(path("camera.yaml"), cv::FileStorage::READ);
  cv::Mat K;
  in["camera_matrix"] >> K;
  EXPECT_DOUBLE_EQ(K.at<double>(1, 1), 905.25);
  EXPECT_DOUBLE_EQ(double(in["rms_reprojection_error_px"]), 0.28);
  EXPECT_DOUBLE_EQ(double(in["parameter_stddev"]["fx"]), 0.8);
  EXPECT_EQ(int(in["views"][1]["rejected"]), 1);
  EXPECT_FALSE(std::string(in["calibration_date"]).empty());
}

TEST_F(CalibrationFiles, ErrorsNameFileAndField) {
  expect_error_containing([&] { read_needle_calibration(path("none.yaml")); },
                          {"none.yaml", "cannot be opened"});
  std::ofstream(path("empty.yaml")) << "%YAML:1.0\n---\nboard: needle\n";
  expect_error_containing([&] { read_needle_calibration(path("empty.yaml")); },
                          {"empty.yaml", "tip_needle", "missing"});
  std::ofstream(path("bad.yaml")) << "%YAML:1.0\n---\ntip_needle: [1, 2]\n";
  expect_error_containing([&] { read_needle_calibration(path("bad.yaml")); },
                          {"bad.yaml", "tip_needle", "3 x 1"});
  std::ofstream(path("reg.yaml"))
      << "%YAML:1.0\n---\nT_ct_patient: !!opencv-matrix\n   rows: 4\n   cols: 4\n   dt: d\n"
         "   data: [ 2., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1. ]\n";
  expect_error_containing([&] { read_registration(path("reg.yaml")); },
                          {"reg.yaml", "T_ct_patient", "rigid"});
  expect_error_containing(
      [&] { write_needle_calibration(path("no/such/folder/needle.yaml"), NeedleCalibration{}); },
      {"needle.yaml", "cannot be written"});
}

// 100 000 nested brackets (100 kB) overflowed the stack in cv::FileStorage: SIGSEGV. Refused from
// the text, for camera, needle and registration files alike.
TEST_F(CalibrationFiles, DeeplyNestedYamlIsRefusedNotACrash) {
  const std::string bomb = "%YAML:1.0\n---\ntip_needle: " + std::string(100000, '[') + "\n";
  std::ofstream(path("bomb.yaml")) << bomb;
  expect_error_containing([&] { CameraModel::read_yaml(path("bomb.yaml")); },
                          {"bomb.yaml", "nest deeper than 64"});
  expect_error_containing([&] { read_needle_calibration(path("bomb.yaml")); },
                          {"bomb.yaml", "nest deeper"});
  expect_error_containing([&] { read_registration(path("bomb.yaml")); }, {"bomb.yaml", "nest deeper"});
  // Brackets inside quotes do not count, nor do a few levels of real nesting.
  std::ofstream(path("quoted.yaml")) << "%YAML:1.0\n---\nnote: \"" + std::string(200, '[') +
                                            "\"\ntip_needle: [[1, 2, 3]]\n";
  EXPECT_NO_THROW(check_nesting_depth(path("quoted.yaml"), read_text_or_empty(path("quoted.yaml"))));
}

// camera.yaml with an integer matrix type: OpenCV would saturate fx = 800 to 255 (dt: u) and the
// camera would be used; refused. A NaN focal length is refused too.
TEST_F(CalibrationFiles, CameraMatrixOfIntegersOrNanIsRefused) {
  const auto camera_yaml = [&](const std::string& dt, const std::string& fx) {
    return "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
           "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: " + dt +
           "\n   data: [ " + fx + ", 0, 320, 0, 800, 240, 0, 0, 1 ]\n"
           "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
           "   data: [ 0., 0., 0., 0., 0. ]\n";
  };
  std::ofstream(path("u.yaml")) << camera_yaml("u", "800");
  expect_error_containing([&] { CameraModel::read_yaml(path("u.yaml")); },
                          {"u.yaml", "camera_matrix", "integer element type"});
  std::ofstream(path("nan.yaml")) << camera_yaml("d", ".nan");
  expect_error_containing([&] { CameraModel::read_yaml(path("nan.yaml")); },
                          {"nan.yaml", "camera_matrix", "finite"});
  std::ofstream(path("good.yaml")) << camera_yaml("d", "800.");
  EXPECT_DOUBLE_EQ(CameraModel::read_yaml(path("good.yaml")).fx, 800.0);
}

// A registration written inside a staged folder (the demo's setup/) names its inputs where they
// will be, never under the staging folder ".NAME.partial-PID".
TEST_F(CalibrationFiles, RegistrationInAStagedFolderNamesFinalPaths) {
  StagedDirectory demo(path("demo"));
  fs::create_directories(demo.file("setup"));
  RegistrationRecord rec;
  rec.date = "2026-11-23T10:00:00Z";
  rec.inputs = {demo.file("phantom/ct.nii.gz"), demo.file("recording_scene/boards.json")};
  rec.board = "patient";
  rec.board_fiducials = {{0, 0, 0}, {100, 0, 0}, {0, 80, 10}};
  rec.ct_fiducials = rec.board_fiducials;
  rec.fre_mm = {0, 0, 0};
  rec.fiducials_in_board = rec.fiducials_in_ct = 3;
  write_registration(demo.file("setup/registration.yaml"), rec);
  demo.commit();
  std::ifstream in(path("demo/setup/registration.yaml"));
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EXPECT_EQ(text.find(".partial-"), std::string::npos) << text;
  EXPECT_EQ(read_registration(path("demo/setup/registration.yaml")).inputs.at(0),
            path("demo/phantom/ct.nii.gz"));
}

}  // namespace
}  // namespace crepuscular::calibration
