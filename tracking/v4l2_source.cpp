// V4L2 capture through ioctl and memory-mapped buffers; MJPEG and YUYV; reconnection.
#include "tracking/v4l2_source.hpp"

#include <errno.h>
#include <fcntl.h>
#include <linux/videodev2.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/select.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <thread>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "recordings/recording.hpp"

namespace crepuscular::tracking {

namespace {

int xioctl(int fd, unsigned long request, void* arg) {
  int r;
  do {
    r = ::ioctl(fd, request, arg);
  } while (r == -1 && errno == EINTR);
  return r;
}

std::string fourcc_name(uint32_t f) {
  std::string s(4, ' ');
  for (int i = 0; i < 4; ++i) s[size_t(i)] = char((f >> (8 * i)) & 0xFF);
  return s;
}

int64_t monotonic_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

class V4l2Source : public FrameSource {
 public:
  V4l2Source(std::string device, V4l2Options options)
      : device_(std::move(device)), options_(std::move(options)) {
    std::string why;
    if (!open_device(&why)) throw Error("v4l2:" + device_ + ": " + why);
    spdlog::info("v4l2:{}: streaming {}x{} {} at {} fps ({} buffers)", device_, width_, height_,
                 fourcc_name(fourcc_), options_.fps, buffers_.size());
  }
  ~V4l2Source() override { close_device(); }

  std::string describe() const override {
    return "v4l2:" + device_ + " (" + std::to_string(width_) + "x" + std::to_string(height_) + " " +
           fourcc_name(fourcc_) + ")";
  }

  std::optional<Frame> next() override {
    if (fd_ < 0) return reconnect_step();
    std::string why;
    std::optional<Frame> f = capture(&why);
    if (f) return f;
    // The device stopped delivering: treat it as gone and start reconnecting.
    spdlog::warn("v4l2:{}: {}; reconnecting", device_, why);
    close_device();
    lost_at_ns_ = monotonic_ns();
    backoff_s_ = 0.1;
    Frame lost;
    lost.index = ++index_;
    lost.timestamp_ns = lost_at_ns_;
    lost.problem = "camera " + device_ + " lost (" + why + "); reconnecting";
    return lost;
  }

 private:
  // One reconnection attempt after the back-off; a frame that reports the gap either way.
  std::optional<Frame> reconnect_step() {
    std::this_thread::sleep_for(std::chrono::duration<double>(backoff_s_));
    backoff_s_ = std::min(options_.max_backoff_s, backoff_s_ * 2.0);
    const int64_t now = monotonic_ns();
    const double gap_s = double(now - lost_at_ns_) * 1e-9;
    std::string why;
    if (open_device(&why)) {
      std::optional<Frame> f = capture(&why);
      if (f) {
        // Frames the gap would have held are counted as dropped.
        f->index = index_ + std::max<int64_t>(1, std::llround(gap_s * options_.fps));
        index_ = f->index;
        f->note = "camera " + device_ + " reconnected after " + std::to_string(gap_s) + " s";
        spdlog::info("v4l2:{}: {}", device_, f->note);
        return f;
      }
      close_device();
    }
    Frame lost;
    lost.index = ++index_;
    lost.timestamp_ns = now;
    lost.problem = "camera " + device_ + " disconnected for " + std::to_string(gap_s) +
                   " s; reconnecting (" + why + ")";
    return lost;
  }

