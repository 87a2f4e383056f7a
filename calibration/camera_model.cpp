// Pinhole + Brown-Conrady or equidistant fisheye camera model, OpenCV's definitions; OpenCV
// FileStorage YAML files.
#include "calibration/camera_model.hpp"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <Eigen/LU>  // 2x2 inverse
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <sstream>
#include <thread>

#include "foundation/error.hpp"
#include "foundation/output_files.hpp"
#include "foundation/text.hpp"

namespace crepuscular::calibration {

namespace {

// Jacobian of distort() at xy (2x2), for Newton's method in unproject().
Eigen::Matrix2d distortion_jacobian(const std::array<double, 5>& d, const Eigen::Vector2d& xy) {
  const double x = xy.x(), y = xy.y();
  const double k1 = d[0], k2 = d[1], p1 = d[2], p2 = d[3], k3 = d[4];
  const double r2 = x * x + y * y;
  const double radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
  const double dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);  // d radial / d r2
  Eigen::Matrix2d j;
  j(0, 0) = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x;
  j(0, 1) = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y;
  j(1, 0) = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y;
  j(1, 1) = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x;
  return j;
}

constexpr double kHalfPi = 1.57079632679489661923;

// theta_d(theta) of the equidistant model and its derivative.
double equidistant_theta_d(const std::array<double, 5>& k, double theta) {
  const double t2 = theta * theta;
  return theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))));
}
double equidistant_slope(const std::array<double, 5>& k, double theta) {
  const double t2 = theta * theta;
  return 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
}

// The largest angle up to which theta_d grows with theta (at most 90 degrees): the first zero of
// the slope, found by a 256-step scan and bisection.
double equidistant_theta_limit(const std::array<double, 5>& k) {
  constexpr int kSteps = 256;
  double lo = 0;
  for (int i = 1; i <= kSteps; ++i) {
    const double hi = kHalfPi * i / kSteps;
    if (!(equidistant_slope(k, hi) > 0)) {
      double a = lo, b = hi;
      for (int j = 0; j < 60; ++j) {
        const double m = 0.5 * (a + b);
        (equidistant_slope(k, m) > 0 ? a : b) = m;
      }
      return a;
    }
    lo = hi;
  }
  return kHalfPi;
}

// Normalised distorted point (theta_d along the direction of the image point) -> undistorted
// normalised point; NaN where the angle would reach the limit.
Eigen::Vector2d equidistant_undistort(const std::array<double, 5>& k, const Eigen::Vector2d& d) {
  const double theta_d = d.norm();
  if (!std::isfinite(theta_d)) return Eigen::Vector2d::Constant(std::nan(""));
  if (theta_d * theta_d <= 1e-16) return d;  // project()'s scale 1 on the axis
  const double limit = equidistant_theta_limit(k);
  if (!(theta_d < equidistant_theta_d(k, limit))) return Eigen::Vector2d::Constant(std::nan(""));
  // Newton's method kept inside the bracket [lo, hi] where theta_d(theta) is increasing.
  // Starts at theta = theta_d, as cv::fisheye::undistortPoints does.
  double lo = 0, hi = limit, theta = theta_d < hi ? theta_d : 0.5 * hi;
  for (int i = 0; i < 100; ++i) {
    const double f = equidistant_theta_d(k, theta) - theta_d;
    (f > 0 ? hi : lo) = theta;
    double next = theta - f / equidistant_slope(k, theta);
    if (!(next > lo && next < hi)) next = 0.5 * (lo + hi);
    const double step = std::abs(next - theta);
    theta = next;
    if (step < 1e-16 * std::max(1.0, theta)) break;
  }
  if (!(theta < kHalfPi)) return Eigen::Vector2d::Constant(std::nan(""));
  return d * (std::tan(theta) / theta_d);
}

std::string shape_of(const cv::Mat& m) {
  std::ostringstream s;
  s << m.rows << "x" << m.cols;
  if (m.channels() != 1) s << "x" << m.channels();
  return s.str();
}

}  // namespace

