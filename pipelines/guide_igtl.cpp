#include "pipelines/guide_igtl.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <filesystem>
#include <thread>

#include <opencv2/core.hpp>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "planning/trajectories/markups.hpp"

namespace crepuscular::pipelines {

namespace fs = std::filesystem;

std::vector<igtlink::Message> on_connect_messages(const planning::PlanData& plan,
                                                  const overlay::GuidanceSetup& setup) {
  std::vector<igtlink::Message> messages;
  Eigen::Isometry3d tip = Eigen::Isometry3d::Identity();
  tip.translation() = setup.tip_in_needle;
  messages.push_back(igtlink::transform_message("NeedleTipToNeedle", tip, 0));
  messages.push_back(igtlink::point_message("Target", "tumor centre", plan.tumor_centre, 0));
  const fs::path planned = fs::path(plan.dir) / "trajectories.mrk.json";
  std::error_code ec;
  if (fs::exists(planned, ec)) {
    try {
      const planning::LineMarkup line = planning::read_line_markup(planned.string());
      messages.push_back(igtlink::trajectory_message(
          "PlannedTrajectory", line.name.empty() ? "planned" : line.name, line.first,
          line.second, 0));
    } catch (const Error& e) {
      spdlog::warn("OpenIGTLink: no planned trajectory sent: {}", e.what());
    }
  }
  return messages;
}

GuidanceBroadcast::GuidanceBroadcast(const igtlink::Server::Options& options,
                                     const planning::PlanData& plan,
                                     const overlay::GuidanceSetup& setup)
    : setup_(setup), server_(options, on_connect_messages(plan, setup)) {}

void GuidanceBroadcast::poses(const tracking::Frame& frame, const tracking::TrackResult& track) {
  const tracking::BoardStatus* patient = nullptr;
  const tracking::BoardStatus* needle = nullptr;
  for (const auto& b : track.boards) {
    if (b.board == setup_.patient_board && b.tracked) patient = &b;
    if (b.board == setup_.needle_board && b.tracked) needle = &b;
  }
  const int64_t t = frame.timestamp_ns;
  std::vector<igtlink::Message> messages;
  if (patient) {
    messages.push_back(igtlink::transform_message("PatientToCT", setup_.T_ct_patient, t));
  } else {
    messages.push_back(igtlink::status_message("PatientToCT", igtlink::kStatusNotFound,
                                               "patient marker lost: no pose in the CT", t));
  }
  if (patient && needle) {
    const Eigen::Isometry3d T_ct_needle =
        setup_.T_ct_patient * patient->T_cam_board.inverse() * needle->T_cam_board;
    messages.push_back(igtlink::transform_message("NeedleToCT", T_ct_needle, t));
  } else {
    messages.push_back(igtlink::status_message(
        "NeedleToCT", igtlink::kStatusNotFound,
        needle ? "patient marker lost: the needle has no pose in the CT" : "needle marker lost",
        t));
  }
  server_.publish(std::move(messages));
}

void GuidanceBroadcast::safety(const overlay::GuidanceFrameInfo& info) {
  std::string text;
  if (!info.needle) {
    text = "no needle reading";
  } else {
    const planning::NeedleState& s = info.needle->state;
    text = fmt::format("{}; line integral {:.3g}", planning::needle_safety_name(s.safety),
                       s.evaluation.line_integral);
    const auto& n = *info.needle;
    if (n.uncertainty.valid) {
      text += fmt::format("; uncertainty at the tumor {:.1f} x {:.1f} mm (95 %)",
                          n.uncertainty.major95_mm, n.uncertainty.minor95_mm);
    }
    if (n.region.uncertain()) {
      text += std::string("; UNCERTAIN: ") + planning::needle_safety_name(n.region.worst) +
              " within the 95 % region";
    }
    for (const std::string& line : overlay::needle_text(s)) text += "; " + line;
  }
  std::vector<igtlink::Message> messages = {
      igtlink::string_message("NeedleSafety", text, info.timestamp_ns)};
  if (info.breathing) {
    // Breathing plans: the phase (its index in the plan's cycle), or why it is not known yet.
    const planning::PhaseEstimate& e = info.breathing->estimate;
    messages.push_back(igtlink::string_message(
        "BreathingPhase",
        e.known ? fmt::format("phase {}; {:.1f} mm above end-exhale; {}", e.phase, e.displacement_mm,
                              e.motion > 0 ? "inhaling" : e.motion < 0 ? "exhaling" : "at rest")
                : "unknown: " + e.reason,
        info.timestamp_ns));
  }
  server_.publish(std::move(messages));
}

namespace {

Eigen::Isometry3d anterior_view(const Eigen::Vector3d& centre) {
  // Camera axes in LPS: x = +L (patient's left on the image's right), y = -S (image down is
  // toward the feet), z = +P (looking posterior, from in front of the patient).
  Eigen::Isometry3d T_ct_cam = Eigen::Isometry3d::Identity();
  T_ct_cam.linear().col(0) = Eigen::Vector3d(1, 0, 0);
  T_ct_cam.linear().col(1) = Eigen::Vector3d(0, 0, -1);
  T_ct_cam.linear().col(2) = Eigen::Vector3d(0, 1, 0);
  T_ct_cam.translation() = centre - 400.0 * Eigen::Vector3d(0, 1, 0);
  return T_ct_cam.inverse();
}

class VirtualCameraSource : public tracking::FrameSource {
 public:
  VirtualCameraSource(const calibration::CameraModel& camera, double fps)
      : camera_(camera), interval_(std::chrono::duration<double>(1.0 / fps)) {}
  std::optional<tracking::Frame> next() override {
    const auto now = std::chrono::steady_clock::now();
    if (index_ == 0) start_ = now;
    const auto due = start_ + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                  interval_ * double(index_));
    if (due > now) std::this_thread::sleep_until(due);
    tracking::Frame f;
    f.index = index_++;
    f.timestamp_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(
                         std::chrono::steady_clock::now().time_since_epoch())
                         .count();
    f.image = cv::Mat(camera_.height, camera_.width, CV_8UC3, cv::Scalar(32, 32, 32));
    return f;
  }
  std::string describe() const override { return "virtual camera (poses over OpenIGTLink)"; }
  std::optional<calibration::CameraModel> camera() const override { return camera_; }

