// Board tracking over frames: region-of-interest search, poses, alpha-beta filter, staleness.
#include "tracking/tracker.hpp"

#include <algorithm>
#include <cmath>
#include <condition_variable>
#include <mutex>
#include <optional>
#include <set>
#include <thread>

#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "foundation/log.hpp"

namespace crepuscular::tracking {

namespace {

constexpr double kDegToRad = 3.14159265358979323846 / 180.0;

Eigen::Matrix3d exp_so3(const Eigen::Vector3d& w) {
  const double a = w.norm();
  if (a < 1e-15) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(a, w / a).toRotationMatrix();
}

Eigen::Vector3d log_so3(const Eigen::Matrix3d& R) {
  const Eigen::AngleAxisd aa(R);
  return aa.angle() * aa.axis();
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// PoseFilter

Eigen::Isometry3d PoseFilter::predict(int64_t timestamp_ns) const {
  if (!initialised_) return Eigen::Isometry3d::Identity();
  const double dt = double(timestamp_ns - timestamp_ns_) * 1e-9;
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = exp_so3(angular_velocity_ * dt) * pose_.linear();
  T.translation() = pose_.translation() + velocity_ * dt;
  return T;
}

Eigen::Isometry3d PoseFilter::update(const Eigen::Isometry3d& measured, const Matrix6d& covariance,
                                     int64_t timestamp_ns, int64_t max_gap_ns, bool* restarted) {
  const double dt = double(timestamp_ns - timestamp_ns_) * 1e-9;
  bool restart = !initialised_ || dt <= 0 || timestamp_ns - timestamp_ns_ > max_gap_ns;
  Eigen::Isometry3d pred;
  Eigen::Matrix<double, 6, 1> innovation;
  if (!restart) {
    pred = predict(timestamp_ns);
    innovation.head<3>() = log_so3(measured.linear() * pred.linear().transpose());
    innovation.tail<3>() = measured.translation() - pred.translation();
    Matrix6d S = 2.0 * covariance;
    const double fr = options_.floor_deg * kDegToRad, ft = options_.floor_mm;
    for (int k = 0; k < 3; ++k) {
      S(k, k) += fr * fr;
      S(3 + k, 3 + k) += ft * ft;
    }
    const double d2 = innovation.dot(S.ldlt().solve(innovation));
    if (!(d2 <= options_.gate_chi2)) restart = true;
  }
  if (restart) {
    // Start again at the measurement. The velocity since the last filtered pose lets a fast but
    // steady move be followed from the next frame on.
    if (initialised_ && dt > 0 && timestamp_ns - timestamp_ns_ <= max_gap_ns) {
      velocity_ = (measured.translation() - pose_.translation()) / dt;
      angular_velocity_ = log_so3(measured.linear() * pose_.linear().transpose()) / dt;
      unit_ << 1.0, 1.0 / dt, 1.0 / dt, (1.0 + unit_(0, 0)) / (dt * dt);
    } else {
      velocity_.setZero();
      angular_velocity_.setZero();
      unit_ << 1.0, 0.0, 0.0, 0.0;
    }
    pose_ = measured;
  } else {
    const double a = options_.alpha, b = options_.beta;
    pose_.linear() = exp_so3(a * innovation.head<3>()) * pred.linear();
    pose_.translation() = pred.translation() + a * innovation.tail<3>();
    angular_velocity_ += b * innovation.head<3>() / dt;
    velocity_ += b * innovation.tail<3>() / dt;
    // The same recursion for the variance: predict, then take in the measurement with the gains.
    Eigen::Matrix2d F;
    F << 1.0, dt, 0.0, 1.0;
    const Eigen::Vector2d K(a, b / dt);
    Eigen::Matrix2d A = Eigen::Matrix2d::Identity();
    A.col(0) -= K;
    unit_ = A * (F * unit_ * F.transpose()) * A.transpose() + K * K.transpose();
  }
  initialised_ = true;
  timestamp_ns_ = timestamp_ns;
  if (restarted) *restarted = restart;
  return pose_;
}

Matrix6d PoseFilter::pose_covariance(const Matrix6d& measurement, bool smoothing) const {
  Matrix6d c = (smoothing ? variance_factor() : 1.0) * measurement;
  const double fr = options_.floor_deg * kDegToRad, ft = options_.floor_mm;
  for (int k = 0; k < 3; ++k) {
    c(k, k) += fr * fr;
    c(3 + k, 3 + k) += ft * ft;
  }
  return c;
}

// ---------------------------------------------------------------------------------------------
// Full-frame search on a worker thread

// One search at a time: a frame's grey image goes in, its detections come out once.
class Tracker::FullSearchWorker {
 public:
  struct Result {
    int64_t frame = 0;
    std::vector<Detection> detections;
  };

  FullSearchWorker(const DetectorOptions& options, const std::vector<std::string>& families)
      : detector_(options, families), thread_([this] { run(); }) {}
  ~FullSearchWorker() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
    }
    wake_.notify_all();
    thread_.join();
  }

