// Board pose: IPPE (or SQPnP for a non-planar board) start, Ceres refinement, covariance.
#include "tracking/pose.hpp"

#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <sstream>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>

namespace crepuscular::tracking {

namespace {

// Reprojection error of one corner. Parameters: [w (3, rotation vector, rad), t (3, mm)] of the
// pose exp(w) * R0, t; the functor holds R0 * X (the corner turned by the start rotation).
struct ReprojectionCost {
  ReprojectionCost(const calibration::CameraModel* cam, const Eigen::Vector3d& turned,
                   const Eigen::Vector2d& pixel)
      : cam(cam), turned(turned), pixel(pixel) {}

  template <typename T>
  bool operator()(const T* pose, T* residual) const {
    const T x[3] = {T(turned.x()), T(turned.y()), T(turned.z())};
    T p[3];
    ceres::AngleAxisRotatePoint(pose, x, p);
    p[0] += pose[3];
    p[1] += pose[4];
    p[2] += pose[5];
    if (!(p[2] > T(1e-6))) return false;  // behind the camera: reject the step
    T uv[2];
    project_with_distortion(*cam, p, uv);
    residual[0] = uv[0] - T(pixel.x());
    residual[1] = uv[1] - T(pixel.y());
    return true;
  }

  static ceres::CostFunction* Create(const calibration::CameraModel* cam,
                                     const Eigen::Vector3d& turned, const Eigen::Vector2d& pixel) {
    return new ceres::AutoDiffCostFunction<ReprojectionCost, 2, 6>(
        new ReprojectionCost(cam, turned, pixel));
  }

  const calibration::CameraModel* cam;
  Eigen::Vector3d turned;
  Eigen::Vector2d pixel;
};

double rms_error(const calibration::CameraModel& cam, const BoardCorners& c,
                 const Eigen::Isometry3d& T, bool* in_front) {
  double sum = 0;
  *in_front = true;
  for (size_t i = 0; i < c.board_mm.size(); ++i) {
    const Eigen::Vector3d p = T * c.board_mm[i];
    if (p.z() <= 1e-6) {
      *in_front = false;
      return std::numeric_limits<double>::infinity();
    }
    double uv[2];
    project_with_distortion(cam, p.data(), uv);
    sum += (Eigen::Vector2d(uv[0], uv[1]) - c.pixels[i]).squaredNorm();
  }
  return std::sqrt(sum / double(c.board_mm.size()));
}

struct Refined {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  double rms = std::numeric_limits<double>::infinity();
};

// Adds one residual per corner for the pose exp(w) * R0, t; returns the problem.
void add_residuals(ceres::Problem& problem, const calibration::CameraModel& cam,
                   const BoardCorners& c, const Eigen::Matrix3d& R0, double* params,
                   double huber_px) {
  for (size_t i = 0; i < c.board_mm.size(); ++i) {
    problem.AddResidualBlock(ReprojectionCost::Create(&cam, R0 * c.board_mm[i], c.pixels[i]),
                             huber_px > 0 ? new ceres::HuberLoss(huber_px) : nullptr, params);
  }
}

Refined refine(const calibration::CameraModel& cam, const BoardCorners& c,
               const Eigen::Isometry3d& start, const PoseOptions& o) {
  double params[6] = {0, 0, 0, start.translation().x(), start.translation().y(),
                      start.translation().z()};
  ceres::Problem problem;
  add_residuals(problem, cam, c, start.linear(), params, o.huber_px);
  ceres::Solver::Options so;
  so.linear_solver_type = ceres::DENSE_QR;
  so.max_num_iterations = o.max_iterations;
  so.logging_type = ceres::SILENT;
  so.num_threads = 1;
  so.function_tolerance = 1e-10;
  so.parameter_tolerance = 1e-10;
  ceres::Solver::Summary summary;
  ceres::Solve(so, &problem, &summary);
  Refined r;
  double R[9];
  ceres::AngleAxisToRotationMatrix(params, ceres::ColumnMajorAdapter3x3(R));
  r.T.linear() = Eigen::Map<Eigen::Matrix3d>(R) * start.linear();
  r.T.translation() = Eigen::Vector3d(params[3], params[4], params[5]);
  bool in_front = true;
  r.rms = rms_error(cam, c, r.T, &in_front);
  return r;
}

Eigen::Isometry3d from_cv(const cv::Mat& rvec, const cv::Mat& tvec) {
  cv::Mat R;
  cv::Rodrigues(rvec, R);
  Eigen::Matrix3d Re;
  cv::cv2eigen(R, Re);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Re;
  T.translation() = Eigen::Vector3d(tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2));
  return T;
}

double rotation_angle(const Eigen::Matrix3d& a, const Eigen::Matrix3d& b) {
  return Eigen::AngleAxisd(a.transpose() * b).angle();
}

bool is_planar(const std::vector<Eigen::Vector3d>& pts) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& p : pts) mean += p;
  mean /= double(pts.size());
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const auto& p : pts) cov += (p - mean) * (p - mean).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
  const Eigen::Vector3d ev = es.eigenvalues();  // ascending
  return ev(0) <= 1e-10 * std::max(ev(2), 1e-12);
}

}  // namespace

bool belongs_to(const Board& board, const Detection& d) {
  return (d.family.empty() || d.family == board.family) && board.find(d.id) != nullptr;
}

