// The synthetic scene as a FrameSource (apart from the renderer, so that programs rendering frames
// in memory need no image codecs).
#include <algorithm>
#include <vector>

#include <opencv2/imgcodecs.hpp>

#include "recordings/recording.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::tracking {

namespace {

class SyntheticSource : public FrameSource {
 public:
  SyntheticSource(SyntheticScene scene, std::string description)
      : renderer_(std::move(scene)), description_(std::move(description)) {
    for (int64_t f : renderer_.scene().dropped_frames) dropped_.push_back(f);
  }

  std::optional<Frame> next() override {
    const SyntheticScene& s = renderer_.scene();
    while (next_ < s.frame_count &&
           std::find(dropped_.begin(), dropped_.end(), next_) != dropped_.end()) {
      ++next_;
    }
    if (next_ >= s.frame_count) return std::nullopt;
    Frame f;
    f.index = next_;
    f.timestamp_ns = renderer_.timestamp_ns_of(next_);
    cv::Mat image = renderer_.render(next_, &f.truth);
    if (std::find(s.corrupt_frames.begin(), s.corrupt_frames.end(), next_) !=
        s.corrupt_frames.end()) {
      // A JPEG cut short, as a camera delivers when its USB transfer breaks off.
      std::vector<uint8_t> jpeg;
      cv::imencode(".jpg", image, jpeg, {cv::IMWRITE_JPEG_QUALITY, 90});
      jpeg.resize(jpeg.size() * 3 / 5);
      f.image = recordings::decode_image(jpeg, &f.problem);
      f.encoded = std::move(jpeg);
      f.encoded_format = "jpg";
    } else {
      f.image = image;
    }
    ++next_;
    return f;
  }

  std::string describe() const override { return description_; }
  std::optional<calibration::CameraModel> camera() const override {
    return renderer_.scene().camera;
  }

 private:
  SyntheticRenderer renderer_;
  std::string description_;
  std::vector<int64_t> dropped_;
  int64_t next_ = 0;
};

}  // namespace

std::unique_ptr<FrameSource> make_synthetic_source(SyntheticScene scene,
                                                   const std::string& description) {
  return std::make_unique<SyntheticSource>(std::move(scene), description);
}

std::unique_ptr<FrameSource> open_synthetic_source(const std::string& scene_path) {
  if (scene_path == "builtin") {
    return make_synthetic_source(builtin_scene(), "synthetic:builtin (built-in guidance scene)");
  }
  return make_synthetic_source(read_scene(scene_path), "synthetic:" + scene_path);
}

}  // namespace crepuscular::tracking
