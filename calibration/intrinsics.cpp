// Camera intrinsic calibration: Zhang start (cv::initCameraMatrix2D + planar PnP), Ceres bundle
// adjustment with a Huber loss, outlier view rejection and covariance (see intrinsics.hpp).
#include "calibration/intrinsics.hpp"

#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <Eigen/SVD>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <memory>
#include <numeric>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "foundation/error.hpp"
#include "foundation/log.hpp"

namespace crepuscular::calibration {
namespace {

constexpr double kPi = 3.14159265358979323846;

// Reprojection of one target corner through CameraModel::project_generic. Parameters:
// intrinsics fx fy cx cy and the five distortion entries of `model`; pose = angle-axis (3) +
// translation (3), T_cam_target.
struct ReprojectionCost {
  ReprojectionCost(DistortionModel model, const Eigen::Vector3d& object,
                   const Eigen::Vector2d& observed)
      : model_(model), object_(object), observed_(observed) {}

  template <typename T>
  bool operator()(const T* intrinsics, const T* pose, T* residual) const {
    const T point[3] = {T(object_.x()), T(object_.y()), T(object_.z())};
    T p[3];
    ceres::AngleAxisRotatePoint(pose, point, p);
    p[0] += pose[3];
    p[1] += pose[4];
    p[2] += pose[5];
    if (!(p[2] > T(1e-9))) return false;  // behind the camera: reject the step
    T pixel[2];
    CameraModel::project_generic(model_, intrinsics, intrinsics + 4, p, pixel);
    residual[0] = pixel[0] - T(observed_.x());
    residual[1] = pixel[1] - T(observed_.y());
    return true;
  }

  static ceres::CostFunction* Create(DistortionModel model, const Eigen::Vector3d& object,
                                     const Eigen::Vector2d& observed) {
    return new ceres::AutoDiffCostFunction<ReprojectionCost, 2, 9, 6>(
        new ReprojectionCost(model, object, observed));
  }

  DistortionModel model_;
  Eigen::Vector3d object_;
  Eigen::Vector2d observed_;
};

double view_rms(DistortionModel model, const CalibrationView& view, const double* intrinsics,
                const double* pose) {
  if (view.object_points.empty()) return 0.0;
  double sum = 0;
  for (size_t i = 0; i < view.object_points.size(); ++i) {
    ReprojectionCost cost(model, view.object_points[i], view.image_points[i]);
    double r[2];
    if (!cost(intrinsics, pose, r)) return std::numeric_limits<double>::infinity();
    sum += r[0] * r[0] + r[1] * r[1];
  }
  return std::sqrt(sum / double(view.object_points.size()));
}

Eigen::Isometry3d pose_to_isometry(const double* pose) {
  Eigen::Vector3d aa(pose[0], pose[1], pose[2]);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  const double angle = aa.norm();
  if (angle > 0) T.linear() = Eigen::AngleAxisd(angle, aa / angle).toRotationMatrix();
  T.translation() = Eigen::Vector3d(pose[3], pose[4], pose[5]);
  return T;
}

Eigen::Vector3d target_normal(const double* pose) { return pose_to_isometry(pose).linear().col(2); }

double angle_deg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  // Normals of a plane: n and -n are the same orientation.
  const double c = std::min(1.0, std::abs(a.normalized().dot(b.normalized())));
  return std::acos(c) * 180.0 / kPi;
}

// Names the empty parts of a 3 x 3 division of the image.
std::string empty_regions(const std::vector<CalibrationView>& views, int width, int height) {
  static const char* kNames[3][3] = {{"top-left", "top", "top-right"},
                                     {"left", "centre", "right"},
                                     {"bottom-left", "bottom", "bottom-right"}};
  bool filled[3][3] = {};
  for (const auto& v : views) {
    for (const auto& p : v.image_points) {
      const int c = std::clamp(int(p.x() / width * 3), 0, 2);
      const int r = std::clamp(int(p.y() / height * 3), 0, 2);
      filled[r][c] = true;
    }
  }
  std::string out;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      if (filled[r][c]) continue;
      if (!out.empty()) out += ", ";
      out += kNames[r][c];
    }
  }
  return out;
}