BoardCorners match_board_corners(const Board& board, const std::vector<Detection>& detections) {
  std::map<int, const Detection*> best;
  for (const Detection& d : detections) {
    if (!belongs_to(board, d)) continue;
    auto it = best.find(d.id);
    if (it == best.end() || it->second->decision_margin < d.decision_margin) best[d.id] = &d;
  }
  BoardCorners c;
  for (const auto& [id, det] : best) {
    const BoardTag* tag = board.find(id);
    for (int k = 0; k < 4; ++k) {
      c.board_mm.push_back(tag->corners[k]);
      c.pixels.push_back(det->corners[k]);
    }
    c.tag_ids.push_back(id);
  }
  return c;
}

BoardPose estimate_board_pose(const calibration::CameraModel& cam, const BoardCorners& c,
                              const Eigen::Isometry3d* previous, const PoseOptions& o) {
  BoardPose out;
  out.corners = int(c.board_mm.size());
  out.tags = int(c.tag_ids.size());
  if (c.board_mm.size() < 4 || c.board_mm.size() != c.pixels.size()) {
    out.problem = "fewer than four corners";
    return out;
  }
  // Start: PnP on undistorted, normalised image points.
  std::vector<cv::Point3d> obj;
  std::vector<cv::Point2d> px;
  for (size_t i = 0; i < c.board_mm.size(); ++i) {
    obj.emplace_back(c.board_mm[i].x(), c.board_mm[i].y(), c.board_mm[i].z());
    px.emplace_back(c.pixels[i].x(), c.pixels[i].y());
  }
  std::vector<cv::Point2d> normalised;
  if (cam.model == calibration::DistortionModel::equidistant) {
    // The exact inverse of the fisheye lens; a corner it cannot unproject (90 degrees or more
    // off axis) leaves no pose to start from.
    for (const Eigen::Vector2d& p : c.pixels) {
      const Eigen::Vector2d xy = cam.unproject(p);
      if (!xy.allFinite()) {
        out.problem = "a corner lies outside the fisheye lens's invertible field of view";
        return out;
      }
      normalised.emplace_back(xy.x(), xy.y());
    }
  } else {
    cv::undistortPoints(
        px, normalised, cam.camera_matrix(), cam.distortion_coefficients(), cv::noArray(),
        cv::noArray(),
        cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 20, 1e-10));
  }
  std::vector<cv::Mat> rvecs, tvecs;
  const bool planar = is_planar(c.board_mm);
  try {
    cv::solvePnPGeneric(obj, normalised, cv::Mat::eye(3, 3, CV_64F), cv::noArray(), rvecs, tvecs,
                        false, planar ? cv::SOLVEPNP_IPPE : cv::SOLVEPNP_SQPNP);
  } catch (const cv::Exception& e) {
    out.problem = std::string("PnP failed: ") + e.what();
    return out;
  }
  if (rvecs.empty()) {
    out.problem = "PnP found no pose";
    return out;
  }
  std::vector<Refined> cands;
  for (size_t i = 0; i < rvecs.size(); ++i) {
    rvecs[i].convertTo(rvecs[i], CV_64F);
    tvecs[i].convertTo(tvecs[i], CV_64F);
    const Eigen::Isometry3d start = from_cv(rvecs[i], tvecs[i]);
    bool in_front = true;
    rms_error(cam, c, start, &in_front);
    if (!in_front) continue;
    cands.push_back(refine(cam, c, start, o));
  }
  if (cands.empty()) {
    out.problem = "no PnP solution places the board in front of the camera";
    return out;
  }
  std::sort(cands.begin(), cands.end(),
            [](const Refined& a, const Refined& b) { return a.rms < b.rms; });
  size_t pick = 0;
  if (cands.size() > 1 &&
      rotation_angle(cands[0].T.linear(), cands[1].T.linear()) > 1e-3 &&
      cands[1].rms < o.ambiguity_ratio * cands[0].rms + 1e-3) {
    out.ambiguous = true;
    if (previous) {
      const double a0 = rotation_angle(cands[0].T.linear(), previous->linear());
      const double a1 = rotation_angle(cands[1].T.linear(), previous->linear());
      if (a1 < a0) pick = 1;
    }
  }
  const Refined& best = cands[pick];
  if (!std::isfinite(best.rms) || best.rms > o.max_rms_px) {
    std::ostringstream msg;
    msg.precision(3);
    msg << "the " << out.tags << " tag(s) seen do not fit the board's layout (reprojection RMS "
        << best.rms << " px, at most " << o.max_rms_px
        << " px): check the board's tag ids, numbering and sizes in its description";
    out.problem = msg.str();
    return out;
  }
  out.valid = true;
  out.T_cam_board = best.T;
  out.rms_px = best.rms;

  if (o.covariance) {
    // Linearise at the solution itself (w = 0) so that the covariance is that of dT.
    double params[6] = {0, 0, 0, best.T.translation().x(), best.T.translation().y(),
                        best.T.translation().z()};
    ceres::Problem problem;
    add_residuals(problem, cam, c, best.T.linear(), params, o.huber_px);
    ceres::Covariance::Options co;
    co.algorithm_type = ceres::DENSE_SVD;
    co.null_space_rank = -1;
    co.min_reciprocal_condition_number = 1e-14;
    ceres::Covariance covariance(co);
    std::vector<std::pair<const double*, const double*>> blocks = {{params, params}};
    if (covariance.Compute(blocks, &problem)) {
      Eigen::Matrix<double, 6, 6, Eigen::RowMajor> cov;
      covariance.GetCovarianceBlock(params, params, cov.data());
      const int dof = 2 * out.corners - 6;
      const double ssr = best.rms * best.rms * double(out.corners);
      const double sigma2 = std::max(dof > 0 ? ssr / dof : 0.0, 0.05 * 0.05);
      out.covariance = cov * sigma2;
      out.covariance_valid = true;
    }
  }
  return out;
}

}  // namespace crepuscular::tracking
