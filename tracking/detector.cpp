// AprilTag detection through libapriltag (OpenCV's ArUco dictionaries through cv::aruco), full
// frame or inside regions of interest.
#include "tracking/detector.hpp"

#include <apriltag.h>

#include <Eigen/LU>
#include <algorithm>
#include <opencv2/aruco.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "calibration/aruco.hpp"
#include "foundation/error.hpp"
#include "recordings/recording.hpp"
#include "tracking/tag_family.hpp"

namespace crepuscular::tracking {

namespace {

// Where libapriltag puts the centre of the top-left pixel (x and y).
constexpr double kApriltagPixelCentre = 0.5;

// Where the quad's diagonals cross: the image of the tag's centre under any homography.
Eigen::Vector2d diagonal_crossing(const std::array<Eigen::Vector2d, 4>& p) {
  const Eigen::Vector2d d0 = p[2] - p[0], d1 = p[3] - p[1];
  Eigen::Matrix2d A;
  A << d0, -d1;
  if (std::abs(A.determinant()) < 1e-9) return 0.25 * (p[0] + p[1] + p[2] + p[3]);
  const Eigen::Vector2d st = A.inverse() * (p[1] - p[0]);
  return p[0] + st.x() * d0;
}

// libapriltag's detection in OpenCV's pixel convention, shifted by `offset` (where the searched
// image lies in the frame). libapriltag 3.3 places pixel centres at half-integer coordinates
// (the top-left pixel spans 0..1); OpenCV and CameraModel place them at integers. The shift was
// measured against cv::projectPoints and cv::aruco in tests/tracking/detector_test.cpp.
Detection from_apriltag(const apriltag_detection_t& det, const std::string& family,
                        const cv::Point& offset) {
  Detection d;
  d.family = family;
  d.id = det.id;
  d.hamming = det.hamming;
  d.decision_margin = det.decision_margin;
  const double ox = offset.x - kApriltagPixelCentre, oy = offset.y - kApriltagPixelCentre;
  for (int k = 0; k < 4; ++k) d.corners[k] = Eigen::Vector2d(det.p[k][0] + ox, det.p[k][1] + oy);
  d.center = Eigen::Vector2d(det.c[0] + ox, det.c[1] + oy);
  return d;
}

// Markers of an OpenCV dictionary (cv::aruco::detectMarkers; pixel centres at integers already),
// corners turned from cv::aruco's order (clockwise in the image from the marker's top-left) into
// apriltag_detection_t::p order (counter-clockwise from its bottom-left).
std::vector<Detection> detect_aruco(const cv::Mat& grey, const cv::Point& offset,
                                    const cv::Ptr<cv::aruco::Dictionary>& dictionary,
                                    const cv::Ptr<cv::aruco::DetectorParameters>& params) {
  std::vector<std::vector<cv::Point2f>> corners;
  std::vector<int> ids;
  cv::aruco::detectMarkers(grey, dictionary, corners, ids, params);
  std::vector<Detection> out(ids.size());
  for (size_t m = 0; m < ids.size(); ++m) {
    Detection& d = out[m];
    d.id = ids[m];
    for (int k = 0; k < 4; ++k) {
      const cv::Point2f& p = corners[m][size_t(3 - k)];
      d.corners[k] = Eigen::Vector2d(p.x + offset.x, p.y + offset.y);
    }
    d.center = diagonal_crossing(d.corners);  // as libapriltag reports a centre
  }
  return out;
}

// Kalibr's aprilgrids (family tag36h11b2) print a black square in the gap at every tag corner,
// touching the tag there: libapriltag segments tag and squares as one blob and fits no quad.
bool has_corner_squares(const std::string& family) { return family == "tag36h11b2"; }

// Where the image counts as a saddle point: Hessian saddle strength Ixy^2 - Ixx Iyy (Sobel, on
// the image smoothed with sigma 1 px) above (kSaddleContrast * local contrast)^2, the contrast
// being max - min over 7 x 7 px, at least kSaddleMinContrast grey levels. Chosen by measurement on
// rendered Kalibr frames (tests/tracking/kalibr_test.cpp, decimate 1 / 2): 0.3 finds 84 / 83 % of
// the tags, 0.4 89 / 88 %, 0.45 90 / 89 %, 0.5 91 / 88 % with 3 wrong ids at decimate 2. Growing
// white everywhere instead (a plain 3 x 3 max filter) found 55 %: it thins the data cells of small
// tags below what the decoder reads.
constexpr double kSaddleContrast = 0.45;
constexpr double kSaddleMinContrast = 16.0;

// The image with white grown by 1 px (a 3 x 3 max filter) at saddle points, where black regions
// touch at a corner (a tag and its corner square): they come apart there, while the tags' data
// cells (sampled at their centres) and the straight edges stay as they are. libapriltag finds
// quads and decodes on this image.
cv::Mat part_corner_squares(const cv::Mat& grey) {
  cv::Mat f, ixx, iyy, ixy, top, bottom;
  grey.convertTo(f, CV_32F);
  cv::GaussianBlur(f, f, cv::Size(0, 0), 1.0);
  cv::Sobel(f, ixx, CV_32F, 2, 0, 3);
  cv::Sobel(f, iyy, CV_32F, 0, 2, 3);
  cv::Sobel(f, ixy, CV_32F, 1, 1, 3);
  const cv::Mat box = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(7, 7));
  cv::dilate(f, top, box);
  cv::erode(f, bottom, box);
  // saddle > (k * max(contrast, floor))^2, per pixel in one pass.
  cv::Mat saddle_points(grey.size(), CV_8U);
  const float k2 = float(kSaddleContrast * kSaddleContrast);
  const float floor_contrast = float(kSaddleMinContrast);
  for (int y = 0; y < grey.rows; ++y) {
    const float *xx = ixx.ptr<float>(y), *yy = iyy.ptr<float>(y), *xy = ixy.ptr<float>(y);
    const float *hi = top.ptr<float>(y), *lo = bottom.ptr<float>(y);
    uint8_t* m = saddle_points.ptr<uint8_t>(y);
    for (int x = 0; x < grey.cols; ++x) {
      const float c = std::max(hi[x] - lo[x], floor_contrast);
      m[x] = xy[x] * xy[x] - xx[x] * yy[x] > k2 * c * c ? 255 : 0;
    }
  }
  cv::Mat grown;
  cv::dilate(grey, grown, cv::Mat());
  cv::Mat out = grey.clone();
  grown.copyTo(out, saddle_points);
  return out;
}

// Corners (OpenCV pixels) of a tag with corner squares refined on the image (cv::cornerSubPix,
// as Kalibr refines them; window half-width about one cell) as the saddle points where the tag's
// black corner meets its corner square. A corner the refinement moves farther than a quarter cell
// (at least 1 px), or too near the image border for the window, keeps libapriltag's position.
void refine_corner_square_corners(const cv::Mat& grey, std::array<Eigen::Vector2d, 4>& p) {
  double side = 1e30;
  for (size_t i = 0; i < 4; ++i) side = std::min(side, (p[(i + 1) % 4] - p[i]).norm());
  const double cell = side / 10.0;  // the 2-cell-border square spans 10 cells
  const int half = std::clamp(int(std::lround(cell)), 2, 12);
  std::vector<cv::Point2f> start, refined;
  for (const Eigen::Vector2d& q : p) start.emplace_back(float(q.x()), float(q.y()));
  const cv::Rect2f inside(float(half + 1), float(half + 1), float(grey.cols - 2 * half - 3),
                          float(grey.rows - 2 * half - 3));
  for (const cv::Point2f& q : start) {
    if (!inside.contains(q)) return;
  }
  refined = start;
  cv::cornerSubPix(grey, refined, cv::Size(half, half), cv::Size(-1, -1),
                   cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 40, 0.001));
  const double limit = std::max(1.0, 0.25 * cell);
  for (size_t i = 0; i < 4; ++i) {
    if (cv::norm(refined[i] - start[i]) <= limit)
      p[i] = Eigen::Vector2d(refined[i].x, refined[i].y);
  }
}


}  // namespace