const char* distortion_model_name(DistortionModel model) {
  return model == DistortionModel::equidistant ? "equidistant" : "plumb_bob";
}

DistortionModel parse_distortion_model(const std::string& name, const std::string& what) {
  if (name == "plumb_bob" || name == "brown_conrady" || name == "pinhole") {
    return DistortionModel::brown_conrady;
  }
  if (name == "equidistant" || name == "fisheye") return DistortionModel::equidistant;
  throw Error(what + ": distortion_model is \"" + name +
              "\", expected \"plumb_bob\" (Brown-Conrady k1 k2 p1 p2 k3, the default) or "
              "\"equidistant\" (fisheye k1 k2 k3 k4, OpenCV's cv::fisheye)");
}

Eigen::Vector2d CameraModel::distort(const Eigen::Vector2d& xy) const {
  const double intrinsics[4] = {1.0, 1.0, 0.0, 0.0};
  const double p[3] = {xy.x(), xy.y(), 1.0};
  Eigen::Vector2d out;
  project_generic(model, intrinsics, distortion.data(), p, out.data());
  return out;
}

Eigen::Vector2d CameraModel::normalized_to_pixel(const Eigen::Vector2d& xy) const {
  const Eigen::Vector2d d = distort(xy);
  return {fx * d.x() + cx, fy * d.y() + cy};
}

Eigen::Vector2d CameraModel::project(const Eigen::Vector3d& p_cam) const {
  const double intrinsics[4] = {fx, fy, cx, cy};
  Eigen::Vector2d pixel;
  project_generic(model, intrinsics, distortion.data(), p_cam.data(), pixel.data());
  return pixel;
}

Eigen::Vector2d CameraModel::unproject(const Eigen::Vector2d& pixel) const {
  const Eigen::Vector2d target((pixel.x() - cx) / fx, (pixel.y() - cy) / fy);
  if (model == DistortionModel::equidistant) return equidistant_undistort(distortion, target);
  const double k1 = distortion[0], k2 = distortion[1], p1 = distortion[2], p2 = distortion[3],
               k3 = distortion[4];
  if (k1 == 0 && k2 == 0 && p1 == 0 && p2 == 0 && k3 == 0) return target;

  // OpenCV's fixed-point iteration (cv::undistortPoints) as a start ...
  Eigen::Vector2d xy = target;
  for (int i = 0; i < 10; ++i) {
    const double r2 = xy.squaredNorm();
    const double icdist = 1.0 / (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)));
    if (!(icdist > 0) || !std::isfinite(icdist)) break;
    const double dx = 2.0 * p1 * xy.x() * xy.y() + p2 * (r2 + 2.0 * xy.x() * xy.x());
    const double dy = p1 * (r2 + 2.0 * xy.y() * xy.y()) + 2.0 * p2 * xy.x() * xy.y();
    const Eigen::Vector2d next((target.x() - dx) * icdist, (target.y() - dy) * icdist);
    if (!next.allFinite()) break;
    xy = next;
  }
  return unproject(pixel, xy);
}

Eigen::Vector2d CameraModel::unproject(const Eigen::Vector2d& pixel,
                                       const Eigen::Vector2d& guess) const {
  if (model == DistortionModel::equidistant) return unproject(pixel);
  const Eigen::Vector2d target((pixel.x() - cx) / fx, (pixel.y() - cy) / fy);
  Eigen::Vector2d xy = guess;
  // Newton's method on distort(xy) = target, which converges quadratically; stops when a step
  // no longer changes the point (1e-15 in normalised units, ~1e-12 px).
  for (int i = 0; i < 30; ++i) {
    const Eigen::Vector2d r = distort(xy) - target;
    const Eigen::Vector2d step = distortion_jacobian(distortion, xy).inverse() * r;
    if (!step.allFinite()) break;
    xy -= step;
    if (step.squaredNorm() < 1e-30) break;
  }
  return xy.allFinite() ? xy : guess;
}

cv::Mat CameraModel::camera_matrix() const {
  cv::Mat k = (cv::Mat_<double>(3, 3) << fx, 0, cx, 0, fy, cy, 0, 0, 1);
  return k;
}

