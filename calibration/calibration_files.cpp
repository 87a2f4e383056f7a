// camera.yaml, needle.yaml and registration.yaml through OpenCV FileStorage (see
// calibration_files.hpp).
#include "calibration/calibration_files.hpp"

#include <fmt/format.h>

#include <cmath>
#include <cstdint>
#include <opencv2/core.hpp>

#include "foundation/error.hpp"
#include "foundation/output_files.hpp"
#include "foundation/text.hpp"

namespace crepuscular::calibration {
namespace {

void write_strings(cv::FileStorage& out, const std::string& key,
                   const std::vector<std::string>& values) {
  out << key << "[";
  for (const auto& v : values) out << final_path_of(v);  // never a staging folder's path
  out << "]";
}

cv::Mat to_mat(const Eigen::Vector3d& v) { return (cv::Mat_<double>(3, 1) << v.x(), v.y(), v.z()); }

cv::Mat to_mat(const Eigen::Isometry3d& T) {
  cv::Mat m(4, 4, CV_64F);
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) m.at<double>(r, c) = T.matrix()(r, c);
  }
  return m;
}

cv::Mat points_mat(const std::vector<Eigen::Vector3d>& p) {
  cv::Mat m(int(p.size()), 3, CV_64F);
  for (size_t i = 0; i < p.size(); ++i) {
    for (int c = 0; c < 3; ++c) m.at<double>(int(i), c) = p[i](c);
  }
  return m;
}

class Reader {
 public:
  explicit Reader(const std::string& path) : path_(path) { open_file_storage(in_, path); }
  cv::FileNode node(const std::string& key, bool required = true) const {
    cv::FileNode n = in_[key];
    if (required && n.empty()) throw Error(path_ + ": field '" + key + "' is missing");
    return n;
  }
  bool has(const std::string& key) const { return !in_[key].empty(); }
  double number(const std::string& key) const {
    const cv::FileNode n = node(key);
    if (!n.isReal() && !n.isInt()) throw Error(path_ + ": field '" + key + "' must be a number");
    const double v = double(n);
    if (!std::isfinite(v)) throw Error(path_ + ": field '" + key + "' is not finite");
    return v;
  }
  int count(const std::string& key) const {
    const double v = has(key) ? number(key) : 0.0;
    if (!(v >= 0 && v <= 1e9) || v != std::floor(v)) {
      throw Error(path_ + ": field '" + key + "' must be a whole number from 0 to 1e9");
    }
    return int(v);
  }
  std::string text(const std::string& key) const {
    const cv::FileNode n = node(key, false);
    return n.isString() ? std::string(n) : std::string();
  }
  std::vector<std::string> strings(const std::string& key) const {
    std::vector<std::string> out;
    const cv::FileNode n = node(key, false);
    if (n.isSeq()) {
      for (const auto& item : n) out.push_back(std::string(item));
    }
    return out;
  }
  // A sequence of frame numbers (whole numbers from 0 to 2^53); empty when the field is missing.
  std::vector<int64_t> frame_numbers(const std::string& key) const {
    std::vector<int64_t> out;
    if (!has(key)) return out;
    const cv::FileNode n = node(key);
    if (!n.isSeq())
      throw Error(path_ + ": field '" + key + "' must be a sequence of frame numbers");
    for (const auto& item : n) {
      const bool numeric = item.isInt() || item.isReal();
      const double v = numeric ? double(item) : -1.0;
      if (!(v >= 0 && v <= 9007199254740992.0) || v != std::floor(v)) {
        throw Error(
            path_ + ": field '" + key + "' holds " +
            (numeric ? fmt::format("{}", v) : std::string("an entry that is not a number")) +
            " (frame numbers are whole numbers from 0)");
      }
      out.push_back(int64_t(v));
    }
    return out;
  }
  cv::Mat matrix(const std::string& key, int rows, int cols) const {
    const std::string shape = (rows >= 0 ? std::to_string(rows) : std::string("N")) + " x " +
                              std::to_string(cols) + " opencv-matrix of doubles";
    const cv::FileNode n = node(key);
    if (!n.isMap()) throw Error(path_ + ": field '" + key + "' must be a " + shape);
    const cv::Mat m = read_opencv_matrix(n, path_, "'" + key + "'");
    if ((rows >= 0 && m.rows != rows) || m.cols != cols || m.type() != CV_64F) {
      throw Error(path_ + ": field '" + key + "' must be a " +
                  (rows >= 0 ? std::to_string(rows) : std::string("N")) + " x " +
                  std::to_string(cols) + " opencv-matrix of doubles");
    }
    for (int r = 0; r < m.rows; ++r) {
      for (int c = 0; c < m.cols; ++c) {
        if (!std::isfinite(m.at<double>(r, c))) {
          throw Error(path_ + ": field '" + key + "' holds a value that is not finite");
        }
      }
    }
    return m;
  }
  Eigen::Vector3d vector3(const std::string& key) const {
    const cv::Mat m = matrix(key, 3, 1);
    return Eigen::Vector3d(m.at<double>(0), m.at<double>(1), m.at<double>(2));
  }
  std::vector<Eigen::Vector3d> points(const std::string& key) const {
    std::vector<Eigen::Vector3d> out;
    if (!has(key)) return out;
    const cv::Mat m = matrix(key, -1, 3);
    for (int r = 0; r < m.rows; ++r) {
      out.emplace_back(m.at<double>(r, 0), m.at<double>(r, 1), m.at<double>(r, 2));
    }
    return out;
  }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
  cv::FileStorage in_;
};

}  // namespace