  // Starts searching `image` (copied as grey) unless a search is under way or its result has not
  // been taken; returns whether it started.
  bool submit(const cv::Mat& image, int64_t frame) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (state_ != State::kIdle) return false;
    }
    cv::Mat grey;
    if (image.channels() == 3) {
      cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
    } else if (image.channels() == 4) {
      cv::cvtColor(image, grey, cv::COLOR_BGRA2GRAY);
    } else {
      grey = image.clone();
    }
    {
      std::lock_guard<std::mutex> lock(mutex_);
      image_ = std::move(grey);
      frame_ = frame;
      state_ = State::kQueued;
    }
    wake_.notify_all();
    return true;
  }

  // The finished search's result (once); with wait, waits for the search under way first.
  std::optional<Result> take(bool wait) {
    std::unique_lock<std::mutex> lock(mutex_);
    if (wait) done_.wait(lock, [&] { return state_ == State::kIdle || state_ == State::kDone; });
    if (state_ != State::kDone) return std::nullopt;
    state_ = State::kIdle;
    if (error_) {
      std::exception_ptr e = error_;
      error_ = nullptr;
      std::rethrow_exception(e);
    }
    return std::move(result_);
  }

 private:
  enum class State { kIdle, kQueued, kRunning, kDone };

  void run() {
    std::unique_lock<std::mutex> lock(mutex_);
    for (;;) {
      wake_.wait(lock, [&] { return stop_ || state_ == State::kQueued; });
      if (stop_) return;
      state_ = State::kRunning;
      cv::Mat image = std::move(image_);
      Result r;
      r.frame = frame_;
      lock.unlock();
      std::exception_ptr error;
      try {
        r.detections = detector_.detect(image);
      } catch (...) {
        error = std::current_exception();
      }
      lock.lock();
      result_ = std::move(r);
      error_ = error;
      state_ = State::kDone;
      done_.notify_all();
    }
  }

  FamilyDetector detector_;  // the worker's own: libapriltag detectors are not shared
  std::mutex mutex_;
  std::condition_variable wake_, done_;
  State state_ = State::kIdle;
  bool stop_ = false;
  cv::Mat image_;
  int64_t frame_ = 0;
  Result result_;
  std::exception_ptr error_;
  std::thread thread_;  // last: starts after the members above exist
};

// ---------------------------------------------------------------------------------------------
// Tracker

namespace {

// Why none of `board`'s tags is among `detections`: none of its family at all, or only tags
// of its family whose ids are not on the board (a board described with other ids or another
// numbering than the one printed).
std::string no_tag_problem(const Board& board, const std::vector<Detection>& detections) {
  std::set<int> ids;
  for (const Detection& d : detections) {
    if (d.family == board.family) ids.insert(d.id);
  }
  if (ids.empty()) return "no tag of the board's family " + board.family + " found";
  std::string list;
  int shown = 0;
  for (int id : ids) {
    if (shown++ == 8) {
      list += " ...";
      break;
    }
    list += (list.empty() ? "" : " ") + std::to_string(id);
  }
  return "tags of " + board.family + " seen (ids " + list +
         ") but none of the board's: check the board's ids in its description";
}

}  // namespace

std::vector<std::string> Tracker::families_of(const std::vector<Board>& boards,
                                              const std::string& fallback) {
  std::vector<std::string> families;
  for (const Board& b : boards) families.push_back(b.family);
  if (families.empty()) families.push_back(fallback);
  return families;
}

