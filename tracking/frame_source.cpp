// Frame source URIs, and the replay of recording folders.
#include "tracking/frame_source.hpp"

#include <algorithm>
#include <cctype>
#include <chrono>
#include <fstream>
#include <cstring>
#include <cstdio>
#include <cerrno>
#include <cmath>
#include <filesystem>
#include <optional>
#include <thread>

#include <fmt/format.h>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "recordings/plus_sequence.hpp"
#include "recordings/recording.hpp"
#include "tracking/synthetic.hpp"
#include "tracking/v4l2_source.hpp"

namespace crepuscular::tracking {

namespace {

bool flag_option(const std::string& uri, const std::string& key, const std::string& value) {
  if (value == "1" || value == "true" || value == "yes") return true;
  if (value == "0" || value == "false" || value == "no") return false;
  throw Error(uri + ": option " + key + "=" + value + " is invalid, expected 0 or 1");
}

Eigen::Isometry3d pose_of(const recordings::PoseRow& r) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::Quaterniond(r.q[0], r.q[1], r.q[2], r.q[3]).normalized().toRotationMatrix();
  T.translation() = Eigen::Vector3d(r.t[0], r.t[1], r.t[2]);
  return T;
}

// A PLUS sequence file's image frames (8-bit as they are, 16-bit scaled to 8 bits; grey shown as
// grey) with its timestamps; its valid transforms ride along as the frame's poses (`truth`, by
// transform name). A frame without an image (no image data, ImageStatus INVALID) is delivered
// without one and says why.
class PlusSource : public FrameSource {
 public:
  PlusSource(const std::string& path, bool realtime)
      : path_(path), sequence_(recordings::read_plus_sequence(path)), realtime_(realtime) {
    const std::string& t = sequence_.element_type;
    if (sequence_.width > 0 && t != "MET_UCHAR" && t != "MET_USHORT" && t != "MET_SHORT") {
      throw Error(path + ": its images are " + t + ": only 8-bit and 16-bit images are shown");
    }
    if (sequence_.width > 0 && sequence_.channels != 1 && sequence_.channels != 3) {
      throw Error(path + ": images of " + std::to_string(sequence_.channels) +
                  " channels: grey or colour (3) images are shown");
    }
  }
  std::optional<Frame> next() override {
    if (index_ >= sequence_.frames.size()) return std::nullopt;
    const recordings::PlusFrame& pf = sequence_.frames[index_];
    Frame f;
    f.index = int64_t(index_);
    const double t = std::isfinite(pf.timestamp_s) ? pf.timestamp_s : double(index_) / 30.0;
    f.timestamp_ns = int64_t(std::llround(t * 1e9));
    if (realtime_) {
      if (index_ == 0) {
        start_ = std::chrono::steady_clock::now();
        t0_ns_ = f.timestamp_ns;
      }
      std::this_thread::sleep_until(start_ + std::chrono::nanoseconds(f.timestamp_ns - t0_ns_));
    }
    if (sequence_.width == 0) {
      f.problem = "the sequence holds no image frames";
    } else if (pf.field("ImageStatus") == "INVALID") {
      f.problem = "the sequence frame's image is INVALID";
    } else {
      const int w = sequence_.width, h = sequence_.height, c = sequence_.channels;
      const size_t bytes = size_t(w) * size_t(h) * size_t(c) * size_t(sequence_.bytes_per_pixel());
      const uint8_t* p = sequence_.pixels.data() + bytes * index_;
      cv::Mat image;
      if (sequence_.element_type == "MET_UCHAR") {
        image = cv::Mat(h, w, CV_8UC(c), const_cast<uint8_t*>(p)).clone();
      } else {
        cv::Mat wide(h, w, sequence_.element_type == "MET_USHORT" ? CV_16UC(c) : CV_16SC(c),
                     const_cast<uint8_t*>(p));
        double lo = 0, hi = 0;
        cv::minMaxLoc(wide.reshape(1), &lo, &hi);
        wide.convertTo(image, CV_8U, hi > lo ? 255.0 / (hi - lo) : 1.0, hi > lo ? -lo * 255.0 / (hi - lo) : 0.0);
      }
      if (c == 1) cv::cvtColor(image, f.image, cv::COLOR_GRAY2BGR);
      else cv::cvtColor(image, f.image, cv::COLOR_RGB2BGR);
    }
    for (const auto& [name, transform] : pf.transforms) {
      if (!transform.valid) continue;
      TruePose pose;
      pose.board = name;
      pose.T_cam_board.matrix() = transform.matrix;
      f.truth.push_back(pose);
    }
    ++index_;
    return f;
  }
  std::string describe() const override { return "PLUS sequence " + path_; }

