// Per-frame tracking of marker boards: tag search where the last poses predict the tags (full frame
// periodically and whenever a board is missing), board poses, a temporal filter that does not lag
// a real motion, and staleness: a pose older than a stated limit is reported lost, never reused.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "calibration/camera_model.hpp"
#include "tracking/board.hpp"
#include "tracking/detector.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/pose.hpp"

namespace crepuscular::tracking {

using Matrix6d = Eigen::Matrix<double, 6, 6>;

// Constant-velocity alpha-beta filter of one board's pose (translation and rotation in the camera
// frame). A measurement whose innovation is improbable under its own covariance (a real, sudden
// move) restarts the filter at the measurement, so the output never trails a move for more than
// the frame in which it happens.
struct PoseFilterOptions {
  double alpha = 0.5;  // share of the innovation taken into the pose
  double beta = 0.2;   // share of the innovation (per frame interval) taken into the velocity
  // Restart when the squared Mahalanobis distance of the innovation, under twice the measurement
  // covariance plus the floor below, exceeds this (chi-square, 6 dof: 22.5 is the 99.9% point).
  double gate_chi2 = 22.5;
  double floor_mm = 0.05;   // standard deviations added to the covariance (never over-trust it)
  double floor_deg = 0.02;
};

class PoseFilter {
 public:
  explicit PoseFilter(const PoseFilterOptions& options = {}) : options_(options) {}

  bool initialised() const { return initialised_; }
  void reset() { initialised_ = false; }

  // Pose expected at timestamp_ns from the last update and the velocity (identity when not
  // initialised).
  Eigen::Isometry3d predict(int64_t timestamp_ns) const;

  // Takes a measured pose with its covariance ([w rad, t mm] as BoardPose::covariance; zero
  // means unknown: the floor alone is used) and returns the filtered pose. *restarted tells
  // whether the filter restarted at the measurement (first measurement, a gap longer than
  // max_gap_ns, or a gated innovation).
  Eigen::Isometry3d update(const Eigen::Isometry3d& measured, const Matrix6d& covariance,
                           int64_t timestamp_ns, int64_t max_gap_ns, bool* restarted = nullptr);

  const Eigen::Isometry3d& pose() const { return pose_; }
  int64_t timestamp_ns() const { return timestamp_ns_; }
  // The filtered pose's variance as a share of one measurement's, for measurements of equal,
  // independent noise: 1 at a restart, falling toward the filter's steady state (0.43 for alpha
  // 0.5, beta 0.2) as measurements are taken in.
  double variance_factor() const { return unit_(0, 0); }
  // The filtered pose's covariance ([w rad, t mm]) when the last measurement's was `measurement`:
  // scaled by variance_factor() (1 when not smoothing), plus the floor.
  Matrix6d pose_covariance(const Matrix6d& measurement, bool smoothing = true) const;