Tracker::Tracker(const calibration::CameraModel& camera, std::vector<Board> boards,
                 const TrackerOptions& options)
    : camera_(camera),
      boards_(std::move(boards)),
      options_(options),
      detector_(options.detector, families_of(boards_, options.detector.family)) {
  if (boards_.empty()) throw Error("tracker: no marker boards given");
  for (const Board& b : boards_) {
    if (b.tags.empty()) throw Error("tracker: board '" + b.name + "' has no tags");
  }
  if (!(camera.fx > 0 && camera.fy > 0) || camera.width <= 0 || camera.height <= 0) {
    throw Error("tracker: camera model has no focal length or image size");
  }
  if (!(options.max_age_ms > 0)) throw Error("tracker: max_age_ms must be > 0");
  tracks_.resize(boards_.size());
  for (Track& t : tracks_) t.filter = PoseFilter(options.filter);
  if (options.full_search_mode != FullSearchMode::kInFrame) {
    worker_ = std::make_unique<FullSearchWorker>(options.detector, detector_.families());
  }
}

Tracker::~Tracker() = default;

std::vector<cv::Rect> Tracker::regions_around(const std::vector<Detection>& detections) const {
  std::vector<cv::Rect> rois;
  const cv::Rect image(0, 0, camera_.width, camera_.height);
  for (const Detection& d : detections) {
    const bool ours = std::any_of(boards_.begin(), boards_.end(), [&](const Board& b) {
      return std::any_of(b.tags.begin(), b.tags.end(),
                         [&](const BoardTag& t) { return t.id == d.id; });
    });
    if (!ours) continue;
    double x0 = 1e300, y0 = 1e300, x1 = -1e300, y1 = -1e300;
    for (const Eigen::Vector2d& c : d.corners) {
      x0 = std::min(x0, c.x());
      y0 = std::min(y0, c.y());
      x1 = std::max(x1, c.x());
      y1 = std::max(y1, c.y());
    }
    // The tag has moved since that frame: a whole tag's size more on every side.
    const double margin = options_.roi_margin_px + std::max(x1 - x0, y1 - y0);
    const cv::Rect r(cv::Point(int(std::floor(x0 - margin)), int(std::floor(y0 - margin))),
                     cv::Point(int(std::ceil(x1 + margin)) + 1, int(std::ceil(y1 + margin)) + 1));
    const cv::Rect clipped = r & image;
    if (clipped.area() > 0) rois.push_back(clipped);
  }
  return rois;
}

std::vector<cv::Rect> Tracker::predicted_regions(int64_t timestamp_ns, bool* all_predicted) const {
  std::vector<cv::Rect> rois;
  *all_predicted = true;
  const cv::Rect image(0, 0, camera_.width, camera_.height);
  for (size_t b = 0; b < boards_.size(); ++b) {
    const Track& tr = tracks_[b];
    if (!tr.measured_last || !tr.filter.initialised()) {
      *all_predicted = false;
      continue;
    }
    const Eigen::Isometry3d now = tr.filter.predict(timestamp_ns);
    const Eigen::Isometry3d before = tr.filter.pose();
    for (const BoardTag& tag : boards_[b].tags) {
      double x0 = 1e300, y0 = 1e300, x1 = -1e300, y1 = -1e300, shift = 0;
      bool ok = true;
      for (const Eigen::Vector3d& c : tag.corners) {
        const Eigen::Vector3d p = now * c, q = before * c;
        // Outside about 60 degrees off axis the Brown-Conrady polynomial is not to be trusted;
        // a fisheye lens is modelled to 80 degrees (tan 80 = 5.7).
        const double reach = camera_.model == calibration::DistortionModel::equidistant ? 5.6 : 2.0;
        if (p.z() <= 1e-3 || std::abs(p.x()) > reach * p.z() || std::abs(p.y()) > reach * p.z() ||
            q.z() <= 1e-3 || std::abs(q.x()) > reach * q.z() || std::abs(q.y()) > reach * q.z()) {
          ok = false;
          break;
        }
        double uv[2], uv0[2];
        project_with_distortion(camera_, p.data(), uv);
        project_with_distortion(camera_, q.data(), uv0);
        x0 = std::min(x0, uv[0]);
        y0 = std::min(y0, uv[1]);
        x1 = std::max(x1, uv[0]);
        y1 = std::max(y1, uv[1]);
        shift = std::max(shift, std::hypot(uv[0] - uv0[0], uv[1] - uv0[1]));
      }
      if (!ok) continue;
      const double margin = options_.roi_margin_px +
                            options_.roi_margin_tag_fraction * std::max(x1 - x0, y1 - y0) + shift;
      const cv::Rect r(cv::Point(int(std::floor(x0 - margin)), int(std::floor(y0 - margin))),
                       cv::Point(int(std::ceil(x1 + margin)) + 1, int(std::ceil(y1 + margin)) + 1));
      const cv::Rect clipped = r & image;
      if (clipped.area() > 0) rois.push_back(clipped);
    }
  }
  return TagDetector::merge_regions(std::move(rois));
}