 private:
  std::string path_;
  recordings::PlusSequence sequence_;
  bool realtime_;
  size_t index_ = 0;
  std::chrono::steady_clock::time_point start_;
  int64_t t0_ns_ = 0;
};

class RecordingSource : public FrameSource {
 public:
  RecordingSource(const std::string& dir, bool realtime, bool loop)
      : reader_(dir), realtime_(realtime), loop_(loop) {
    for (const std::string& p : reader_.problems()) spdlog::warn("recording: {}", p);
    if (!reader_.camera_path().empty()) {
      try {
        camera_ = calibration::CameraModel::read_yaml(reader_.camera_path());
      } catch (const Error& e) {
        spdlog::warn("recording: {}", e.what());
      }
    }
    const auto& e = reader_.entries();
    if (e.size() >= 2) {
      // One loop lasts the recording plus one mean frame interval.
      const int64_t span = e.back().timestamp_ns - e.front().timestamp_ns;
      loop_ns_ = span + span / int64_t(e.size() - 1);
      loop_frames_ = e.back().frame - e.front().frame + 1;
    } else if (e.size() == 1) {
      loop_ns_ = 33333333;
      loop_frames_ = 1;
    }
    spdlog::info("recording: {} frames in {}{}{}", e.size(), dir, realtime_ ? ", recorded timing" : "",
                 loop_ ? ", looping" : "");
  }

  std::optional<Frame> next() override {
    const auto& entries = reader_.entries();
    if (entries.empty()) return std::nullopt;
    if (pos_ >= entries.size()) {
      if (!loop_) return std::nullopt;
      pos_ = 0;
      ++loops_;
    }
    const recordings::RecordingReader::Entry& e = entries[pos_];
    Frame f;
    f.index = e.frame + loops_ * loop_frames_;
    f.timestamp_ns = e.timestamp_ns + loops_ * loop_ns_;
    if (realtime_) {
      const auto now = std::chrono::steady_clock::now();
      if (!started_) {
        started_ = true;
        wall_start_ = now;
        first_ns_ = f.timestamp_ns;
      }
      std::this_thread::sleep_until(wall_start_ + std::chrono::nanoseconds(f.timestamp_ns - first_ns_));
    }
    recordings::RecordingReader::Loaded loaded = reader_.load(pos_);
    f.image = std::move(loaded.image);
    f.problem = std::move(loaded.problem);
    f.encoded = std::move(loaded.bytes);
    const std::string ext = std::filesystem::path(e.file).extension().string();
    f.encoded_format = ext.empty() ? std::string() : ext.substr(1);
    if (f.encoded_format == "jpeg") f.encoded_format = "jpg";
    for (const recordings::PoseRow& r : reader_.ground_truth(e.frame)) {
      f.truth.push_back({r.board, pose_of(r)});
    }
    ++pos_;
    return f;
  }

  std::string describe() const override { return "recording:" + reader_.dir(); }
  std::optional<calibration::CameraModel> camera() const override { return camera_; }

 private:
  recordings::RecordingReader reader_;
  bool realtime_;
  bool loop_;
  std::optional<calibration::CameraModel> camera_;
  size_t pos_ = 0;
  int64_t loops_ = 0;
  int64_t loop_ns_ = 0;
  int64_t loop_frames_ = 0;
  bool started_ = false;
  std::chrono::steady_clock::time_point wall_start_;
  int64_t first_ns_ = 0;
};

}  // namespace

