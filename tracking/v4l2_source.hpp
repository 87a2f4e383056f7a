// V4L2 camera source: memory-mapped streaming of MJPEG or YUYV frames, with reconnection when the
// device disappears and returns (a USB cable pulled and plugged back in the operating room).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "tracking/frame_source.hpp"

namespace crepuscular::tracking {

struct V4l2Options {
  int width = 1280;
  int height = 720;
  double fps = 30;
  std::string format = "auto";  // "mjpeg", "yuyv" or "auto" (MJPEG if the camera offers it)
  int buffers = 4;              // memory-mapped buffers (2 to 32)
  double timeout_s = 2.0;       // no frame for this long: the device is treated as lost
  double max_backoff_s = 2.0;   // reconnection attempts start at 0.1 s and double up to this
};

// Options from a source URI's key=value pairs (width, height, fps, format, buffers, timeout);
// throws Error naming the URI and the option for unknown keys or values out of range.
V4l2Options parse_v4l2_options(const std::string& uri,
                               const std::vector<std::pair<std::string, std::string>>& options);

// Opens the device and starts streaming. Throws Error when the device is missing or cannot capture
// (the URI and the system's reason in the message). Once open, a device that disappears is
// reopened with back-off: meanwhile next() returns frames with an empty image and a problem
// ("camera disconnected, reconnecting"), and the first frame after it carries a note and an index
// that skips the frames the gap would have held.
std::unique_ptr<FrameSource> open_v4l2_source(const std::string& device,
                                              const V4l2Options& options);

// Format conversions of one V4L2 buffer, exposed for tests. Never throw: a bad buffer gives an
// empty image and a problem.
// YUYV 4:2:2 (Y0 U Y1 V, bytes_per_line >= 2 * width) -> BGR (OpenCV's COLOR_YUV2BGR_YUYV, BT.601).
cv::Mat yuyv_to_bgr(const uint8_t* data, size_t size, int width, int height,
                    size_t bytes_per_line, std::string* problem);
// MJPEG (one JPEG per buffer) -> BGR; a truncated or corrupt JPEG gives a problem.
cv::Mat mjpeg_to_bgr(const uint8_t* data, size_t size, std::string* problem);

}  // namespace crepuscular::tracking