bool Tracker::measure(size_t b, const std::vector<Detection>& detections, int64_t timestamp_ns,
                      BoardStatus* st) {
  Track& tr = tracks_[b];
  const BoardCorners corners = match_board_corners(boards_[b], detections);
  st->tags = int(corners.tag_ids.size());
  st->corners = int(corners.board_mm.size());
  if (corners.tag_ids.empty()) {
    st->problem = no_tag_problem(boards_[b], detections);
    return false;
  }
  const double max_age_ns = options_.max_age_ms * 1e6;
  const bool recent = tr.has_pose && double(timestamp_ns - tr.measured_ns) <= max_age_ns;
  Eigen::Isometry3d previous = Eigen::Isometry3d::Identity();
  if (recent) previous = tr.filter.initialised() ? tr.filter.predict(timestamp_ns) : tr.last.T_cam_board;
  const BoardPose pose = estimate_board_pose(camera_, corners, recent ? &previous : nullptr,
                                             options_.pose);
  if (!pose.valid) {
    st->problem = pose.problem;
    return false;
  }
  bool restarted = false;
  const Matrix6d cov = pose.covariance_valid ? pose.covariance : Matrix6d::Zero();
  const Eigen::Isometry3d filtered = tr.filter.update(
      pose.T_cam_board, cov, timestamp_ns, int64_t(max_age_ns), &restarted);
  st->measured = true;
  st->tracked = true;
  st->T_measured = pose.T_cam_board;
  st->T_cam_board = options_.smoothing ? filtered : pose.T_cam_board;
  st->rms_px = pose.rms_px;
  st->age_ms = 0;
  st->covariance = pose.covariance;
  st->covariance_valid = pose.covariance_valid;
  st->pose_covariance = tr.filter.pose_covariance(cov, options_.smoothing);
  st->ambiguous = pose.ambiguous;
  st->filter_restarted = restarted;
  st->problem.clear();
  tr.has_pose = true;
  tr.measured_ns = timestamp_ns;
  tr.measured_index = last_index_;
  tr.last = *st;
  return true;
}

bool Tracker::measure_boards(const Frame& frame, TrackResult& res, std::vector<bool>& measured) {
  bool missing = false;
  for (size_t b = 0; b < boards_.size(); ++b) {
    if (!measured[b]) measured[b] = measure(b, res.detections, frame.timestamp_ns, &res.boards[b]);
    if (!measured[b]) missing = true;
  }
  return missing;
}

bool Tracker::too_large(const std::vector<cv::Rect>& rois) const {
  double area = 0;
  for (const cv::Rect& r : rois) area += r.area();
  return area > options_.max_roi_fraction * camera_.width * camera_.height;
}

void Tracker::search_in_frame(const Frame& frame, TrackResult& res, std::vector<bool>& measured) {
  bool full = options_.full_search_interval <= 0 ||
              frames_since_full_ + 1 >= options_.full_search_interval;
  std::vector<cv::Rect> rois;
  if (!full) {
    bool all_predicted = true;
    rois = predicted_regions(frame.timestamp_ns, &all_predicted);
    if (!all_predicted || rois.empty() || too_large(rois)) full = true;
  }
  if (!full) {
    res.regions = int(rois.size());
    res.detections = detector_.detect(frame.image, rois);
    // A board the regions did not show is searched for in the whole frame at once.
    full = measure_boards(frame, res, measured);
  }
  if (full) {
    res.full_search = true;
    ++full_searches_;
    frames_since_full_ = 0;
    res.detections = detector_.detect(frame.image);
    measure_boards(frame, res, measured);
  } else {
    ++frames_since_full_;
  }
}