SourceUri parse_source_uri(const std::string& uri) {
  const size_t colon = uri.find(':');
  if (colon == std::string::npos || colon == 0) {
    throw Error("source '" + uri +
                "': expected KIND:WHERE, e.g. v4l2:/dev/video0, recording:DIR or "
                "synthetic:SCENE.json");
  }
  SourceUri u;
  u.scheme = uri.substr(0, colon);
  for (char c : u.scheme) {
    if (!std::isalnum(static_cast<unsigned char>(c))) {
      throw Error("source '" + uri + "': kind '" + u.scheme + "' is not a word");
    }
  }
  const std::string rest = uri.substr(colon + 1);
  const size_t q = rest.find('?');
  u.path = rest.substr(0, q);
  if (u.path.empty()) throw Error("source '" + uri + "': nothing after '" + u.scheme + ":'");
  if (q != std::string::npos) {
    const std::string query = rest.substr(q + 1);
    size_t start = 0;
    while (start <= query.size()) {
      const size_t amp = std::min(query.find('&', start), query.size());
      const std::string item = query.substr(start, amp - start);
      const size_t eq = item.find('=');
      if (item.empty() || eq == std::string::npos || eq == 0) {
        throw Error("source '" + uri + "': option '" + item + "' is malformed, expected key=value");
      }
      u.options.emplace_back(item.substr(0, eq), item.substr(eq + 1));
      start = amp + 1;
    }
  }
  return u;
}

std::unique_ptr<FrameSource> open_recording_source(const std::string& dir, bool realtime,
                                                   bool loop) {
  return std::make_unique<RecordingSource>(dir, realtime, loop);
}

std::unique_ptr<FrameSource> open_frame_source(const std::string& uri) {
  const SourceUri u = parse_source_uri(uri);
  if (u.scheme == "recording") {
    bool realtime = false, loop = false;
    for (const auto& [key, value] : u.options) {
      if (key == "realtime") {
        realtime = flag_option(uri, key, value);
      } else if (key == "loop") {
        loop = flag_option(uri, key, value);
      } else {
        throw Error(uri + ": unknown option '" + key + "', expected realtime or loop");
      }
    }
    return open_recording_source(u.path, realtime, loop);
  }
  if (u.scheme == "synthetic") {
    if (!u.options.empty()) {
      throw Error(uri + ": synthetic sources take no options (put them in the scene file)");
    }
    return open_synthetic_source(u.path);
  }
  if (u.scheme == "v4l2") {
    return open_v4l2_source(u.path, parse_v4l2_options(uri, u.options));
  }
  if (u.scheme == "plus") {
    bool realtime = false;
    for (const auto& [key, value] : u.options) {
      if (key != "realtime") throw Error(uri + ": unknown option '" + key + "', expected realtime");
      realtime = flag_option(uri, key, value);
    }
    return std::make_unique<PlusSource>(u.path, realtime);
  }
  throw Error("source '" + uri + "': unknown kind '" + u.scheme +
              "', expected v4l2:, recording:, synthetic: or plus:");
}

struct FrameRecorder::Impl {
  std::string final_dir, partial;
  std::optional<StagedDirectory> staged;  // partial, kept when the recording is interrupted
  RecordOptions options;
  std::unique_ptr<recordings::RecordingWriter> writer;
  RecordSummary summary;
  int64_t last_index = -1;
  std::chrono::steady_clock::time_point t0 = std::chrono::steady_clock::now();
  bool finished = false;
};

FrameRecorder::FrameRecorder(const std::string& out_dir, const std::string& source_description,
                             const std::optional<calibration::CameraModel>& camera,
                             const RecordOptions& options, bool with_truth)
    : impl_(std::make_unique<Impl>()) {
  namespace fs = std::filesystem;
  Impl& m = *impl_;
  m.options = options;
  m.final_dir = out_dir;
  while (m.final_dir.size() > 1 && m.final_dir.back() == '/') m.final_dir.pop_back();
  m.partial = m.final_dir + ".partial";
  if (fs::exists(m.final_dir)) {
    throw Error(m.final_dir + ": exists; choose another output folder or remove it first");
  }
  if (fs::exists(m.partial)) {
    throw Error(m.partial + ": exists (an interrupted recording, replayable as recording:" +
                m.partial + "); move or remove it first");
  }
  recordings::SessionInfo session;
  session.source = source_description;
  session.plan = options.plan;
  if (!options.boards_json.empty()) {
    session.boards = parse_json_text(options.boards_json, "boards for the recording");
  }
  m.staged.emplace(m.final_dir, StagedDirectory::OnFailure::kKeep);
  m.writer = std::make_unique<recordings::RecordingWriter>(
      m.partial, session, options.image_format, options.jpeg_quality, with_truth);
  if (const std::optional<calibration::CameraModel> c = options.camera ? options.camera : camera) {
    c->write_yaml((fs::path(m.partial) / "camera.yaml").string());
  }
  m.summary.path = m.final_dir;
  spdlog::info("record: {} -> {} (a recording in progress is {}: it replays as it is)",
               source_description, m.final_dir, m.partial);
}