 private:
  PoseFilterOptions options_;
  bool initialised_ = false;
  Eigen::Isometry3d pose_ = Eigen::Isometry3d::Identity();
  Eigen::Vector3d velocity_ = Eigen::Vector3d::Zero();          // mm/s
  Eigen::Vector3d angular_velocity_ = Eigen::Vector3d::Zero();  // rad/s, camera frame
  int64_t timestamp_ns_ = 0;
  // Covariance of [pose, velocity] per unit measurement variance (velocity per second).
  Eigen::Matrix2d unit_ = Eigen::Matrix2d::Identity();
};

// Where the full-frame tag search runs. kInFrame: in the frame that needs it, which waits for it.
// kBackground: on a worker thread; the frame goes on with the regions it has, and the first frame
// after the search finishes searches the regions around the tags it found (no frame waits for a
// full-frame search; which frame takes the result depends on timing). kBackgroundWait: on the
// worker, with the next frame waiting for its result (the same output on every run: replays,
// tests).
enum class FullSearchMode { kInFrame, kBackground, kBackgroundWait };

struct TrackerOptions {
  DetectorOptions detector;
  PoseOptions pose;
  PoseFilterOptions filter;
  bool smoothing = true;        // false: report each frame's measured pose as is
  double max_age_ms = 100.0;    // a pose older than this is reported lost
  // Full-frame search at least every this many frames while every board is tracked (0: every
  // frame); in between, tags are searched where the boards' predicted poses put them.
  int full_search_interval = 15;
  FullSearchMode full_search_mode = FullSearchMode::kInFrame;
  double roi_margin_px = 16.0;        // margin around each predicted tag
  double roi_margin_tag_fraction = 0.5;  // plus this share of the tag's predicted size
  // Above this share of the image, the regions are not worth it: search the full frame.
  double max_roi_fraction = 0.5;
};

struct BoardStatus {
  std::string board;
  bool tracked = false;   // a pose no older than max_age_ms exists (T_cam_board is valid)
  bool measured = false;  // this frame's tags gave a pose
  Eigen::Isometry3d T_cam_board = Eigen::Isometry3d::Identity();  // filtered (if tracked)
  Eigen::Isometry3d T_measured = Eigen::Isometry3d::Identity();   // this frame's (if measured)
  double rms_px = 0;        // of the measurement behind T_cam_board
  double age_ms = std::numeric_limits<double>::infinity();  // since that measurement
  int tags = 0;             // tags seen in this frame
  int corners = 0;
  Matrix6d covariance = Matrix6d::Zero();  // of the measurement behind T_cam_board
  bool covariance_valid = false;
  // Of T_cam_board itself ([w rad, t mm] as covariance): the measurement's scaled by the filter's
  // variance factor (1 without smoothing), plus the filter's floor; valid as covariance is.
  Matrix6d pose_covariance = Matrix6d::Zero();
  bool ambiguous = false;
  bool filter_restarted = false;
  std::string problem;      // why the board was not measured in this frame
};

struct TrackResult {
  int64_t frame = 0;
  int64_t timestamp_ns = 0;
  std::vector<BoardStatus> boards;  // in the order of the tracker's boards
  std::vector<Detection> detections;
  bool full_search = false;  // the whole frame was searched in this frame (possibly after the regions)
  int regions = 0;           // regions searched before any full-frame search
  // Background modes: this frame started a full-frame search on the worker, and the frame whose
  // full-frame search this frame took the result of (-1: none).
  bool full_search_started = false;
  int64_t full_search_frame = -1;
  int64_t dropped = 0;       // frames missing just before this one (gap in frame numbers)
  std::string problem;       // the frame's own problem (undecodable image, ...)
};

class Tracker {
 public:
  // Searches the tags of every family the boards use (each board's own), with the settings of
  // options.detector (its family is not used). Throws Error for an empty board list, a board
  // without tags, an unknown family or a camera without a focal length.
  Tracker(const calibration::CameraModel& camera, std::vector<Board> boards,
          const TrackerOptions& options = {});
  ~Tracker();
  Tracker(const Tracker&) = delete;
  Tracker& operator=(const Tracker&) = delete;

  TrackResult process(const Frame& frame);

  const std::vector<Board>& boards() const { return boards_; }
  const TrackerOptions& options() const { return options_; }
  int64_t full_searches() const { return full_searches_; }
  int64_t frames() const { return frames_; }

 private:
  struct Track {
    PoseFilter filter;
    bool has_pose = false;
    int64_t measured_ns = 0;
    int64_t measured_index = 0;  // frame index of that measurement
    bool measured_last = false;  // measured in the previous frame
    BoardStatus last;            // status carrying the last pose
  };
  std::vector<cv::Rect> predicted_regions(int64_t timestamp_ns, bool* all_predicted) const;
  bool measure(size_t b, const std::vector<Detection>& detections, int64_t timestamp_ns,
               BoardStatus* status);
  // Measures every board not yet measured from res.detections; true when one is still missing.
  bool measure_boards(const Frame& frame, TrackResult& res, std::vector<bool>& measured);
  // Regions so large that searching them costs what the whole frame does.
  bool too_large(const std::vector<cv::Rect>& rois) const;
  // The search of one frame in kInFrame mode and in the background modes.
  void search_in_frame(const Frame& frame, TrackResult& res, std::vector<bool>& measured);
  void search_with_worker(const Frame& frame, TrackResult& res, std::vector<bool>& measured);
  // Regions around the detections of a full-frame search that belong to a board.
  std::vector<cv::Rect> regions_around(const std::vector<Detection>& detections) const;

  calibration::CameraModel camera_;
  std::vector<Board> boards_;
  TrackerOptions options_;
  static std::vector<std::string> families_of(const std::vector<Board>& boards,
                                              const std::string& fallback);

  FamilyDetector detector_;
  std::vector<Track> tracks_;
  int64_t last_index_ = -1;
  int64_t last_timestamp_ns_ = 0;
  // Time per frame from timestamps that advance (default 30 fps): a pose's age counts frames as
  // well as timestamps, so timestamps that stall or run backwards never make a pose current.
  double frame_interval_ns_ = 1e9 / 30.0;
  bool interval_measured_ = false;
  int64_t frames_ = 0;
  int64_t frames_since_full_ = 0;
  int64_t full_searches_ = 0;
  class FullSearchWorker;
  std::unique_ptr<FullSearchWorker> worker_;  // background modes
};

}  // namespace crepuscular::tracking