void Tracker::search_with_worker(const Frame& frame, TrackResult& res,
                                 std::vector<bool>& measured) {
  // A finished full-frame search: the regions around the tags it found join the predicted ones.
  std::vector<cv::Rect> rois;
  if (auto done = worker_->take(options_.full_search_mode == FullSearchMode::kBackgroundWait)) {
    res.full_search_frame = done->frame;
    rois = regions_around(done->detections);
  }
  bool all_predicted = true;
  for (const cv::Rect& r : predicted_regions(frame.timestamp_ns, &all_predicted)) rois.push_back(r);
  rois = TagDetector::merge_regions(std::move(rois));
  const bool nothing_to_search = rois.empty();
  if (too_large(rois) ||
      (nothing_to_search && options_.full_search_mode == FullSearchMode::kBackgroundWait)) {
    // Regions that large cost what the whole frame does; and a replay with nothing to search
    // would only wait for the worker in the next frame: the whole frame now.
    res.full_search = true;
    ++full_searches_;
    res.detections = detector_.detect(frame.image);
  } else if (!rois.empty()) {
    res.regions = int(rois.size());
    res.detections = detector_.detect(frame.image, rois);
  }
  const bool missing = measure_boards(frame, res, measured);
  // A missing board, or the periodic search, starts one on the worker when it is free.
  const bool due = options_.full_search_interval <= 0 ||
                   frames_since_full_ + 1 >= options_.full_search_interval;
  if ((missing || due) && !res.full_search && worker_->submit(frame.image, frame.index)) {
    res.full_search_started = true;
    ++full_searches_;
    frames_since_full_ = 0;
  } else if (res.full_search) {
    frames_since_full_ = 0;
  } else {
    ++frames_since_full_;
  }
}

TrackResult Tracker::process(const Frame& frame) {
  TrackResult res;
  res.frame = frame.index;
  res.timestamp_ns = frame.timestamp_ns;
  res.problem = frame.problem;
  if (last_index_ >= 0 && frame.index > last_index_ + 1) res.dropped = frame.index - last_index_ - 1;
  if (last_index_ >= 0 && frame.index > last_index_ && frame.timestamp_ns > last_timestamp_ns_) {
    const double per_frame =
        double(frame.timestamp_ns - last_timestamp_ns_) / double(frame.index - last_index_);
    frame_interval_ns_ = std::clamp(
        interval_measured_ ? 0.9 * frame_interval_ns_ + 0.1 * per_frame : per_frame, 1e6, 1e9);
    interval_measured_ = true;
  }
  last_index_ = frame.index;
  last_timestamp_ns_ = frame.timestamp_ns;
  ++frames_;

  res.boards.resize(boards_.size());
  std::vector<bool> measured(boards_.size(), false);
  for (size_t b = 0; b < boards_.size(); ++b) res.boards[b].board = boards_[b].name;

  // A frame of another size than the camera model's cannot be measured with it: skipped and
  // reported (the session goes on), never measured with the wrong intrinsics.
  const bool wrong_size = !frame.image.empty() && (frame.image.cols != camera_.width ||
                                                   frame.image.rows != camera_.height);
  if (wrong_size && res.problem.empty()) {
    res.problem = "frame " + std::to_string(frame.index) + " is " +
                  std::to_string(frame.image.cols) + "x" + std::to_string(frame.image.rows) +
                  " but the camera model is " + std::to_string(camera_.width) + "x" +
                  std::to_string(camera_.height) + ": skipped";
  }
  if (frame.image.empty() || wrong_size) {
    if (res.problem.empty()) res.problem = "no image";
  } else {
    if (worker_) {
      search_with_worker(frame, res, measured);
    } else {
      search_in_frame(frame, res, measured);
    }
  }

  // Boards without a measurement now: their last pose while it is young enough, else lost.
  for (size_t b = 0; b < boards_.size(); ++b) {
    Track& tr = tracks_[b];
    // A frame without an image says nothing of where the boards are: the one before still counts.
    if (!frame.image.empty() && !wrong_size) tr.measured_last = measured[b];
    if (measured[b]) continue;
    BoardStatus& st = res.boards[b];
    if (st.problem.empty()) st.problem = res.problem.empty() ? "not searched" : res.problem;
    if (!tr.has_pose) continue;
    // The age by the source's clock, but never less than the frames since then at the frame
    // interval: a source whose timestamps stop or go backwards cannot keep a pose current.
    st.age_ms = std::max(double(frame.timestamp_ns - tr.measured_ns),
                         double(frame.index - tr.measured_index) * frame_interval_ns_) *
                1e-6;
    if (st.age_ms <= options_.max_age_ms) {
      st.tracked = true;
      st.T_cam_board = tr.last.T_cam_board;
      st.rms_px = tr.last.rms_px;
      st.covariance = tr.last.covariance;
      st.covariance_valid = tr.last.covariance_valid;
      st.pose_covariance = tr.last.pose_covariance;
    } else {
      st.tracked = false;
    }
  }
  return res;
}

}  // namespace crepuscular::tracking