FrameRecorder::~FrameRecorder() = default;

bool FrameRecorder::add(const Frame& frame) {
  Impl& m = *impl_;
  if (!frame.problem.empty()) ++m.summary.problems;
  if (frame.index <= m.last_index) {
    spdlog::warn("record: frame {} does not follow frame {}; skipped", frame.index, m.last_index);
    ++m.summary.skipped;
    return false;
  }
  std::vector<recordings::PoseRow> truth;
  for (const TruePose& p : frame.truth) {
    recordings::PoseRow r;
    r.board = p.board;
    r.state = "tracked";
    const Eigen::Quaterniond q(p.T_cam_board.linear());
    r.q[0] = q.w();
    r.q[1] = q.x();
    r.q[2] = q.y();
    r.q[3] = q.z();
    for (int k = 0; k < 3; ++k) r.t[k] = p.T_cam_board.translation()[k];
    truth.push_back(r);
  }
  const bool passthrough = !frame.encoded.empty() && frame.encoded_format == "jpg" &&
                           m.options.image_format == "jpg";
  if (passthrough) {
    m.writer->add_encoded(frame.index, frame.timestamp_ns, frame.encoded, "jpg", truth);
  } else if (!frame.image.empty()) {
    m.writer->add_frame(frame.index, frame.timestamp_ns, frame.image, truth);
  } else {
    ++m.summary.skipped;
    return false;
  }
  m.last_index = frame.index;
  ++m.summary.frames;
  m.summary.truth_rows += int64_t(truth.size());
  return true;
}

const RecordSummary& FrameRecorder::summary() const { return impl_->summary; }

RecordSummary FrameRecorder::finish() {
  Impl& m = *impl_;
  if (m.finished) return m.summary;
  m.finished = true;
  m.writer->finish();
  m.staged->commit();
  m.summary.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - m.t0).count();
  return m.summary;
}

RecordSummary record_to_folder(FrameSource& source, const std::string& out_dir,
                               const RecordOptions& options) {
  std::optional<Frame> frame = source.next();
  FrameRecorder recorder(out_dir, source.describe(), source.camera(), options,
                         frame && !frame->truth.empty());
  const auto t0 = std::chrono::steady_clock::now();
  int64_t first_ns = 0;
  bool have_first = false;
  auto last_log = t0;
  for (; frame; frame = source.next()) {
    if (options.stop && options.stop->load()) {
      spdlog::info("record: stopped");
      break;
    }
    if (!have_first) {
      first_ns = frame->timestamp_ns;
      have_first = true;
    }
    if (options.max_seconds >= 0 &&
        double(frame->timestamp_ns - first_ns) * 1e-9 >= options.max_seconds) {
      break;
    }
    if (!frame->note.empty()) spdlog::info("record: frame {}: {}", frame->index, frame->note);
    if (!frame->problem.empty()) spdlog::warn("record: frame {}: {}", frame->index, frame->problem);
    if (!recorder.add(*frame)) continue;
    const int64_t frames = recorder.summary().frames;
    if (options.max_frames >= 0 && frames >= options.max_frames) break;
    const auto now = std::chrono::steady_clock::now();
    if (now - last_log > std::chrono::seconds(1)) {
      last_log = now;
      const double s = std::chrono::duration<double>(now - t0).count();
      spdlog::info("record: {} frames in {:.1f} s ({:.1f} fps)", frames, s,
                   double(frames) / std::max(s, 1e-9));
    }
  }
  return recorder.finish();
}