cv::Mat CameraModel::distortion_coefficients() const {
  const int n = model == DistortionModel::equidistant ? 4 : 5;
  cv::Mat d(1, n, CV_64F);
  for (int i = 0; i < n; ++i) d.at<double>(0, i) = distortion[size_t(i)];
  return d;
}

CameraModel CameraModel::from_opencv(const cv::Mat& camera_matrix, const cv::Mat& distortion,
                                     int width, int height, const std::string& what,
                                     DistortionModel model) {
  if (camera_matrix.rows != 3 || camera_matrix.cols != 3 || camera_matrix.channels() != 1) {
    throw Error(what + ": camera_matrix is " + shape_of(camera_matrix) + ", expected 3x3");
  }
  cv::Mat k;
  camera_matrix.convertTo(k, CV_64F);
  if (std::abs(k.at<double>(0, 1)) > 1e-9 || k.at<double>(1, 0) != 0 || k.at<double>(2, 0) != 0 ||
      k.at<double>(2, 1) != 0 || std::abs(k.at<double>(2, 2) - 1.0) > 1e-12) {
    throw Error(what + ": camera_matrix must be [fx 0 cx; 0 fy cy; 0 0 1] (no skew)");
  }
  if (!cv::checkRange(k) || !(k.at<double>(0, 0) > 0) || !(k.at<double>(1, 1) > 0)) {
    throw Error(what + ": camera_matrix needs finite values and focal lengths fx, fy > 0");
  }
  CameraModel m;
  m.model = model;
  m.width = width;
  m.height = height;
  m.fx = k.at<double>(0, 0);
  m.fy = k.at<double>(1, 1);
  m.cx = k.at<double>(0, 2);
  m.cy = k.at<double>(1, 2);
  if (!distortion.empty()) {
    if (distortion.channels() != 1 || (distortion.rows != 1 && distortion.cols != 1)) {
      throw Error(what + ": distortion_coefficients is " + shape_of(distortion) +
                  ", expected a 1xN vector (k1 k2 p1 p2 k3)");
    }
    cv::Mat d;
    distortion.reshape(1, 1).convertTo(d, CV_64F);
    if (!cv::checkRange(d)) throw Error(what + ": distortion_coefficients are not all finite");
    const int n = d.cols;
    if (model == DistortionModel::equidistant && n != 4) {
      throw Error(what + ": distortion_coefficients has " + std::to_string(n) +
                  " entries, expected 4 (k1 k2 k3 k4) for distortion_model equidistant");
    }
    if (n < 4) {
      throw Error(what + ": distortion_coefficients has " + std::to_string(n) +
                  " entries, expected 4 or 5 (k1 k2 p1 p2 k3)");
    }
    for (int i = 0; i < std::min(n, 5); ++i) m.distortion[size_t(i)] = d.at<double>(0, i);
    for (int i = 5; i < n; ++i) {
      if (d.at<double>(0, i) != 0.0) {
        throw Error(what + ": distortion_coefficients entry " + std::to_string(i) + " is " +
                    std::to_string(d.at<double>(0, i)) +
                    "; only k1 k2 p1 p2 k3 are supported (the rational, thin-prism and tilted "
                    "models are not), expected 0");
      }
    }
  }
  m.validate(what);
  return m;
}

void CameraModel::validate(const std::string& what) const {
  if (width <= 0 || height <= 0) {
    throw Error(what + ": image size " + std::to_string(width) + "x" + std::to_string(height) +
                ", expected image_width and image_height > 0");
  }
  if (!(fx > 0) || !(fy > 0) || !std::isfinite(fx) || !std::isfinite(fy)) {
    throw Error(what + ": focal lengths fx=" + std::to_string(fx) + " fy=" + std::to_string(fy) +
                " in camera_matrix, expected finite values > 0");
  }
  if (!std::isfinite(cx) || !std::isfinite(cy)) {
    throw Error(what + ": principal point in camera_matrix is not finite");
  }
  for (double d : distortion) {
    if (!std::isfinite(d)) throw Error(what + ": distortion_coefficients are not finite");
  }
  if (model == DistortionModel::equidistant && distortion[4] != 0.0) {
    throw Error(what +
                ": an equidistant (fisheye) lens has four coefficients k1..k4; the fifth is " +
                std::to_string(distortion[4]) + ", expected 0");
  }
}