bool collinear(const std::vector<Eigen::Vector3d>& points) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& p : points) mean += p;
  mean /= double(points.size());
  Eigen::MatrixXd A(points.size(), 3);
  for (size_t i = 0; i < points.size(); ++i)
    A.row(Eigen::Index(i)) = (points[i] - mean).transpose();
  Eigen::JacobiSVD<Eigen::MatrixXd> svd(A);
  const auto s = svd.singularValues();
  return s(0) <= 0 || s(1) < 1e-3 * s(0);
}

}  // namespace

const std::vector<std::string>& intrinsic_parameter_names(DistortionModel model) {
  static const std::vector<std::string> brown = {"fx", "fy", "cx", "cy", "k1",
                                                 "k2", "p1", "p2", "k3"};
  static const std::vector<std::string> equidistant = {"fx", "fy", "cx", "cy",
                                                       "k1", "k2", "k3", "k4"};
  return model == DistortionModel::equidistant ? equidistant : brown;
}

double corner_coverage(const std::vector<CalibrationView>& views, int width, int height,
                       int cells) {
  std::vector<char> filled(size_t(cells * cells), 0);
  for (const auto& v : views) {
    for (const auto& p : v.image_points) {
      const int c = std::clamp(int(p.x() / width * cells), 0, cells - 1);
      const int r = std::clamp(int(p.y() / height * cells), 0, cells - 1);
      filled[size_t(r * cells + c)] = 1;
    }
  }
  return double(std::count(filled.begin(), filled.end(), 1)) / double(cells * cells);
}

std::vector<size_t> select_views_for_coverage(const std::vector<CalibrationView>& views, int width,
                                              int height, size_t max_views) {
  constexpr int kCells = 10;
  auto cells_of = [&](const CalibrationView& v) {
    std::vector<int> cells;
    for (const auto& p : v.image_points) {
      const int c = std::clamp(int(p.x() / width * kCells), 0, kCells - 1);
      const int r = std::clamp(int(p.y() / height * kCells), 0, kCells - 1);
      cells.push_back(r * kCells + c);
    }
    std::sort(cells.begin(), cells.end());
    cells.erase(std::unique(cells.begin(), cells.end()), cells.end());
    return cells;
  };
  std::vector<std::vector<int>> view_cells;
  for (const auto& v : views) view_cells.push_back(cells_of(v));
  std::vector<char> covered(kCells * kCells, 0);
  std::vector<char> taken(views.size(), 0);
  std::vector<size_t> picked;
  while (picked.size() < max_views) {
    size_t best = views.size();
    int best_gain = 0;
    for (size_t i = 0; i < views.size(); ++i) {
      if (taken[i] || views[i].image_points.empty()) continue;
      int gain = 0;
      for (int c : view_cells[i]) gain += covered[size_t(c)] ? 0 : 1;
      if (gain > best_gain) {
        best_gain = gain;
        best = i;
      }
    }
    if (best == views.size()) break;
    taken[best] = 1;
    picked.push_back(best);
    for (int c : view_cells[best]) covered[size_t(c)] = 1;
  }
  // Fill up with evenly spaced views (different moments usually mean different poses).
  std::vector<size_t> rest;
  for (size_t i = 0; i < views.size(); ++i) {
    if (!taken[i] && !views[i].image_points.empty()) rest.push_back(i);
  }
  const size_t want = std::min(max_views - picked.size(), rest.size());
  for (size_t k = 0; k < want; ++k) {
    picked.push_back(rest[(k * rest.size()) / want]);
  }
  std::sort(picked.begin(), picked.end());
  return picked;
}