std::string utc_timestamp() { return utc_now_iso8601(); }

void write_camera_calibration(const std::string& path, const IntrinsicsResult& result,
                              const std::string& board, const std::vector<std::string>& inputs) {
  const CameraModel& cam = result.camera;
  write_file_storage(path, [&](cv::FileStorage& out) {
    out << "calibration_date" << utc_timestamp();
    out << "board" << board;
    write_strings(out, "inputs", inputs);
    out << "image_width" << cam.width;
    out << "image_height" << cam.height;
    out << "camera_matrix" << cam.camera_matrix();
    out << "distortion_coefficients" << cam.distortion_coefficients();
    out << "distortion_model" << distortion_model_name(cam.model);
    out << "rms_reprojection_error_px" << result.rms_px;
    out << "views_used" << result.views_used;
    out << "points_used" << result.points_used;
    out << "corner_coverage" << result.coverage;
    out << "tilt_spread_deg" << result.tilt_spread_deg;
    out << "parameter_stddev" << "{";
    const auto& names = intrinsic_parameter_names(cam.model);
    for (size_t p = 0; p < names.size(); ++p) out << names[p] << result.stddev[p];
    out << "}";
    out << "views" << "[";
    for (const auto& v : result.views) {
      out << "{" << "name" << v.name << "points" << v.points << "rms_px" << v.rms_px << "tilt_deg"
          << v.tilt_deg << "rejected" << int(v.rejected) << "}";
    }
    out << "]";
  });
}

void write_needle_calibration(const std::string& path, const NeedleCalibration& n) {
  write_file_storage(path, [&](cv::FileStorage& out) {
    out << "calibration_date" << n.date;
    out << "board" << n.board;
    write_strings(out, "inputs", n.inputs);
    out << "tip_needle" << to_mat(n.tip_needle);
    out << "tip_stddev_mm" << to_mat(n.tip_stddev_mm);
    out << "tip_stddev_3d_mm" << n.tip_stddev_3d_mm;
    out << "pivot_cam" << to_mat(n.pivot_cam);
    out << "pivot_rms_mm" << n.pivot_rms_mm;
    out << "pivot_rms_axis_mm" << to_mat(n.pivot_rms_axis_mm);
    out << "pivot_rms_all_mm" << n.pivot_rms_all_mm;
    out << "poses_used" << n.poses_used;
    out << "poses_total" << n.poses_total;
    out << "rotation_spread_deg" << n.rotation_spread_deg;
    out << "least_axis_tilt_deg" << n.least_axis_tilt_deg;
    out << "outliers" << int(n.outlier_frames.size());
    out << "outlier_frames"
        << "[:";
    for (int64_t f : n.outlier_frames) {
      // FileStorage has no 64-bit integers; frame numbers beyond 2^31 are written as doubles.
      if (f >= 0 && f <= INT32_MAX) {
        out << int(f);
      } else {
        out << double(f);
      }
    }
    out << "]";
    if (n.axis_needle) {
      out << "axis_needle" << to_mat(*n.axis_needle);
      out << "axis_rms_deg" << n.axis_rms_deg;
      out << "tip_to_axis_mm" << n.tip_to_axis_mm;
    }
  });
}

