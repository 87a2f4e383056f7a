// AprilTag detection: the one wrapper around libapriltag (nobody else includes its C header).
// Pixels follow OpenCV's convention, as calibration::CameraModel does: (0,0) is the centre of the
// top-left pixel.
#pragma once

#include <Eigen/Core>
#include <array>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

namespace crepuscular::tracking {

struct DetectorOptions {
  std::string family = "tag36h11";  // tag36h11, tag25h9, tag16h5, tagStandard41h12, ...
  double decimate = 2.0;            // quad detection on an image decimated by this factor
  int threads = 2;                  // worker threads of libapriltag
  double blur_sigma = 0.0;          // Gaussian blur before quad detection (px); 0 = none
  double sharpening = 0.25;         // decode sharpening of libapriltag
  bool refine_edges = true;         // snap quad edges to strong gradients at full resolution
  int max_hamming = 2;              // bits libapriltag may correct per tag (0..2); fewer: fewer
                                    // false detections, more missed damaged tags
};

// One detected tag. corners are in libapriltag's order (apriltag_detection_t::p: counter-clockwise
// in the image as seen by the camera, starting bottom-left of the upright tag), the order in which
// tracking::BoardTag stores its corners.
struct Detection {
  int id = 0;
  std::array<Eigen::Vector2d, 4> corners;  // pixels
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  double decision_margin = 0;  // average distance of the data bits from the threshold (grey levels)
  int hamming = 0;             // bits corrected
};

class TagDetector {
 public:
  // Throws Error for an unknown family or options out of range.
  explicit TagDetector(const DetectorOptions& options = {});
  ~TagDetector();
  TagDetector(const TagDetector&) = delete;
  TagDetector& operator=(const TagDetector&) = delete;

  const DetectorOptions& options() const { return options_; }

  // All tags of the family in the image (8- or 16-bit grey, BGR or BGRA; 16-bit as grey_8bit
  // maps it). An empty image gives no detections. Family tag36h11b2 (Kalibr's aprilgrids, whose
  // black corner squares touch the tags): tags are searched where white is grown by 1 px at the
  // saddle points (tag and square come apart there), then on the image itself; their corners are
  // refined on the image (cv::cornerSubPix at the tag/corner-square saddle). About twice the time.
  std::vector<Detection> detect(const cv::Mat& image);

  // Tags searched only inside the given rectangles (clipped to the image; overlapping rectangles
  // are merged first, so a tag is reported once). Corners are in full-image pixels.
  std::vector<Detection> detect(const cv::Mat& image, std::vector<cv::Rect> regions);

  // Merges rectangles that overlap until none do; the result covers the union of the inputs.
  static std::vector<cv::Rect> merge_regions(std::vector<cv::Rect> regions);

 private:
  std::vector<Detection> detect_grey(const cv::Mat& grey, const cv::Point& offset);

  struct Impl;
  DetectorOptions options_;
  std::unique_ptr<Impl> impl_;
};

// The image as 8-bit grey: colour converted to grey; 16-bit images mapped linearly from their own
// range (recordings::to_8bit_by_range) to 0..255, so that 10- or
// 12-bit data in 16-bit words keep their contrast (measured better than >> 8 on 12-bit frames in
// tests/tracking/kalibr_test.cpp). Throws Error for other types.
cv::Mat grey_8bit(const cv::Mat& image);

// The family names TagDetector accepts.
std::vector<std::string> tag_family_names();

}  // namespace crepuscular::tracking
