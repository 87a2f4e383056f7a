// Tag detection: the one wrapper around libapriltag (nobody else includes its C header), and
// OpenCV's ArUco dictionaries through cv::aruco with the same corner order.
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

// The detector's settings: libapriltag's "user-configurable parameters". The defaults were
// measured on apriltag's own test photos and on rendered boards (bench/RESULTS.md, 2026-12-07,
// real cameras and real trackers).
struct DetectorOptions {
  // tag36h11, tag36h11b2 (Kalibr), tag25h9, tag16h5, ..., or an OpenCV dictionary
  // (DICT_6X6_250, ...) found by cv::aruco
  std::string family = "tag36h11";
  // Quad detection on an image decimated by this factor: 2 is about 3x faster than 1 but misses
  // tags smaller than about 25 px and moves corners by tenths of a pixel.
  double decimate = 1.0;
  int threads = 2;           // worker threads of libapriltag
  double blur_sigma = 0.0;   // Gaussian blur before quad detection (px); 0 = none; < 0 sharpens
  double sharpening = 0.25;  // decode sharpening of libapriltag (0 = none)
  // Snap quad edges to the strongest gradient near them: corners nearer the truth at every
  // decimation (rendered tags of 20 to 80 px: mean 0.07-0.17 px instead of 0.14-0.24 px).
  bool refine_edges = true;
  int max_hamming = 2;  // bits libapriltag may correct per tag (0..2); fewer: fewer false
                        // detections, more missed damaged tags

  // Throws Error naming the setting, its value and its range when one is out of range.
  void check() const;
};

// One detected tag. corners are in libapriltag's order (apriltag_detection_t::p: counter-clockwise
// in the image as seen by the camera, starting bottom-left of the upright tag), the order in which
// tracking::BoardTag stores its corners.
struct Detection {
  std::string family;  // the family the tag was decoded in
  int id = 0;
  std::array<Eigen::Vector2d, 4> corners;  // pixels
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  double decision_margin = 0;  // average distance of the data bits from the threshold (grey levels)
                               // (0 for OpenCV dictionaries: cv::aruco reports none)
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


// The tags of several families at once (those of a set of boards): one TagDetector per family,
// each detection naming its family. Throws Error as TagDetector does, or for no family.
class FamilyDetector {
 public:
  FamilyDetector(const DetectorOptions& options, std::vector<std::string> families);

  const std::vector<std::string>& families() const { return families_; }

  // As TagDetector::detect, the detections of every family in the order of families().
  std::vector<Detection> detect(const cv::Mat& image);
  std::vector<Detection> detect(const cv::Mat& image, const std::vector<cv::Rect>& regions);

 private:
  std::vector<std::string> families_;
  std::vector<std::unique_ptr<TagDetector>> detectors_;
};

// Tags of any of `families` in one pass of libapriltag over the image (no bit correction, quads
// found at half resolution): to tell which family a board that was not found is printed in.
// Unknown family names are skipped.
std::vector<Detection> detect_families(const cv::Mat& image,
                                       const std::vector<std::string>& families);

// The family names TagDetector accepts (libapriltag's families, then OpenCV's dictionaries).
std::vector<std::string> tag_family_names();

}  // namespace crepuscular::tracking