struct TagDetector::Impl {
  cv::Ptr<cv::aruco::Dictionary> aruco;  // set for an OpenCV dictionary instead of `family`
  cv::Ptr<cv::aruco::DetectorParameters> aruco_params;
  TagFamilyPtr family{nullptr, nullptr};
  apriltag_detector_t* detector = nullptr;  // destroyed before the family it refers to
  ~Impl() {
    if (detector) apriltag_detector_destroy(detector);
  }
};

void DetectorOptions::check() const {
  const auto range = [](const char* name, double value, double lo, double hi) {
    if (!(value >= lo && value <= hi)) {
      std::ostringstream msg;
      msg << "tag detector: " << name << " " << value << " is out of range; expected " << lo
          << " to " << hi;
      throw Error(msg.str());
    }
  };
  range("decimate", decimate, 1.0, 8.0);
  range("threads", threads, 1, 64);
  range("blur", blur_sigma, -5.0, 5.0);
  range("sharpening", sharpening, 0.0, 2.0);
  range("max_hamming", max_hamming, 0, 2);
}

TagDetector::TagDetector(const DetectorOptions& options)
    : options_(options), impl_(std::make_unique<Impl>()) {
  if (calibration::is_aruco_dictionary(options.family)) {
    impl_->aruco = calibration::aruco_dictionary(options.family);
    impl_->aruco_params = cv::aruco::DetectorParameters::create();
    // Measured on rendered ChArUco boards (tests/tracking/aruco_board_test.cpp): SUBPIX with a
    // 3 px window puts corners 0.23 px (median) from the truth; a 5 px window reaches into the
    // next chessboard square (up to 7 px off), CONTOUR and APRILTAG refinement 0.66 to 0.69 px.
    impl_->aruco_params->cornerRefinementMethod = cv::aruco::CORNER_REFINE_SUBPIX;
    impl_->aruco_params->cornerRefinementWinSize = 3;
  } else {
    try {
      impl_->family = open_tag_family(options.family);
    } catch (const Error& e) {
      throw Error(std::string("tag detector: ") + e.what());
    }
  }
  options.check();
  if (impl_->aruco) return;  // the options below are libapriltag's
  impl_->detector = apriltag_detector_create();
  apriltag_detector_add_family_bits(impl_->detector, impl_->family.get(), options.max_hamming);
  impl_->detector->quad_decimate = static_cast<float>(options.decimate);
  impl_->detector->quad_sigma = static_cast<float>(options.blur_sigma);
  impl_->detector->nthreads = options.threads;
  impl_->detector->decode_sharpening = options.sharpening;
  impl_->detector->refine_edges = options.refine_edges;
}