namespace {

using Pose = std::array<double, 6>;  // angle-axis (3) + translation (3), T_cam_target

// Checks every view and names it in result->views; the indices of the usable ones (enough
// points, not collinear), whose point counts result->views records.
std::vector<size_t> usable_views(const std::vector<CalibrationView>& views,
                                 const IntrinsicsOptions& options, IntrinsicsResult* result) {
  result->views.resize(views.size());
  std::vector<size_t> usable;
  for (size_t i = 0; i < views.size(); ++i) {
    const CalibrationView& v = views[i];
    result->views[i].name = v.name;
    if (v.object_points.size() != v.image_points.size()) {
      throw Error("camera calibration: view " + v.name + " has " +
                  std::to_string(v.object_points.size()) + " target points but " +
                  std::to_string(v.image_points.size()) + " image points (expected equal counts)");
    }
    double extent = 0;
    for (const auto& p : v.object_points) extent = std::max(extent, p.head<2>().norm());
    for (const auto& p : v.object_points) {
      if (std::abs(p.z()) > 1e-6 * std::max(1.0, extent)) {
        throw Error("camera calibration: view " + v.name +
                    ": target points must lie in the plane z = 0 of the target (found z = " +
                    std::to_string(p.z()) + " mm)");
      }
    }
    if (int(v.object_points.size()) < options.min_points_per_view) continue;
    if (collinear(v.object_points)) continue;
    usable.push_back(i);
    result->views[i].points = int(v.object_points.size());
  }
  return usable;
}

// Refusals with advice on what to capture: too few usable views, corners covering too little of
// the image, views all in nearly the same orientation.
void check_view_count(int n_usable, size_t n_views, const IntrinsicsOptions& options) {
  if (n_usable >= options.min_views) return;
  std::ostringstream msg;
  msg << "camera calibration: only " << n_usable << " usable view(s) of the target out of "
      << n_views << " (at least " << options.min_views << " needed, 15-25 recommended). Capture "
      << (options.min_views - n_usable)
      << " or more further views with the whole target visible, tilted by 20-45 degrees in "
         "different directions and placed near every corner of the image.";
  throw Error(msg.str());
}

void check_coverage(double coverage, const std::vector<CalibrationView>& used_views, int width,
                    int height, const IntrinsicsOptions& options) {
  if (!(coverage < options.min_coverage)) return;
  std::ostringstream msg;
  msg.precision(0);
  msg << std::fixed << "camera calibration: the target's corners cover only " << 100.0 * coverage
      << "% of the image (of a 4 x 4 division; at least " << 100.0 * options.min_coverage
      << "% needed to determine the distortion). Capture views with the target near the "
         "empty parts of the image: "
      << empty_regions(used_views, width, height) << ".";
  throw Error(msg.str());
}

void check_tilt_spread(double spread_deg, size_t n_views, const IntrinsicsOptions& options) {
  if (!(spread_deg < options.min_tilt_spread_deg)) return;
  std::ostringstream msg;
  msg.precision(1);
  msg << std::fixed << "camera calibration: all " << n_views
      << " views show the target in nearly the same orientation (largest angle between two "
         "views "
      << spread_deg << " degrees, at least " << options.min_tilt_spread_deg
      << " needed; fronto-parallel views cannot separate the focal length from the distance). "
         "Capture views with the target tilted by 20-45 degrees to the left, right, up and "
         "down.";
  throw Error(msg.str());
}

// The views' points as OpenCV takes them (float, target plane z = 0).
struct OpenCvViews {
  std::vector<std::vector<cv::Point3f>> object;
  std::vector<std::vector<cv::Point2f>> image;
};

OpenCvViews opencv_views(const std::vector<CalibrationView>& views) {
  OpenCvViews out;
  for (const auto& v : views) {
    std::vector<cv::Point3f> o;
    std::vector<cv::Point2f> m;
    for (size_t k = 0; k < v.object_points.size(); ++k) {
      o.emplace_back(float(v.object_points[k].x()), float(v.object_points[k].y()), 0.f);
      m.emplace_back(float(v.image_points[k].x()), float(v.image_points[k].y()));
    }
    out.object.push_back(std::move(o));
    out.image.push_back(std::move(m));
  }
  return out;
}

// Zhang start: the focal length from the homographies with the principal point at the centre
// (the larger image side when that fails or gives an implausible value).
double initial_focal_length(const OpenCvViews& cv_views, int width, int height) {
  double f0 = std::max(width, height);
  try {
    const cv::Mat K =
        cv::initCameraMatrix2D(cv_views.object, cv_views.image, cv::Size(width, height), 1.0);
    const double f = K.at<double>(0, 0);
    if (std::isfinite(f) && f > 0.1 * f0 && f < 20.0 * f0) f0 = f;
  } catch (const cv::Exception& e) {
    spdlog::debug("camera calibration: initCameraMatrix2D failed ({}); starting from f = {}",
                  e.what(), f0);
  }
  return f0;
}

// Every view's pose by planar PnP (IPPE; the iterative method where IPPE fails).
std::vector<Pose> planar_poses(const OpenCvViews& cv_views, const cv::Matx33d& K) {
  std::vector<Pose> poses(cv_views.object.size());
  for (size_t i = 0; i < poses.size(); ++i) {
    cv::Vec3d rvec, tvec;
    bool ok = false;
    try {
      ok = cv::solvePnP(cv_views.object[i], cv_views.image[i], K, cv::noArray(), rvec, tvec, false,
                        cv::SOLVEPNP_IPPE);
    } catch (const cv::Exception&) {
      ok = false;
    }
    if (!ok) {
      cv::solvePnP(cv_views.object[i], cv_views.image[i], K, cv::noArray(), rvec, tvec, false,
                   cv::SOLVEPNP_ITERATIVE);
    }
    poses[i] = {rvec[0], rvec[1], rvec[2], tvec[0], tvec[1], tvec[2]};
  }
  return poses;
}

// Every view's pose by planar PnP (IPPE) on its corners unprojected through `camera` (corners
// that the camera cannot unproject are left out; a view with fewer than four left keeps a pose
// 1 m straight ahead).
std::vector<Pose> unprojected_poses(const std::vector<CalibrationView>& views,
                                    const CameraModel& camera) {
  std::vector<Pose> poses(views.size());
  for (size_t i = 0; i < views.size(); ++i) {
    std::vector<cv::Point3d> object;
    std::vector<cv::Point2d> normalised;
    for (size_t k = 0; k < views[i].object_points.size(); ++k) {
      const Eigen::Vector2d xy = camera.unproject(views[i].image_points[k]);
      if (!xy.allFinite()) continue;
      object.emplace_back(views[i].object_points[k].x(), views[i].object_points[k].y(), 0.0);
      normalised.emplace_back(xy.x(), xy.y());
    }
    cv::Vec3d rvec(0, 0, 0), tvec(0, 0, 1000.0);
    if (object.size() >= 4) {
      try {
        cv::solvePnP(object, normalised, cv::Matx33d::eye(), cv::noArray(), rvec, tvec, false,
                     cv::SOLVEPNP_IPPE);
      } catch (const cv::Exception&) {
        rvec = cv::Vec3d(0, 0, 0);
        tvec = cv::Vec3d(0, 0, 1000.0);
      }
    }
    poses[i] = {rvec[0], rvec[1], rvec[2], tvec[0], tvec[1], tvec[2]};
  }
  return poses;
}

// Equidistant start, as cv::fisheye::calibrate begins: k1..k4 = 0, the principal point at the
// image centre; of the focal lengths from the homographies and max(width, height) / pi (a 180
// degree lens filling the image), the one whose poses reproject the corners best.
std::vector<Pose> equidistant_start(const std::vector<CalibrationView>& views,
                                    const OpenCvViews& cv_views, int width, int height,
                                    double* intr) {
  const double zhang = initial_focal_length(cv_views, width, height);
  const double fill = std::max(width, height) / kPi;
  double best_cost = std::numeric_limits<double>::infinity();
  std::vector<Pose> best_poses;
  double best_f = fill;
  for (double f : {zhang, fill, 0.5 * (zhang + fill), 1.5 * fill}) {
    CameraModel cam;
    cam.model = DistortionModel::equidistant;
    cam.width = width;
    cam.height = height;
    cam.fx = cam.fy = f;
    cam.cx = 0.5 * (width - 1);
    cam.cy = 0.5 * (height - 1);
    std::vector<Pose> poses = unprojected_poses(views, cam);
    const double trial[9] = {f, f, cam.cx, cam.cy, 0, 0, 0, 0, 0};
    std::vector<double> rms;
    for (size_t i = 0; i < views.size(); ++i) {
      rms.push_back(view_rms(DistortionModel::equidistant, views[i], trial, poses[i].data()));
    }
    std::nth_element(rms.begin(), rms.begin() + long(rms.size() / 2), rms.end());
    const double cost = rms[rms.size() / 2];
    spdlog::debug("camera calibration: fisheye start f = {:.1f} px: median view RMS {:.2f} px", f,
                  cost);
    if (cost < best_cost) {
      best_cost = cost;
      best_poses = std::move(poses);
      best_f = f;
    }
  }
  intr[0] = intr[1] = best_f;
  return best_poses;
}

// Largest angle (degrees) between the target normals of two of the `active` views.
double tilt_spread(const std::vector<Pose>& poses, const std::vector<size_t>& active) {
  double spread = 0;
  for (size_t a = 0; a < active.size(); ++a) {
    for (size_t b = a + 1; b < active.size(); ++b) {
      spread = std::max(spread, angle_deg(target_normal(poses[active[a]].data()),
                                          target_normal(poses[active[b]].data())));
    }
  }
  return spread;
}

// The orientation spread seen through a nominal camera (f = the larger image side, principal
// point cx, cy): nearly parallel views stay nearly parallel for any focal length, whereas the
// homography start is meaningless for them.
double nominal_tilt_spread(const OpenCvViews& cv_views, int width, int height, double cx,
                           double cy) {
  const double nominal = std::max(width, height);
  const cv::Matx33d Kn(nominal, 0, cx, 0, nominal, cy, 0, 0, 1);
  std::vector<Pose> poses(cv_views.object.size());
  for (size_t i = 0; i < poses.size(); ++i) {
    cv::Vec3d rvec, tvec;
    cv::solvePnP(cv_views.object[i], cv_views.image[i], Kn, cv::noArray(), rvec, tvec, false,
                 cv::SOLVEPNP_IPPE);
    poses[i] = {rvec[0], rvec[1], rvec[2], tvec[0], tvec[1], tvec[2]};
  }
  std::vector<size_t> all(poses.size());
  std::iota(all.begin(), all.end(), 0);
  return tilt_spread(poses, all);
}

// The bundle adjustment's outcome: the last problem solved (for the covariance), its summary,
// the views kept and those rejected as outliers.
struct Adjustment {
  std::unique_ptr<ceres::Problem> problem;
  ceres::Solver::Summary summary;
  std::vector<size_t> active;
  std::vector<char> rejected;
};

// Bundle adjustment of intrinsics and poses with a Huber loss; views whose RMS is far above the
// median are dropped and the problem is solved again (at most 6 rounds).
Adjustment bundle_adjust(const std::vector<CalibrationView>& used_views, double* intr,
                         std::vector<Pose>& poses, const IntrinsicsOptions& options) {
  const DistortionModel model = options.model;
  Adjustment out;
  out.active.resize(used_views.size());
  std::iota(out.active.begin(), out.active.end(), 0);
  out.rejected.assign(used_views.size(), 0);
  for (int round = 0; round < 6; ++round) {
    ceres::Problem::Options problem_options;
    out.problem = std::make_unique<ceres::Problem>(problem_options);
    out.problem->AddParameterBlock(intr, 9);
    for (size_t i : out.active) {
      const auto& v = used_views[i];
      for (size_t k = 0; k < v.object_points.size(); ++k) {
        out.problem->AddResidualBlock(
            ReprojectionCost::Create(model, v.object_points[k], v.image_points[k]),
            new ceres::HuberLoss(options.huber_px), intr, poses[i].data());
      }
    }
    if (options.fix_k3 || model == DistortionModel::equidistant) {
      intr[8] = 0;
      out.problem->SetManifold(intr, new ceres::SubsetManifold(9, {8}));
    }
    ceres::Solver::Options solver_options;
    solver_options.linear_solver_type = ceres::DENSE_SCHUR;
    solver_options.max_num_iterations = options.max_iterations;
    solver_options.function_tolerance = 1e-12;
    solver_options.parameter_tolerance = 1e-12;
    solver_options.num_threads = 2;
    ceres::Solve(solver_options, out.problem.get(), &out.summary);
    spdlog::debug("camera calibration, round {}: {}", round + 1, out.summary.BriefReport());
    if (!out.summary.IsSolutionUsable()) {
      throw Error("camera calibration: the bundle adjustment failed (" + out.summary.BriefReport() +
                  "). Capture more views with the target tilted in different directions.");
    }
    std::vector<double> rms;
    for (size_t i : out.active) {
      rms.push_back(view_rms(model, used_views[i], intr, poses[i].data()));
    }
    std::vector<double> sorted = rms;
    std::nth_element(sorted.begin(), sorted.begin() + long(sorted.size() / 2), sorted.end());
    const double median = sorted[sorted.size() / 2];
    const double limit =
        std::max(options.outlier_view_factor * median, options.outlier_view_min_px);
    std::vector<size_t> keep;
    for (size_t a = 0; a < out.active.size(); ++a) {
      if (rms[a] > limit) {
        out.rejected[out.active[a]] = 1;
        spdlog::info("camera calibration: view {} rejected (RMS {:.3f} px > {:.3f} px)",
                     used_views[out.active[a]].name, rms[a], limit);
      } else {
        keep.push_back(out.active[a]);
      }
    }
    if (keep.size() == out.active.size()) break;
    if (int(keep.size()) < options.min_views) {
      throw Error("camera calibration: after rejecting views with large reprojection errors only " +
                  std::to_string(keep.size()) + " remain (at least " +
                  std::to_string(options.min_views) +
                  " needed). Check the target definition (size, spacing) and capture sharper "
                  "views without motion blur.");
    }
    out.active = keep;
  }
  return out;
}

// Standard deviations of the nine intrinsics: the covariance of the solved problem scaled by the
// residual variance sigma2 (0 for the fixed last entry: k3 kept at 0, or an equidistant lens).
std::array<double, 9> intrinsic_stddev(ceres::Problem& problem, double* intr, double sigma2,
                                       bool fix_last) {
  ceres::Covariance::Options cov_options;
  cov_options.algorithm_type = ceres::DENSE_SVD;
  cov_options.null_space_rank = 0;
  cov_options.num_threads = 2;
  ceres::Covariance covariance(cov_options);
  std::vector<std::pair<const double*, const double*>> blocks = {{intr, intr}};
  if (!covariance.Compute(blocks, &problem)) {
    throw Error(
        "camera calibration: the views do not determine all camera parameters (the covariance is "
        "rank deficient): the target's orientation varies too little between views, or its "
        "corners leave much of the image empty. Capture views with the target tilted by 20-45 "
        "degrees to the left, right, up and down, and near the image corners.");
  }
  double cov[81];
  covariance.GetCovarianceBlockInTangentSpace(intr, intr, cov);
  // In the tangent space of a SubsetManifold, the fixed last entry is left out.
  const int dim = fix_last ? 8 : 9;
  std::array<double, 9> stddev{};
  for (int p = 0; p < 9; ++p) {
    stddev[size_t(p)] = p < dim ? std::sqrt(std::max(0.0, cov[p * dim + p] * sigma2)) : 0.0;
  }
  return stddev;
}

// Refuses focal lengths determined to worse than 2 % (advice on what to capture).
void check_focal_lengths(const IntrinsicsResult& result, const double* intr) {
  for (int p : {0, 1}) {
    const double rel = result.stddev[size_t(p)] / intr[p];
    if (!(rel < 0.02)) {
      std::ostringstream msg;
      msg.precision(2);
      msg << std::fixed << "camera calibration: " << intrinsic_parameter_names()[size_t(p)].c_str()
          << " is poorly determined (standard deviation " << 100.0 * rel
          << "% of its value, at most 2% accepted). Capture more views with the target tilted "
             "by 20-45 degrees and filling more of the image.";
      throw Error(msg.str());
    }
  }
}

}  // namespace