RecordSummary record_to_plus_sequence(FrameSource& source, const std::string& path,
                                      const RecordOptions& options) {
  const auto t0 = std::chrono::steady_clock::now();
  RecordSummary summary;
  summary.path = path;
  // The pixels go to a scratch file while the frames' fields are gathered; the header (which
  // lists every frame's fields) then goes before them.
  PendingFile scratch(path + ".pixels");
  std::FILE* pixels = std::fopen(scratch.temporary().c_str(), "wb");
  if (!pixels) throw Error(path + ": cannot write the sequence's image frames (" + std::strerror(errno) + ")");
  struct Closer {
    std::FILE*& f;
    ~Closer() { if (f) std::fclose(f); }
  } closer{pixels};
  recordings::PlusSequence seq;
  seq.header = {{"AnatomicalOrientation", "RAI"}, {"Kinds", "domain domain list"},
                {"ElementSpacing", "1 1 1"},      {"Offset", "0 0 0"},
                {"TransformMatrix", "1 0 0 0 1 0 0 0 1"}, {"UltrasoundImageOrientation", "MF"}};
  seq.channels = 3;
  int64_t blank_before_size = 0;  // frames before the first image: black once its size is known
  const auto write_black = [&](int64_t frames) {
    const std::vector<uint8_t> black(size_t(seq.width) * size_t(seq.height) * 3, 0);
    for (int64_t k = 0; k < frames; ++k) std::fwrite(black.data(), 1, black.size(), pixels);
  };
  int64_t first_ns = 0;
  bool have_first = false;
  for (std::optional<Frame> frame = source.next(); frame; frame = source.next()) {
    if (options.stop && options.stop->load()) break;
    if (!have_first) {
      first_ns = frame->timestamp_ns;
      have_first = true;
    }
    if (options.max_seconds >= 0 && double(frame->timestamp_ns - first_ns) * 1e-9 >= options.max_seconds) {
      break;
    }
    if (!frame->problem.empty()) {
      spdlog::warn("record: frame {}: {}", frame->index, frame->problem);
      ++summary.problems;
    }
    recordings::PlusFrame f;
    f.fields.emplace_back("FrameNumber", std::to_string(frame->index));
    f.fields.emplace_back("Timestamp", fmt::format("{:.6f}", double(frame->timestamp_ns) * 1e-9));
    const bool image = !frame->image.empty() && frame->image.type() == CV_8UC3 &&
                       (seq.width == 0 || (frame->image.cols == seq.width && frame->image.rows == seq.height));
    if (image && seq.width == 0) {
      seq.width = frame->image.cols;
      seq.height = frame->image.rows;
      write_black(blank_before_size);
    }
    if (image) {
      cv::Mat rgb;
      cv::cvtColor(frame->image, rgb, cv::COLOR_BGR2RGB);
      for (int r = 0; r < rgb.rows; ++r) std::fwrite(rgb.ptr(r), 1, size_t(rgb.cols) * 3, pixels);
    } else if (seq.width > 0) {
      write_black(1);
    } else {
      ++blank_before_size;
    }
    f.fields.emplace_back("ImageStatus", image ? "OK" : "INVALID");
    for (const TruePose& pose : frame->truth) {
      // A board's pose in the camera; a sequence's own transform keeps its name.
      std::string name = recordings::plus_tool_name(pose.board);
      if (name.find("To") == std::string::npos) name += "ToCamera";
      f.fields.emplace_back(name + "Transform", recordings::plus_matrix_text(pose.T_cam_board.matrix()));
      f.fields.emplace_back(name + "TransformStatus", "OK");
      ++summary.truth_rows;
    }
    seq.frames.push_back(std::move(f));
    ++summary.frames;
    if (options.max_frames >= 0 && summary.frames >= options.max_frames) break;
  }
  if (std::fflush(pixels) != 0 || std::ferror(pixels)) {
    throw Error(path + ": cannot write the sequence's image frames");
  }
  std::fclose(pixels);
  pixels = nullptr;
  // The header, then the staged pixels, through the file's own temporary.
  PendingFile out(path);
  {
    std::ofstream o(out.temporary(), std::ios::binary);
    const std::string header = recordings::plus_sequence_header(seq);
    o.write(header.data(), std::streamsize(header.size()));
    if (seq.width > 0) {
      std::ifstream in(scratch.temporary(), std::ios::binary);
      o << in.rdbuf();
    }
    o.flush();
    if (!o) throw Error(path + ": cannot write the sequence file");
  }
  out.commit();
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return summary;
}

}  // namespace crepuscular::tracking
