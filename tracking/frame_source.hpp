// Frame sources: a V4L2 camera, a recording replay, or synthetic frames with ground truth.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <opencv2/core.hpp>

#include "calibration/camera_model.hpp"

namespace crepuscular::tracking {

// Ground-truth pose of one board in one synthetic frame (T_cam_board, mm).
struct TruePose {
  std::string board;
  Eigen::Isometry3d T_cam_board = Eigen::Isometry3d::Identity();
};

struct Frame {
  int64_t index = 0;          // running number from the source (gaps mean dropped frames)
  int64_t timestamp_ns = 0;   // capture time
  cv::Mat image;              // BGR 8-bit; empty when the frame could not be decoded
  std::string problem;        // why image is empty (corrupt JPEG, ...), else empty
  std::vector<TruePose> truth;  // synthetic sources only
  std::vector<uint8_t> encoded;  // the compressed bytes as received (MJPEG camera, recording,
                                 // corrupt synthetic frame), else empty; `record` stores them as-is
  std::string encoded_format;    // "jpg" or "png" when encoded is set
  std::string note;              // an event worth logging (e.g. "camera reconnected after 2.1 s")
};

class FrameSource {
 public:
  virtual ~FrameSource() = default;
  // The next frame, or nullopt at the end of the stream.
  virtual std::optional<Frame> next() = 0;
  virtual std::string describe() const = 0;
  // The camera model that goes with the frames when the source knows it (synthetic scenes, a
  // recording with camera.yaml), else nullopt.
  virtual std::optional<calibration::CameraModel> camera() const { return std::nullopt; }
};

// "v4l2:/dev/video0?width=1280&height=720&fps=60", "recording:DIR[?realtime=1&loop=1]",
// "synthetic:SCENE.json" or "synthetic:builtin" (the built-in guidance scene). Errors name the
// source and the problem.
std::unique_ptr<FrameSource> open_frame_source(const std::string& uri);

// A source URI split into scheme, path and options: "v4l2:/dev/video0?width=640&fps=30" ->
// {"v4l2", "/dev/video0", {{"width", "640"}, {"fps", "30"}}}. Throws Error for a URI without a
// scheme or a malformed option.
struct SourceUri {
  std::string scheme;
  std::string path;
  std::vector<std::pair<std::string, std::string>> options;
};
SourceUri parse_source_uri(const std::string& uri);

// Replays a recording folder (recordings/recording.hpp). realtime: sleep so that frames come at
// their recorded intervals; loop: start again at the end (frame numbers and timestamps keep
// increasing). Frames that are missing or corrupt come with `problem` set; ground truth, when the
// recording has it, comes with every frame.
std::unique_ptr<FrameSource> open_recording_source(const std::string& dir, bool realtime = false,
                                                   bool loop = false);

// Recording a source into a recording folder (`crepuscular record`, `crepuscular synth`).
struct RecordOptions {
  int64_t max_frames = -1;      // stop after this many frames (-1: until the source ends)
  double max_seconds = -1;      // stop after this much capture time (-1: no limit)
  std::string image_format = "jpg";  // jpg or png; frames the source delivers as JPEG bytes
                                     // (MJPEG cameras, recordings, corrupt frames) are stored as
                                     // received when the format is jpg
  int jpeg_quality = 95;
  std::string boards_json;      // boards.json text to store with the recording ("" = none)
  std::string plan;             // plan folder this session belongs to ("" = none)
  std::optional<calibration::CameraModel> camera;  // camera.yaml to store; default: the source's
  const std::atomic<bool>* stop = nullptr;  // set (e.g. by Ctrl-C) to end the recording cleanly
};

struct RecordSummary {
  std::string path;             // the final folder
  int64_t frames = 0;           // frames written
  int64_t skipped = 0;          // frames without image data (camera lost, missing file)
  int64_t problems = 0;         // frames written or skipped that came with a problem
  int64_t truth_rows = 0;       // ground-truth rows written
  double seconds = 0;           // wall time
};

// Records frames one at a time into a recording folder: written into out_dir + ".partial"
// (replayable at any moment, also after a crash or kill) and renamed to out_dir by finish().
// Without finish() the .partial folder stays, as after an interrupted recording. Throws Error
// when out_dir or out_dir.partial already exist, or on a write failure.
class FrameRecorder {
 public:
  // with_truth: store ground truth (ground_truth.csv) from the frames. camera: camera.yaml to
  // store (options.camera overrides).
  FrameRecorder(const std::string& out_dir, const std::string& source_description,
                const std::optional<calibration::CameraModel>& camera,
                const RecordOptions& options, bool with_truth);
  ~FrameRecorder();
  FrameRecorder(const FrameRecorder&) = delete;
  FrameRecorder& operator=(const FrameRecorder&) = delete;
  // Appends a frame; false when it was skipped (no image data, or not after the last frame).
  bool add(const Frame& frame);
  const RecordSummary& summary() const;
  RecordSummary finish();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Records `source` into out_dir. The recording is written frame by frame into out_dir + ".partial"
// (replayable at any moment, also after a crash or kill) and renamed to out_dir when it ends.
// Throws Error when out_dir or out_dir.partial already exist, or on a write failure. Ground truth
// (ground_truth.csv) is written when the source's frames carry it; camera.yaml when the source
// knows its camera. Logs progress about once a second.
RecordSummary record_to_folder(FrameSource& source, const std::string& out_dir,
                               const RecordOptions& options);

// The same frames into a PLUS sequence file (.igs.mha, .seq.mha) for 3D Slicer's Sequences module
// and PLUS: colour image frames (RGB, of the first frame's size; a frame without an image, or of
// another size, is black with ImageStatus INVALID), the timestamps, and the frames' poses
// (synthetic truth, a sequence's transforms) as <Board>ToCameraTransform. The pixels are staged
// beside the file while recording; the file appears complete at the end or not at all.
RecordSummary record_to_plus_sequence(FrameSource& source, const std::string& path,
                                      const RecordOptions& options);

}  // namespace crepuscular::tracking
