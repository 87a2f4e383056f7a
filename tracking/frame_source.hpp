// Frame sources: a V4L2 camera, a recording replay, or synthetic frames with ground truth.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <opencv2/core.hpp>

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
};

class FrameSource {
 public:
  virtual ~FrameSource() = default;
  // The next frame, or nullopt at the end of the stream.
  virtual std::optional<Frame> next() = 0;
  virtual std::string describe() const = 0;
};

// "v4l2:/dev/video0?width=1280&height=720&fps=60", "recording:DIR[?realtime=1&loop=1]",
// "synthetic:SCENE.json". Errors name the source and the problem.
std::unique_ptr<FrameSource> open_frame_source(const std::string& uri);

}  // namespace crepuscular::tracking