 private:
  calibration::CameraModel camera_;
  std::chrono::duration<double> interval_;
  std::chrono::steady_clock::time_point start_;
  int64_t index_ = 0;
};

}  // namespace

PoseInput::PoseInput(const std::string& uri, std::string needle, std::string patient,
                     double max_age_ms, const overlay::GuidanceSetup& setup,
                     const Eigen::Vector3d& tumor_centre)
    : needle_(std::move(needle)), patient_(std::move(patient)), max_age_ms_(max_age_ms),
      setup_(setup), T_cam_ct_(anterior_view(tumor_centre)) {
  if (const auto plus = plus_poses_address(uri)) {
    sequence_path_ = plus->first;
    sequence_ = std::make_unique<recordings::PlusSequence>(recordings::read_plus_sequence(plus->first));
    const std::vector<std::string> names = sequence_->transform_names();
    std::string listed;
    for (const auto& n : names) listed += (listed.empty() ? "" : ", ") + n;
    for (const std::string* device : {&needle_, &patient_}) {
      if (!device->empty() && std::find(names.begin(), names.end(), *device) == names.end()) {
        throw Error(plus->first + ": no transform " + *device + " (it holds " +
                    (listed.empty() ? std::string("none") : listed) +
                    "): name them with --poses-needle and --poses-patient");
      }
    }
  } else {
    receiver_ = std::make_unique<igtlink::PoseReceiver>(uri);
  }
}

std::string PoseInput::where() const { return sequence_ ? sequence_path_ : receiver_->uri(); }

std::optional<std::pair<std::string, bool>> plus_poses_address(const std::string& uri) {
  if (uri.rfind("plus:", 0) != 0) return std::nullopt;
  std::string path = uri.substr(5);
  bool realtime = false;
  const size_t q = path.find('?');
  if (q != std::string::npos) {
    const std::string query = path.substr(q + 1);
    if (query != "realtime=1" && query != "realtime=0") {
      throw Error("--poses " + uri + ": the only option is ?realtime=1 (as recorded) or "
                  "?realtime=0 (as fast as possible)");
    }
    realtime = query == "realtime=1";
    path = path.substr(0, q);
  }
  return std::make_pair(path, realtime);
}

bool PoseInput::current_pose(const std::string& device, int64_t frame, Eigen::Isometry3d* T,
                             double* age_ms) const {
  if (sequence_) {
    *age_ms = 0;
    if (frame < 0 || size_t(frame) >= sequence_->frames.size()) return false;
    const auto& transforms = sequence_->frames[size_t(frame)].transforms;
    const auto it = transforms.find(device);
    if (it == transforms.end() || !it->second.valid) return false;
    T->matrix() = it->second.matrix;
    return true;
  }
  const std::optional<igtlink::PoseReceiver::Pose> p = receiver_->latest(device);
  if (!p) return false;
  *age_ms = std::chrono::duration<double, std::milli>(igtlink::PoseReceiver::Clock::now() -
                                                      p->received)
                .count();
  *T = p->transform;
  return *age_ms <= max_age_ms_;
}

