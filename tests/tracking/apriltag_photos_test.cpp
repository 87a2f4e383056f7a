// apriltag's own detection test on its three real photos (tests/data/apriltag-test-photos): the
// 47 tags found and their corners against the reference, with the reference settings and with
// the project's defaults.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "tracking/detector.hpp"

namespace crepuscular::tracking {
namespace {

const std::string kData = std::string(CREPUSCULAR_TEST_DATA) + "/apriltag-test-photos/";
const char* const kPhotos[] = {"33369213973_9d9bb4cc96_c", "34085369442_304b6bafd9_c",
                               "34139872896_defdb2f8d9_c"};

// The reference corners of one photo, moved to OpenCV's pixel convention: the reference holds
// libapriltag's own coordinates, whose pixel centres are at +0.5 (moved by 0.5 px either way
// the corners lie 0.7 px from ours instead of 0.004 px).
std::vector<std::array<Eigen::Vector2d, 4>> reference(const std::string& photo) {
  std::ifstream in(kData + photo + ".txt");
  std::vector<std::array<Eigen::Vector2d, 4>> out;
  std::string line;
  while (std::getline(in, line)) {
    int id = -1;
    double p[8];
    if (std::sscanf(line.c_str(), "%d, (%lf %lf), (%lf %lf), (%lf %lf), (%lf %lf)", &id, &p[0],
                    &p[1], &p[2], &p[3], &p[4], &p[5], &p[6], &p[7]) != 9) {
      continue;
    }
    std::array<Eigen::Vector2d, 4> c;
    for (int k = 0; k < 4; ++k) c[k] = Eigen::Vector2d(p[2 * k] - 0.5, p[2 * k + 1] - 0.5);
    out.push_back(c);
  }
  return out;
}

Eigen::Vector2d centre(const std::array<Eigen::Vector2d, 4>& c) {
  return 0.25 * (c[0] + c[1] + c[2] + c[3]);
}

struct Agreement {
  int reference = 0, found = 0, extra = 0;
  std::vector<double> errors_px;  // every corner of every tag found
  double mean() const {
    double s = 0;
    for (double e : errors_px) s += e;
    return errors_px.empty() ? 0 : s / double(errors_px.size());
  }
  double max() const {
    return errors_px.empty() ? 0 : *std::max_element(errors_px.begin(), errors_px.end());
  }
  double share_within(double px) const {
    return double(std::count_if(errors_px.begin(), errors_px.end(),
                                [&](double e) { return e <= px; })) /
           double(std::max<size_t>(1, errors_px.size()));
  }
};

// Every tag of the three photos (all id 0) matched to the detection nearest its centre.
Agreement agreement(const DetectorOptions& options) {
  TagDetector detector(options);
  Agreement a;
  for (const char* photo : kPhotos) {
    const cv::Mat image = cv::imread(kData + photo + ".jpg", cv::IMREAD_GRAYSCALE);
    EXPECT_FALSE(image.empty()) << photo;
    const std::vector<Detection> found = detector.detect(image);
    std::vector<bool> used(found.size(), false);
    for (const auto& ref : reference(photo)) {
      ++a.reference;
      int best = -1;
      double best_px = 5.0;  // a detection more than 5 px away is another tag
      for (size_t i = 0; i < found.size(); ++i) {
        const double d = (found[i].center - centre(ref)).norm();
        if (d < best_px) best_px = d, best = int(i);
      }
      if (best < 0) continue;
      used[size_t(best)] = true;
      ++a.found;
      for (int k = 0; k < 4; ++k) a.errors_px.push_back((found[size_t(best)].corners[k] - ref[k]).norm());
    }
    a.extra += int(std::count(used.begin(), used.end(), false));
  }
  return a;
}

// apriltag's test settings: no decimation, no edge refinement, the rest at libapriltag's
// defaults. All 47 tags, nothing else; corners at the reference to 0.1 px as apriltag's own test
// requires, except three of 188 corners (0.11, 0.14 and 0.14 px): the reference was made by a
// newer libapriltag than Debian's 3.3 (libapriltag's own JPEG decoder in place of OpenCV's gives
// the same three, max 0.141 px).
TEST(AprilTagPhotos, ReferenceSettingsFindAll47TagsAtTheReferenceCorners) {
  DetectorOptions o;
  o.decimate = 1.0;
  o.refine_edges = false;
  o.sharpening = 0.25;
  o.blur_sigma = 0.0;
  const Agreement a = agreement(o);
  EXPECT_EQ(a.reference, 47);
  EXPECT_EQ(a.found, 47);
  EXPECT_EQ(a.extra, 0);
  EXPECT_LT(a.mean(), 0.01) << "mean corner error, px";
  EXPECT_GE(a.share_within(0.1), 0.98) << "max " << a.max() << " px";
  EXPECT_LT(a.max(), 0.15);
}

// The project's defaults: full resolution with edge refinement, which puts the corners of rendered
// tags nearer their truth (bench/RESULTS.md, 2026-12-07). On these photos they find 46 of the 47
// tags, and their corners differ from the reference (made without refinement) by 0.37 px on
// average, 2.3 px on the most oblique tag. Decimation 2, libapriltag's faster choice, misses the
// small tags (34).
TEST(AprilTagPhotos, DefaultsFindAllButOneTagWhereDecimationMissesTheSmallOnes) {
  const Agreement defaults = agreement(DetectorOptions{});
  EXPECT_GE(defaults.found, 46);
  EXPECT_EQ(defaults.extra, 0);
  EXPECT_LT(defaults.mean(), 0.45) << "mean corner difference from the reference, px";
  EXPECT_LT(defaults.max(), 2.6);

  DetectorOptions fast;
  fast.decimate = 2.0;
  const Agreement decimated = agreement(fast);
  EXPECT_LT(decimated.found, 40);
}

}  // namespace
}  // namespace crepuscular::tracking