TagDetector::~TagDetector() = default;

std::vector<Detection> TagDetector::detect_grey(const cv::Mat& grey, const cv::Point& offset) {
  if (impl_->aruco) {
    std::vector<Detection> found = detect_aruco(grey, offset, impl_->aruco, impl_->aruco_params);
    for (Detection& d : found) d.family = options_.family;
    return found;
  }
  std::vector<Detection> out;
  // libapriltag needs room for its quad search; tiny crops hold no decodable tag.
  if (grey.cols < 8 || grey.rows < 8) return out;
  // Tags with corner squares: searched on the parted image, then on the image itself for the tags
  // the parting loses (measured on rendered Kalibr frames: 89 % of the tags found by the first
  // search, 92 % by both).
  const bool corner_squares = has_corner_squares(options_.family);
  std::vector<cv::Mat> searched{corner_squares ? part_corner_squares(grey) : grey};
  if (corner_squares) searched.push_back(grey);
  for (const cv::Mat& quads : searched) {
    const size_t earlier = out.size();
    image_u8_t im{quads.cols, quads.rows, static_cast<int32_t>(quads.step[0]),
                  const_cast<uint8_t*>(quads.ptr<uint8_t>(0))};
    zarray_t* found = apriltag_detector_detect(impl_->detector, &im);
    const int n = zarray_size(found);
    for (int i = 0; i < n; ++i) {
      apriltag_detection_t* det = nullptr;
      zarray_get(found, i, &det);
      const auto same_id = [&](const Detection& e) { return e.id == det->id; };
      if (std::any_of(out.begin(), out.begin() + std::ptrdiff_t(earlier), same_id)) continue;
      Detection d = from_apriltag(*det, options_.family, offset);
      if (corner_squares) {
        const Eigen::Vector2d o(offset.x, offset.y);
        for (Eigen::Vector2d& c : d.corners) c -= o;
        refine_corner_square_corners(grey, d.corners);
        for (Eigen::Vector2d& c : d.corners) c += o;
        d.center = diagonal_crossing(d.corners);
      }
      out.push_back(d);
    }
    apriltag_detections_destroy(found);
  }
  return out;
}

std::vector<Detection> TagDetector::detect(const cv::Mat& image) {
  if (image.empty()) return {};
  if (image.type() == CV_8UC1) return detect_grey(image, {0, 0});
  return detect_grey(grey_8bit(image), {0, 0});
}

cv::Mat grey_8bit(const cv::Mat& image) {
  cv::Mat grey;
  if (image.type() == CV_8UC1 || image.type() == CV_16UC1) {
    grey = image;
  } else if (image.type() == CV_8UC3 || image.type() == CV_16UC3) {
    cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  } else if (image.type() == CV_8UC4 || image.type() == CV_16UC4) {
    cv::cvtColor(image, grey, cv::COLOR_BGRA2GRAY);
  } else {
    throw Error("tag detector: image type " + std::to_string(image.type()) +
                " is not supported; expected 8- or 16-bit grey, BGR or BGRA");
  }
  return recordings::to_8bit_by_range(grey);
}