  bool open_device(std::string* why) {
    fd_ = ::open(device_.c_str(), O_RDWR | O_NONBLOCK);
    if (fd_ < 0) {
      *why = std::string("cannot open (") + std::strerror(errno) + ")";
      return false;
    }
    v4l2_capability cap{};
    if (xioctl(fd_, VIDIOC_QUERYCAP, &cap) < 0) {
      *why = std::string("not a V4L2 device (") + std::strerror(errno) + ")";
      close_device();
      return false;
    }
    if (!(cap.capabilities & V4L2_CAP_VIDEO_CAPTURE) || !(cap.capabilities & V4L2_CAP_STREAMING)) {
      *why = "device cannot capture video by streaming";
      close_device();
      return false;
    }
    std::vector<uint32_t> formats;
    if (options_.format == "mjpeg" || options_.format == "auto") formats.push_back(V4L2_PIX_FMT_MJPEG);
    if (options_.format == "yuyv" || options_.format == "auto") formats.push_back(V4L2_PIX_FMT_YUYV);
    bool set = false;
    for (uint32_t want : formats) {
      v4l2_format fmt{};
      fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      fmt.fmt.pix.width = uint32_t(options_.width);
      fmt.fmt.pix.height = uint32_t(options_.height);
      fmt.fmt.pix.pixelformat = want;
      fmt.fmt.pix.field = V4L2_FIELD_NONE;
      if (xioctl(fd_, VIDIOC_S_FMT, &fmt) < 0) continue;
      if (fmt.fmt.pix.pixelformat != want) continue;
      fourcc_ = want;
      width_ = int(fmt.fmt.pix.width);
      height_ = int(fmt.fmt.pix.height);
      bytes_per_line_ = fmt.fmt.pix.bytesperline;
      set = true;
      break;
    }
    if (!set) {
      *why = "the camera offers neither MJPEG nor YUYV (format=" + options_.format + ")";
      close_device();
      return false;
    }
    if (width_ != options_.width || height_ != options_.height) {
      spdlog::warn("v4l2:{}: asked for {}x{}, the camera gives {}x{}", device_, options_.width,
                   options_.height, width_, height_);
    }
    v4l2_streamparm parm{};
    parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    parm.parm.capture.timeperframe.numerator = 1000;
    parm.parm.capture.timeperframe.denominator = uint32_t(std::lround(options_.fps * 1000.0));
    if (xioctl(fd_, VIDIOC_S_PARM, &parm) < 0) {
      spdlog::warn("v4l2:{}: cannot set {} fps ({})", device_, options_.fps, std::strerror(errno));
    }
    v4l2_requestbuffers req{};
    req.count = uint32_t(options_.buffers);
    req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    req.memory = V4L2_MEMORY_MMAP;
    if (xioctl(fd_, VIDIOC_REQBUFS, &req) < 0 || req.count < 2) {
      *why = std::string("memory-mapped streaming refused (") + std::strerror(errno) + ")";
      close_device();
      return false;
    }
    for (uint32_t i = 0; i < req.count; ++i) {
      v4l2_buffer buf{};
      buf.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      buf.memory = V4L2_MEMORY_MMAP;
      buf.index = i;
      if (xioctl(fd_, VIDIOC_QUERYBUF, &buf) < 0) {
        *why = std::string("VIDIOC_QUERYBUF failed (") + std::strerror(errno) + ")";
        close_device();
        return false;
      }
      void* p = ::mmap(nullptr, buf.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_, buf.m.offset);
      if (p == MAP_FAILED) {
        *why = std::string("mmap failed (") + std::strerror(errno) + ")";
        close_device();
        return false;
      }
      buffers_.push_back({p, buf.length});
      if (xioctl(fd_, VIDIOC_QBUF, &buf) < 0) {
        *why = std::string("VIDIOC_QBUF failed (") + std::strerror(errno) + ")";
        close_device();
        return false;
      }
    }
    v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (xioctl(fd_, VIDIOC_STREAMON, &type) < 0) {
      *why = std::string("VIDIOC_STREAMON failed (") + std::strerror(errno) + ")";
      close_device();
      return false;
    }
    return true;
  }

  void close_device() {
    if (fd_ >= 0) {
      v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      xioctl(fd_, VIDIOC_STREAMOFF, &type);
    }
    for (const auto& b : buffers_) ::munmap(b.first, b.second);
    buffers_.clear();
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
  }

  // Waits for and converts one frame; nullopt (with *why) when the device fails or times out.
  std::optional<Frame> capture(std::string* why) {
    fd_set fds;
    FD_ZERO(&fds);
    FD_SET(fd_, &fds);
    timeval tv{};
    tv.tv_sec = long(options_.timeout_s);
    tv.tv_usec = long((options_.timeout_s - double(tv.tv_sec)) * 1e6);
    const int r = ::select(fd_ + 1, &fds, nullptr, nullptr, &tv);
    if (r <= 0) {
      *why = r == 0 ? "no frame for " + std::to_string(options_.timeout_s) + " s"
                    : std::string("select failed (") + std::strerror(errno) + ")";
      return std::nullopt;
    }
    v4l2_buffer buf{};
    buf.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    buf.memory = V4L2_MEMORY_MMAP;
    if (xioctl(fd_, VIDIOC_DQBUF, &buf) < 0) {
      *why = std::string("VIDIOC_DQBUF failed (") + std::strerror(errno) + ")";
      return std::nullopt;
    }
    Frame f;
    f.index = ++index_;
    // The driver's capture time (CLOCK_MONOTONIC for UVC cameras), else the time of arrival.
    const int64_t driver_ns = int64_t(buf.timestamp.tv_sec) * 1000000000LL +
                              int64_t(buf.timestamp.tv_usec) * 1000LL;
    f.timestamp_ns = driver_ns > 0 ? driver_ns : monotonic_ns();
    const uint8_t* data = static_cast<const uint8_t*>(buffers_[buf.index].first);
    const size_t size = std::min<size_t>(buf.bytesused, buffers_[buf.index].second);
    if (buf.flags & V4L2_BUF_FLAG_ERROR) {
      f.problem = "the driver marked the frame as corrupt";
    } else if (fourcc_ == V4L2_PIX_FMT_MJPEG) {
      f.image = mjpeg_to_bgr(data, size, &f.problem);
      f.encoded.assign(data, data + size);
      f.encoded_format = "jpg";
    } else {
      f.image = yuyv_to_bgr(data, size, width_, height_, bytes_per_line_, &f.problem);
    }
    if (xioctl(fd_, VIDIOC_QBUF, &buf) < 0) {
      spdlog::warn("v4l2:{}: VIDIOC_QBUF failed ({})", device_, std::strerror(errno));
    }
    return f;
  }