namespace {

int storage_format(const std::string& path) {
  const std::string ext = std::filesystem::path(path).extension().string();
  if (ext == ".xml") return cv::FileStorage::FORMAT_XML;
  if (ext == ".json") return cv::FileStorage::FORMAT_JSON;
  return cv::FileStorage::FORMAT_YAML;
}

// Parses `text` in a child process: "" when OpenCV parses it there within the deadline, else why
// not. The child leaves through _exit (no exit handlers of this process run twice).
std::string parse_in_child(const std::string& text, int flags) {
  const pid_t child = ::fork();
  if (child < 0) return {};  // no child to spare: parse here as before
  if (child == 0) {
    int code = 3;
    try {
      cv::FileStorage storage(text, flags);
      code = storage.isOpened() ? 0 : 3;
    } catch (...) {
      code = 4;
    }
    ::_exit(code);
  }
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(3);
  int status = 0;
  for (;;) {
    const pid_t done = ::waitpid(child, &status, WNOHANG);
    if (done == child) break;
    if (done < 0) return {};
    if (std::chrono::steady_clock::now() > deadline) {
      ::kill(child, SIGKILL);
      ::waitpid(child, &status, 0);
      return "the parser did not finish within 3 s on it";
    }
    std::this_thread::sleep_for(std::chrono::microseconds(200));
  }
  if (WIFSIGNALED(status))
    return "the parser failed on it (signal " + std::to_string(WTERMSIG(status)) + ")";
  if (WIFEXITED(status) && WEXITSTATUS(status) != 0) return "it cannot be parsed";
  return {};
}

}  // namespace

void open_file_storage(cv::FileStorage& storage, const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    throw Error(path + (std::filesystem::exists(path, ec) ? ": cannot be opened (not a file)"
                                                          : ": cannot be opened (not found)"));
  }
  const std::string text = read_text_or_empty(path);
  if (text.size() > (64u << 20)) throw Error(path + ": over 64 MB, not a calibration file");
  check_nesting_depth(path, text);
  const int flags = cv::FileStorage::READ | cv::FileStorage::MEMORY | storage_format(path);
  const std::string why = parse_in_child(text, flags);
  if (!why.empty()) throw Error(path + ": not a valid OpenCV FileStorage file (" + why + ")");
  try {
    if (!storage.open(text, flags)) throw Error(path + ": cannot be read as OpenCV FileStorage");
  } catch (const cv::Exception& e) {
    throw Error(path + ": not a valid OpenCV FileStorage file (" + e.err + ")");
  }
  // Fields are looked up by name: a top level that is a list or a value has none (and OpenCV
  // asserts on the lookup).
  if (!storage.root().isMap()) throw Error(path + ": expected named fields at the top of the file");
}

cv::Mat read_opencv_matrix(const cv::FileNode& node, const std::string& path,
                           const std::string& field) {
  const std::string at = path + ": field " + field;
  if (!node.isMap()) throw Error(at + " is not an OpenCV matrix (opencv-matrix)");
  const cv::FileNode rows = node["rows"], cols = node["cols"], dt = node["dt"], data = node["data"];
  if (!rows.isInt() || !cols.isInt() || !dt.isString() || !data.isSeq()) {
    throw Error(at + " needs rows, cols (integers), dt and data (a list)");
  }
  const int r = int(rows), c = int(cols);
  if (r < 0 || c < 0 || r > 100000 || c > 100000) {
    throw Error(at + ": rows and cols must be 0 to 100000");
  }
  const std::string type = std::string(dt);
  // One channel of any type (d, f, u, ...; the callers check the type), or 2-4 channels ("3d").
  const int channels = type.size() == 2 && type[0] >= '1' && type[0] <= '4' ? type[0] - '0' : 1;
  if (int64_t(data.size()) != int64_t(r) * c * channels) {
    throw Error(at + ": data holds " + std::to_string(data.size()) + " values, rows x cols is " +
                std::to_string(int64_t(r) * c * channels));
  }
  for (const auto& value : data) {
    if (!value.isInt() && !value.isReal())
      throw Error(at + ": data holds a value that is not a number");
  }
  cv::Mat m;
  try {
    node >> m;
  } catch (const cv::Exception& e) {
    throw Error(at + " is not an OpenCV matrix (" + e.err + ")");
  }
  return m;
}