tracking::TrackResult PoseInput::track(const tracking::Frame& frame) const {
  tracking::TrackResult r;
  r.frame = frame.index;
  r.timestamp_ns = frame.timestamp_ns;
  tracking::BoardStatus patient, needle;
  patient.board = setup_.patient_board;
  needle.board = setup_.needle_board;
  Eigen::Isometry3d T_tracker_patient = Eigen::Isometry3d::Identity(), T_tracker_needle;
  double patient_age = 0, needle_age = 0;
  patient.tracked =
      patient_.empty() || current_pose(patient_, frame.index, &T_tracker_patient, &patient_age);
  // The virtual camera sees the CT from a fixed place: the patient board is where the
  // registration puts it.
  const Eigen::Isometry3d T_cam_patient = T_cam_ct_ * setup_.T_ct_patient;
  if (patient.tracked) {
    patient.T_cam_board = T_cam_patient;
    patient.measured = true;
    patient.age_ms = patient_age;
  } else {
    patient.problem = "no current " + patient_ + " pose from " + where();
  }
  needle.tracked = current_pose(needle_, frame.index, &T_tracker_needle, &needle_age);
  if (needle.tracked) {
    needle.T_cam_board = T_cam_patient * T_tracker_patient.inverse() * T_tracker_needle;
    needle.measured = true;
    needle.age_ms = needle_age;
  } else {
    needle.problem = "no current " + needle_ + " pose from " + where();
  }
  r.boards = {patient, needle};
  return r;
}

void PoseInput::replace_needle(tracking::TrackResult& camera) const {
  const tracking::BoardStatus* patient = nullptr;
  for (const auto& b : camera.boards) {
    if (b.board == setup_.patient_board) patient = &b;
  }
  tracking::BoardStatus needle;
  needle.board = setup_.needle_board;
  Eigen::Isometry3d T_tracker_patient = Eigen::Isometry3d::Identity(), T_tracker_needle;
  double patient_age = 0, needle_age = 0;
  const bool reference =
      patient_.empty() || current_pose(patient_, camera.frame, &T_tracker_patient, &patient_age);
  needle.tracked = patient && patient->tracked && reference &&
                   current_pose(needle_, camera.frame, &T_tracker_needle, &needle_age);
  if (needle.tracked) {
    needle.T_cam_board = patient->T_cam_board * T_tracker_patient.inverse() * T_tracker_needle;
    needle.measured = true;
    needle.age_ms = std::max({needle_age, patient_age, patient->age_ms});
  } else {
    needle.problem = "no current " + needle_ + " pose from " + where() +
                     " with the patient board in view";
  }
  bool replaced = false;
  for (auto& b : camera.boards) {
    if (b.board == setup_.needle_board) {
      b = needle;
      replaced = true;
    }
  }
  if (!replaced) camera.boards.push_back(needle);
}

namespace {

class PlusFramesSource : public tracking::FrameSource {
 public:
  PlusFramesSource(const calibration::CameraModel& camera, const recordings::PlusSequence& sequence,
                   double fps, bool realtime)
      : camera_(camera), realtime_(realtime) {
    double t0 = std::numeric_limits<double>::quiet_NaN();
    for (size_t f = 0; f < sequence.frames.size(); ++f) {
      const double t = sequence.frames[f].timestamp_s;
      if (std::isfinite(t) && !std::isfinite(t0)) t0 = t;
      // Nanoseconds from the first timestamped frame; the frame rate where a frame has none.
      times_ns_.push_back(std::isfinite(t) ? int64_t(std::llround((t - t0) * 1e9))
                                           : int64_t(std::llround(double(f) / fps * 1e9)));
    }
  }
  std::optional<tracking::Frame> next() override {
    if (index_ >= times_ns_.size()) return std::nullopt;
    if (realtime_) {
      if (index_ == 0) start_ = std::chrono::steady_clock::now();
      std::this_thread::sleep_until(start_ + std::chrono::nanoseconds(times_ns_[index_] - times_ns_[0]));
    }
    tracking::Frame f;
    f.index = int64_t(index_);
    f.timestamp_ns = times_ns_[index_];
    f.image = cv::Mat(camera_.height, camera_.width, CV_8UC3, cv::Scalar(32, 32, 32));
    ++index_;
    return f;
  }
  std::string describe() const override { return "virtual camera (poses of a PLUS sequence file)"; }
  std::optional<calibration::CameraModel> camera() const override { return camera_; }

 private:
  calibration::CameraModel camera_;
  bool realtime_;
  std::vector<int64_t> times_ns_;
  size_t index_ = 0;
  std::chrono::steady_clock::time_point start_;
};

}  // namespace

std::unique_ptr<tracking::FrameSource> plus_frames_source(const calibration::CameraModel& camera,
                                                          const recordings::PlusSequence& sequence,
                                                          double fps, bool realtime) {
  return std::make_unique<PlusFramesSource>(camera, sequence, fps, realtime);
}

std::unique_ptr<tracking::FrameSource> virtual_camera_source(const calibration::CameraModel& camera,
                                                             double fps) {
  return std::make_unique<VirtualCameraSource>(camera, fps);
}

}  // namespace crepuscular::pipelines