NeedleCalibration read_needle_calibration(const std::string& path) {
  const Reader in(path);
  NeedleCalibration n;
  n.date = in.text("calibration_date");
  n.board = in.text("board");
  n.inputs = in.strings("inputs");
  n.tip_needle = in.vector3("tip_needle");
  if (in.has("tip_stddev_mm")) n.tip_stddev_mm = in.vector3("tip_stddev_mm");
  n.pivot_rms_mm = in.has("pivot_rms_mm") ? in.number("pivot_rms_mm") : 0.0;
  n.poses_used = in.count("poses_used");
  n.poses_total = in.count("poses_total");
  n.rotation_spread_deg = in.has("rotation_spread_deg") ? in.number("rotation_spread_deg") : 0.0;
  // Files written before the tip's 3D uncertainty, the pivot point and the outliers were recorded
  // read with those fields zero and empty.
  n.tip_stddev_3d_mm = in.has("tip_stddev_3d_mm") ? in.number("tip_stddev_3d_mm") : 0.0;
  if (in.has("pivot_cam")) n.pivot_cam = in.vector3("pivot_cam");
  if (in.has("pivot_rms_axis_mm")) n.pivot_rms_axis_mm = in.vector3("pivot_rms_axis_mm");
  n.pivot_rms_all_mm = in.has("pivot_rms_all_mm") ? in.number("pivot_rms_all_mm") : 0.0;
  n.least_axis_tilt_deg = in.has("least_axis_tilt_deg") ? in.number("least_axis_tilt_deg") : 0.0;
  n.outlier_frames = in.frame_numbers("outlier_frames");
  if (in.has("outliers") && in.count("outliers") != int(n.outlier_frames.size())) {
    throw Error(path + ": field 'outliers' is " + std::to_string(in.count("outliers")) +
                " but 'outlier_frames' lists " + std::to_string(n.outlier_frames.size()) +
                " frames; they must agree (run `crepuscular calibrate pivot` again)");
  }
  if (in.has("axis_needle")) {
    const Eigen::Vector3d a = in.vector3("axis_needle");
    if (std::abs(a.norm() - 1.0) > 1e-3) {
      throw Error(path + ": field 'axis_needle' must be a unit vector (length " +
                  std::to_string(a.norm()) + ")");
    }
    n.axis_needle = a.normalized();
    n.axis_rms_deg = in.has("axis_rms_deg") ? in.number("axis_rms_deg") : 0.0;
    n.tip_to_axis_mm = in.has("tip_to_axis_mm") ? in.number("tip_to_axis_mm") : 0.0;
  }
  return n;
}

void write_registration(const std::string& path, const RegistrationRecord& r) {
  write_file_storage(path, [&](cv::FileStorage& out) {
    out << "registration_date" << r.date;
    out << "board" << r.board;
    write_strings(out, "inputs", r.inputs);
    out << "T_ct_patient" << to_mat(r.T_ct_patient);
    out << "coordinate_system" << "LPS";
    out << "fiducials_in_board" << r.fiducials_in_board;
    out << "fiducials_in_ct" << r.fiducials_in_ct;
    out << "fiducials_paired" << int(r.fre_mm.size());
    out << "board_fiducials" << points_mat(r.board_fiducials);
    out << "ct_fiducials" << points_mat(r.ct_fiducials);
    out << "fre_mm" << "[";
    for (double f : r.fre_mm) out << f;
    out << "]";
    out << "fre_rms_mm" << r.fre_rms_mm;
    out << "fle_estimate_mm" << r.fle_mm;
    if (r.target_ct) {
      out << "tre_target_ct" << to_mat(*r.target_ct);
      out << "expected_tre_mm" << r.expected_tre_mm;
    }
  });
}

RegistrationRecord read_registration(const std::string& path) {
  const Reader in(path);
  RegistrationRecord r;
  r.date = in.text("registration_date");
  r.board = in.text("board");
  r.inputs = in.strings("inputs");
  const std::string cs = in.text("coordinate_system");
  if (!cs.empty() && cs != "LPS") {
    throw Error(path + ": field 'coordinate_system' is \"" + cs + "\" (expected \"LPS\")");
  }
  const cv::Mat T = in.matrix("T_ct_patient", 4, 4);
  Eigen::Matrix4d M;
  for (int a = 0; a < 4; ++a) {
    for (int b = 0; b < 4; ++b) M(a, b) = T.at<double>(a, b);
  }
  const Eigen::Matrix3d R = M.topLeftCorner<3, 3>();
  if ((R.transpose() * R - Eigen::Matrix3d::Identity()).norm() > 1e-6 || R.determinant() < 0 ||
      (M.row(3) - Eigen::RowVector4d(0, 0, 0, 1)).norm() > 1e-9) {
    throw Error(path + ": field 'T_ct_patient' is not a rigid transform (expected a rotation and "
                       "a translation, last row 0 0 0 1)");
  }
  r.T_ct_patient.matrix() = M;
  r.board_fiducials = in.points("board_fiducials");
  r.ct_fiducials = in.points("ct_fiducials");
  const cv::FileNode fre = in.node("fre_mm", false);
  if (fre.isSeq()) {
    for (const auto& f : fre) r.fre_mm.push_back(double(f));
  }
  r.fre_rms_mm = in.has("fre_rms_mm") ? in.number("fre_rms_mm") : 0.0;
  r.fle_mm = in.has("fle_estimate_mm") ? in.number("fle_estimate_mm") : 0.0;
  r.fiducials_in_board = in.count("fiducials_in_board");
  r.fiducials_in_ct = in.count("fiducials_in_ct");
  if (in.has("tre_target_ct")) {
    r.target_ct = in.vector3("tre_target_ct");
    r.expected_tre_mm = in.has("expected_tre_mm") ? in.number("expected_tre_mm") : 0.0;
  }
  return r;
}

}  // namespace crepuscular::calibration