CameraModel CameraModel::read_yaml(const std::string& path) {
  if (!std::filesystem::exists(path)) {
    throw Error(path +
                ": camera file not found (expected OpenCV FileStorage YAML with "
                "camera_matrix, distortion_coefficients, image_width, image_height)");
  }
  cv::FileStorage fs;
  open_file_storage(fs, path);
  const auto read_mat = [&](const char* field) {
    const cv::FileNode node = fs[field];
    if (node.empty() || node.isNone()) {
      throw Error(path + ": field " + field + " is missing (expected an OpenCV matrix)");
    }
    const cv::Mat m = read_opencv_matrix(node, path, field);
    if (m.empty())
      throw Error(path + ": field " + field + " is not an OpenCV matrix (opencv-matrix)");
    // OpenCV stores the data in the element type `dt` names and saturates them to it: with an
    // integer type an fx of 800 would be read as 255 (dt: u) or rounded. Only f or d are read.
    if (m.depth() != CV_32F && m.depth() != CV_64F) {
      throw Error(path + ": field " + field +
                  " has an integer element type (dt other than f or d), "
                  "which clips or rounds its values; write it with dt: d");
    }
    return m;
  };
  const auto read_int = [&](const char* field) {
    const cv::FileNode node = fs[field];
    if (node.empty() || node.isNone()) {
      throw Error(path + ": field " + field + " is missing (expected a positive integer)");
    }
    if (!node.isInt()) {
      throw Error(path + ": field " + field + " is not an integer (expected a positive integer)");
    }
    const int v = int(node);
    if (v <= 0) {
      throw Error(path + ": field " + field + " is " + std::to_string(v) + ", expected > 0");
    }
    return v;
  };
  DistortionModel model = DistortionModel::brown_conrady;
  const cv::FileNode model_node = fs["distortion_model"];
  if (!model_node.empty() && !model_node.isNone()) {
    if (!model_node.isString()) {
      throw Error(path +
                  ": field distortion_model is not a string (expected \"plumb_bob\" or "
                  "\"equidistant\")");
    }
    model = parse_distortion_model(std::string(model_node), path);
  }
  const cv::Mat k = read_mat("camera_matrix");
  const cv::Mat d = read_mat("distortion_coefficients");
  const int width = read_int("image_width");
  const int height = read_int("image_height");
  return from_opencv(k, d, width, height, path, model);
}

void CameraModel::write_yaml(const std::string& path) const {
  validate(path);
  write_file_storage(
      path,
      [&](cv::FileStorage& out) {
        out << "image_width" << width;
        out << "image_height" << height;
        out << "distortion_model" << distortion_model_name(model);
        out << "camera_matrix" << camera_matrix();
        out << "distortion_coefficients" << distortion_coefficients();
      },
      cv::FileStorage::FORMAT_YAML);
}

void write_file_storage(const std::string& path, const std::function<void(cv::FileStorage&)>& body,
                        int format) {
  write_file_atomically(path, [&](const std::string& temporary) {
    try {
      cv::FileStorage out(temporary, cv::FileStorage::WRITE | format);
      if (!out.isOpened()) throw Error(path + ": cannot be written (folder missing or read-only?)");
      body(out);
      out.release();
    } catch (const cv::Exception& e) {
      throw Error(path + ": cannot be written (" + e.err + ")");
    }
  });
}

}  // namespace crepuscular::calibration
