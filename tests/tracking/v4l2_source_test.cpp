// Tests of the V4L2 source (tracking/v4l2_source.hpp) without a camera: YUYV and MJPEG buffer
// conversion against hand-computed pixels and OpenCV's encoder, corrupt and short buffers, option
// parsing and the error paths of opening (missing device, a file that is no V4L2 device).
// Not run here (no camera on these machines): streaming, format negotiation and reconnection.
#include "tracking/v4l2_source.hpp"

#include <gtest/gtest.h>

#include <string>
#include <vector>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"

namespace crepuscular::tracking {
namespace {

using test::expect_error_containing;

// BT.601 with video range, as cameras send YUYV:
//   R = 1.164 (Y - 16) + 1.596 (V - 128)
//   G = 1.164 (Y - 16) - 0.391 (U - 128) - 0.813 (V - 128)
//   B = 1.164 (Y - 16) + 2.018 (U - 128)
TEST(V4l2Source, YuyvToBgrMatchesHandComputedPixels) {
  // Two rows of 4 pixels (2 macropixels each), with 4 padding bytes per row (bytes_per_line 12).
  // Row 0: pure red (Y 81, U 90, V 240) | mid grey (Y 126, U 128, V 128), Y1 differs from Y0.
  // Row 1: blue-ish (Y 41, U 240, V 110) | white (Y 235, U 128, V 128).
  const std::vector<uint8_t> buf = {81,  90,  81,  240, 126, 128, 140, 128, 0, 0, 0, 0,
                                    41,  240, 41,  110, 235, 128, 235, 128, 0, 0, 0, 0};
  std::string problem;
  const cv::Mat bgr = yuyv_to_bgr(buf.data(), buf.size(), 4, 2, 12, &problem);
  ASSERT_TRUE(problem.empty()) << problem;
  ASSERT_EQ(bgr.size(), cv::Size(4, 2));
  const auto expect_pixel = [&](int x, int y, double Y, double U, double V) {
    const double r = 1.164 * (Y - 16) + 1.596 * (V - 128);
    const double g = 1.164 * (Y - 16) - 0.391 * (U - 128) - 0.813 * (V - 128);
    const double b = 1.164 * (Y - 16) + 2.018 * (U - 128);
    const auto clamp = [](double v) { return std::min(255.0, std::max(0.0, v)); };
    const cv::Vec3b p = bgr.at<cv::Vec3b>(y, x);
    EXPECT_NEAR(p[0], clamp(b), 1.0) << "B at " << x << "," << y;
    EXPECT_NEAR(p[1], clamp(g), 1.0) << "G at " << x << "," << y;
    EXPECT_NEAR(p[2], clamp(r), 1.0) << "R at " << x << "," << y;
  };
  expect_pixel(0, 0, 81, 90, 240);
  expect_pixel(1, 0, 81, 90, 240);
  expect_pixel(2, 0, 126, 128, 128);
  expect_pixel(3, 0, 140, 128, 128);
  expect_pixel(0, 1, 41, 240, 110);
  expect_pixel(3, 1, 235, 128, 128);
  // Red by the formula: R 254, G 0, B 0.
  EXPECT_GE(bgr.at<cv::Vec3b>(0, 0)[2], 253);
  EXPECT_LE(bgr.at<cv::Vec3b>(0, 0)[1], 1);
}

TEST(V4l2Source, ShortOrOddYuyvBuffersAreProblems) {
  std::vector<uint8_t> buf(4 * 2 * 2 - 1, 128);
  std::string problem;
  EXPECT_TRUE(yuyv_to_bgr(buf.data(), buf.size(), 4, 2, 0, &problem).empty());
  EXPECT_NE(problem.find("too short"), std::string::npos) << problem;
  EXPECT_TRUE(yuyv_to_bgr(buf.data(), buf.size(), 3, 2, 0, &problem).empty());
  EXPECT_NE(problem.find("even"), std::string::npos) << problem;
}

TEST(V4l2Source, MjpegBufferDecodesAndCorruptOneIsAProblem) {
  cv::Mat img(48, 64, CV_8UC3, cv::Scalar(30, 160, 220));
  cv::rectangle(img, cv::Rect(10, 10, 20, 20), cv::Scalar(255, 255, 255), cv::FILLED);
  std::vector<uint8_t> jpeg;
  cv::imencode(".jpg", img, jpeg, {cv::IMWRITE_JPEG_QUALITY, 95});
  std::string problem;
  const cv::Mat out = mjpeg_to_bgr(jpeg.data(), jpeg.size(), &problem);
  ASSERT_TRUE(problem.empty()) << problem;
  ASSERT_EQ(out.size(), img.size());
  // The same pixels as OpenCV's own decoder gives, and close to what was encoded.
  EXPECT_EQ(cv::norm(out, cv::imdecode(jpeg, cv::IMREAD_COLOR), cv::NORM_INF), 0.0);
  EXPECT_GT(cv::PSNR(out, img), 30.0);
  // A transfer cut short.
  EXPECT_TRUE(mjpeg_to_bgr(jpeg.data(), jpeg.size() / 2, &problem).empty());
  EXPECT_NE(problem.find("corrupt JPEG"), std::string::npos) << problem;
  // Garbage.
  std::vector<uint8_t> garbage(1000, 0x55);
  EXPECT_TRUE(mjpeg_to_bgr(garbage.data(), garbage.size(), &problem).empty());
  EXPECT_FALSE(problem.empty());
  EXPECT_TRUE(mjpeg_to_bgr(garbage.data(), 0, &problem).empty());
}

// Many UVC cameras send MJPEG frames without Huffman tables (DHT segments), relying on the standard
// tables of the JPEG specification; the decoder must supply them.
TEST(V4l2Source, MjpegWithoutHuffmanTablesDecodes) {
  cv::Mat img(48, 64, CV_8UC3, cv::Scalar(90, 20, 200));
  cv::circle(img, cv::Point(30, 20), 12, cv::Scalar(250, 250, 250), cv::FILLED);
  std::vector<uint8_t> jpeg;
  cv::imencode(".jpg", img, jpeg);
  std::vector<uint8_t> mjpeg(jpeg.begin(), jpeg.begin() + 2);  // SOI
  int removed = 0;
  for (size_t i = 2; i + 4 <= jpeg.size();) {
    ASSERT_EQ(jpeg[i], 0xFF);
    const uint8_t marker = jpeg[i + 1];
    if (marker == 0xDA) {  // start of scan: the rest is entropy-coded data and EOI
      mjpeg.insert(mjpeg.end(), jpeg.begin() + long(i), jpeg.end());
      break;
    }
    const size_t length = size_t(jpeg[i + 2]) << 8 | jpeg[i + 3];
    if (marker == 0xC4) {
      ++removed;
    } else {
      mjpeg.insert(mjpeg.end(), jpeg.begin() + long(i), jpeg.begin() + long(i + 2 + length));
    }
    i += 2 + length;
  }
  ASSERT_GT(removed, 0);
  std::string problem;
  const cv::Mat out = mjpeg_to_bgr(mjpeg.data(), mjpeg.size(), &problem);
  ASSERT_TRUE(problem.empty()) << problem;
  EXPECT_EQ(cv::norm(out, cv::imdecode(jpeg, cv::IMREAD_COLOR), cv::NORM_INF), 0.0);
}

TEST(V4l2Source, OptionsAreParsedAndCheckedAgainstRanges) {
  const V4l2Options o = parse_v4l2_options(
      "v4l2:/dev/video0", {{"width", "640"}, {"height", "480"}, {"fps", "60"}, {"format", "yuyv"}});
  EXPECT_EQ(o.width, 640);
  EXPECT_EQ(o.height, 480);
  EXPECT_DOUBLE_EQ(o.fps, 60);
  EXPECT_EQ(o.format, "yuyv");
  expect_error_containing([] { parse_v4l2_options("v4l2:x", {{"width", "abc"}}); },
                          {"v4l2:x", "width=abc"});
  expect_error_containing([] { parse_v4l2_options("v4l2:x", {{"fps", "0"}}); }, {"fps=0"});
  expect_error_containing([] { parse_v4l2_options("v4l2:x", {{"format", "h264"}}); },
                          {"format=h264", "mjpeg"});
  expect_error_containing([] { parse_v4l2_options("v4l2:x", {{"colour", "1"}}); },
                          {"unknown option 'colour'"});
}

TEST(V4l2Source, MissingDeviceAndNonCameraAreClearErrors) {
  expect_error_containing([] { open_v4l2_source("/dev/video_does_not_exist", V4l2Options{}); },
                          {"v4l2:/dev/video_does_not_exist", "cannot open", "No such file"});
  expect_error_containing([] { open_v4l2_source("/dev/null", V4l2Options{}); },
                          {"v4l2:/dev/null", "not a V4L2 device"});
}

}  // namespace
}  // namespace crepuscular::tracking