  std::string device_;
  V4l2Options options_;
  int fd_ = -1;
  uint32_t fourcc_ = 0;
  int width_ = 0, height_ = 0;
  size_t bytes_per_line_ = 0;
  std::vector<std::pair<void*, size_t>> buffers_;
  int64_t index_ = -1;
  int64_t lost_at_ns_ = 0;
  double backoff_s_ = 0.1;
};

}  // namespace

cv::Mat yuyv_to_bgr(const uint8_t* data, size_t size, int width, int height,
                    size_t bytes_per_line, std::string* problem) {
  if (width <= 0 || height <= 0 || (width % 2) != 0) {
    *problem = "YUYV frame size " + std::to_string(width) + "x" + std::to_string(height) +
               " is invalid (width must be even and > 0)";
    return {};
  }
  if (bytes_per_line == 0) bytes_per_line = size_t(width) * 2;
  if (bytes_per_line < size_t(width) * 2 || size < bytes_per_line * size_t(height - 1) + width * 2) {
    *problem = "YUYV frame of " + std::to_string(size) + " bytes is too short for " +
               std::to_string(width) + "x" + std::to_string(height);
    return {};
  }
  const cv::Mat yuyv(height, width, CV_8UC2, const_cast<uint8_t*>(data), bytes_per_line);
  cv::Mat bgr;
  cv::cvtColor(yuyv, bgr, cv::COLOR_YUV2BGR_YUYV);
  problem->clear();
  return bgr;
}

cv::Mat mjpeg_to_bgr(const uint8_t* data, size_t size, std::string* problem) {
  const std::vector<uint8_t> bytes(data, data + size);
  return recordings::decode_image(bytes, problem);
}

V4l2Options parse_v4l2_options(const std::string& uri,
                               const std::vector<std::pair<std::string, std::string>>& options) {
  V4l2Options o;
  for (const auto& option : options) {
    const std::string& key = option.first;  // named, not bound: lambdas capture them (C++17)
    const std::string& value = option.second;
    const auto number = [&](double lo, double hi) {
      char* end = nullptr;
      const double v = std::strtod(value.c_str(), &end);
      if (value.empty() || end != value.c_str() + value.size() || !(v >= lo && v <= hi)) {
        throw Error(uri + ": option " + key + "=" + value + " is invalid, expected a number from " +
                    std::to_string(int(lo)) + " to " + std::to_string(int(hi)));
      }
      return v;
    };
    if (key == "width") {
      o.width = int(number(16, 16384));
    } else if (key == "height") {
      o.height = int(number(16, 16384));
    } else if (key == "fps") {
      o.fps = number(1, 1000);
    } else if (key == "buffers") {
      o.buffers = int(number(2, 32));
    } else if (key == "timeout") {
      o.timeout_s = number(0.05, 60);
    } else if (key == "format") {
      if (value != "mjpeg" && value != "yuyv" && value != "auto") {
        throw Error(uri + ": option format=" + value + " is invalid, expected mjpeg, yuyv or auto");
      }
      o.format = value;
    } else {
      throw Error(uri + ": unknown option '" + key +
                  "', expected width, height, fps, format, buffers or timeout");
    }
  }
  return o;
}

std::unique_ptr<FrameSource> open_v4l2_source(const std::string& device,
                                              const V4l2Options& options) {
  return std::make_unique<V4l2Source>(device, options);
}

}  // namespace crepuscular::tracking