IntrinsicsResult calibrate_intrinsics(const std::vector<CalibrationView>& views, int width,
                                      int height, const IntrinsicsOptions& options) {
  if (width <= 0 || height <= 0) {
    throw Error("camera calibration: image size " + std::to_string(width) + " x " +
                std::to_string(height) + " is not positive");
  }
  if (options.fix_k3 && options.model == DistortionModel::equidistant) {
    throw Error(
        "camera calibration: fix_k3 (--fix-k3) keeps the Brown-Conrady k3 at 0; a fisheye "
        "(equidistant) lens has k1..k4 and no k3 to keep. Leave out --fix-k3 or calibrate "
        "with --lens pinhole.");
  }
  IntrinsicsResult result;
  const std::vector<size_t> usable = usable_views(views, options, &result);
  check_view_count(int(usable.size()), views.size(), options);
  std::vector<CalibrationView> used_views;
  for (size_t i : usable) used_views.push_back(views[i]);
  result.coverage = corner_coverage(used_views, width, height);
  check_coverage(result.coverage, used_views, width, height, options);

  // Zhang start: focal length from the homographies, then every view's pose by planar PnP.
  const OpenCvViews cv_views = opencv_views(used_views);
  const DistortionModel model = options.model;
  const bool fix_last = options.fix_k3 || model == DistortionModel::equidistant;
  double intr[9] = {0, 0, 0.5 * (width - 1), 0.5 * (height - 1), 0, 0, 0, 0, 0};
  std::vector<Pose> poses;
  if (model == DistortionModel::equidistant) {
    poses = equidistant_start(used_views, cv_views, width, height, intr);
    // A fisheye's start poses come through its own (undistorting) start camera.
    std::vector<size_t> all(poses.size());
    std::iota(all.begin(), all.end(), 0);
    result.tilt_spread_deg = tilt_spread(poses, all);
  } else {
    intr[0] = intr[1] = initial_focal_length(cv_views, width, height);
    poses = planar_poses(cv_views, cv::Matx33d(intr[0], 0, intr[2], 0, intr[1], intr[3], 0, 0, 1));
    result.tilt_spread_deg = nominal_tilt_spread(cv_views, width, height, intr[2], intr[3]);
  }
  check_tilt_spread(result.tilt_spread_deg, used_views.size(), options);

  Adjustment adjusted = bundle_adjust(used_views, intr, poses, options);
  const std::vector<size_t>& active = adjusted.active;

  // Residual variance and covariance of the intrinsics.
  double sum_sq = 0;
  int n_points = 0;
  for (size_t i : active) {
    const double r = view_rms(model, used_views[i], intr, poses[i].data());
    sum_sq += r * r * double(used_views[i].object_points.size());
    n_points += int(used_views[i].object_points.size());
  }
  const int n_params = (fix_last ? 8 : 9) + 6 * int(active.size());
  const int dof = 2 * n_points - n_params;
  const double sigma2 = dof > 0 ? sum_sq / double(dof) : 0.0;
  result.stddev = intrinsic_stddev(*adjusted.problem, intr, sigma2, fix_last);

  result.camera.model = model;
  result.camera.width = width;
  result.camera.height = height;
  result.camera.fx = intr[0];
  result.camera.fy = intr[1];
  result.camera.cx = intr[2];
  result.camera.cy = intr[3];
  result.camera.distortion = {intr[4], intr[5], intr[6], intr[7], intr[8]};
  result.rms_px = n_points > 0 ? std::sqrt(sum_sq / n_points) : 0.0;
  result.views_used = int(active.size());
  result.points_used = n_points;
  result.tilt_spread_deg = tilt_spread(poses, active);
  result.solver_report = adjusted.summary.BriefReport();
  for (size_t u = 0; u < usable.size(); ++u) {
    ViewReport& report = result.views[usable[u]];
    report.rms_px = view_rms(model, used_views[u], intr, poses[u].data());
    report.rejected = adjusted.rejected[u] != 0;
    report.T_cam_target = pose_to_isometry(poses[u].data());
    report.tilt_deg = angle_deg(report.T_cam_target.linear().col(2), Eigen::Vector3d::UnitZ());
  }
  check_focal_lengths(result, intr);
  spdlog::info(
      "camera calibration: RMS {:.3f} px over {} views ({} points), fx {:.2f} +- {:.2f}, "
      "fy {:.2f} +- {:.2f}",
      result.rms_px, result.views_used, n_points, intr[0], result.stddev[0], intr[1],
      result.stddev[1]);
  return result;
}