std::vector<cv::Rect> TagDetector::merge_regions(std::vector<cv::Rect> regions) {
  regions.erase(std::remove_if(regions.begin(), regions.end(),
                               [](const cv::Rect& r) { return r.area() <= 0; }),
                regions.end());
  bool merged = true;
  while (merged) {
    merged = false;
    for (size_t i = 0; i < regions.size() && !merged; ++i) {
      for (size_t j = i + 1; j < regions.size(); ++j) {
        if ((regions[i] & regions[j]).area() > 0) {
          regions[i] |= regions[j];
          regions.erase(regions.begin() + static_cast<std::ptrdiff_t>(j));
          merged = true;
          break;
        }
      }
    }
  }
  return regions;
}

std::vector<Detection> TagDetector::detect(const cv::Mat& image, std::vector<cv::Rect> regions) {
  if (image.empty()) return {};
  const cv::Rect whole(0, 0, image.cols, image.rows);
  for (cv::Rect& r : regions) r &= whole;
  regions = merge_regions(std::move(regions));
  std::vector<Detection> out;
  for (const cv::Rect& r : regions) {
    cv::Mat crop = image(r);
    const std::vector<Detection> found =
        detect_grey(crop.type() == CV_8UC1 ? crop : grey_8bit(crop), r.tl());
    out.insert(out.end(), found.begin(), found.end());
  }
  return out;
}

FamilyDetector::FamilyDetector(const DetectorOptions& options, std::vector<std::string> families)
    : families_(std::move(families)) {
  std::sort(families_.begin(), families_.end());
  families_.erase(std::unique(families_.begin(), families_.end()), families_.end());
  if (families_.empty()) throw Error("tag detector: no tag family to detect");
  for (const std::string& family : families_) {
    DetectorOptions o = options;
    o.family = family;
    detectors_.push_back(std::make_unique<TagDetector>(o));
  }
}

std::vector<Detection> FamilyDetector::detect(const cv::Mat& image) {
  std::vector<Detection> out = detectors_.front()->detect(image);
  for (size_t i = 1; i < detectors_.size(); ++i) {
    std::vector<Detection> more = detectors_[i]->detect(image);
    out.insert(out.end(), more.begin(), more.end());
  }
  return out;
}

std::vector<Detection> FamilyDetector::detect(const cv::Mat& image,
                                              const std::vector<cv::Rect>& regions) {
  std::vector<Detection> out = detectors_.front()->detect(image, regions);
  for (size_t i = 1; i < detectors_.size(); ++i) {
    std::vector<Detection> more = detectors_[i]->detect(image, regions);
    out.insert(out.end(), more.begin(), more.end());
  }
  return out;
}

std::vector<Detection> detect_families(const cv::Mat& image,
                                       const std::vector<std::string>& families) {
  std::vector<Detection> out;
  if (image.empty()) return out;
  cv::Mat grey;
  try {
    grey = grey_8bit(image);
  } catch (const Error&) {
    return out;
  }
  if (grey.cols < 8 || grey.rows < 8) return out;
  std::vector<std::pair<std::string, TagFamilyPtr>> opened;
  for (const std::string& name : families) {
    try {
      opened.emplace_back(name, open_tag_family(name));
    } catch (const Error&) {
    }
  }
  if (opened.empty()) return out;
  apriltag_detector_t* detector = apriltag_detector_create();
  for (auto& [name, family] : opened) apriltag_detector_add_family_bits(detector, family.get(), 0);
  detector->quad_decimate = 2.0f;
  detector->nthreads = 2;
  image_u8_t im{grey.cols, grey.rows, static_cast<int32_t>(grey.step[0]),
                const_cast<uint8_t*>(grey.ptr<uint8_t>(0))};
  zarray_t* found = apriltag_detector_detect(detector, &im);
  for (int i = 0; i < zarray_size(found); ++i) {
    apriltag_detection_t* det = nullptr;
    zarray_get(found, i, &det);
    std::string name;
    for (auto& [candidate, family] : opened) {
      if (family.get() == det->family) name = candidate;
    }
    Detection d = from_apriltag(*det, name, {0, 0});
    out.push_back(d);
  }
  apriltag_detections_destroy(found);
  apriltag_detector_destroy(detector);  // before the families it refers to
  return out;
}

}  // namespace crepuscular::tracking