std::optional<ChessboardSpec> parse_chessboard_spec(const std::string& text) {
  const std::string prefix = "chessboard:";
  if (text.rfind(prefix, 0) != 0) return std::nullopt;
  const std::string rest = text.substr(prefix.size());
  ChessboardSpec spec;
  char x = 0, colon = 0;
  std::istringstream in(rest);
  in >> spec.cols >> x >> spec.rows >> colon >> spec.square_mm;
  if (in.fail() || (x != 'x' && x != 'X') || colon != ':' || !(in >> std::ws).eof() ||
      spec.cols < 2 || spec.rows < 2 || !(spec.square_mm > 0)) {
    throw Error("board \"" + text +
                "\": expected chessboard:COLSxROWS:SQUARE_MM with inner corners counted as OpenCV "
                "does, e.g. chessboard:9x6:25 for a board of 10 x 7 squares of 25 mm");
  }
  return spec;
}

std::optional<CalibrationView> detect_chessboard(const cv::Mat& image, const ChessboardSpec& spec,
                                                 const std::string& name) {
  if (image.empty()) return std::nullopt;
  cv::Mat gray;
  if (image.channels() == 3) {
    cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  } else if (image.channels() == 4) {
    cv::cvtColor(image, gray, cv::COLOR_BGRA2GRAY);
  } else {
    gray = image;
  }
  if (gray.depth() != CV_8U) gray.convertTo(gray, CV_8U);
  std::vector<cv::Point2f> corners;
  const cv::Size pattern(spec.cols, spec.rows);
  if (!cv::findChessboardCorners(gray, pattern, corners,
                                 cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE)) {
    return std::nullopt;
  }
  // Refinement window: under half the smallest corner spacing, at most 11 x 11.
  double spacing = 1e9;
  for (int r = 0; r < spec.rows; ++r) {
    for (int c = 0; c + 1 < spec.cols; ++c) {
      spacing = std::min(spacing, double(cv::norm(corners[size_t(r * spec.cols + c + 1)] -
                                                  corners[size_t(r * spec.cols + c)])));
    }
  }
  const int half = std::clamp(int(spacing * 0.4), 2, 5);
  cv::cornerSubPix(gray, corners, cv::Size(half, half), cv::Size(-1, -1),
                   cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 40, 0.001));
  CalibrationView view;
  view.name = name;
  for (int r = 0; r < spec.rows; ++r) {
    for (int c = 0; c < spec.cols; ++c) {
      view.object_points.emplace_back(c * spec.square_mm, r * spec.square_mm, 0.0);
      const cv::Point2f& p = corners[size_t(r * spec.cols + c)];
      view.image_points.emplace_back(p.x, p.y);
    }
  }
  return view;
}

}  // namespace crepuscular::calibration
