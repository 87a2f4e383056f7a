// Tests of recordings (recordings/recording.hpp): write and read back frames, timestamps, ground
// truth and session.json; a recorder killed with SIGKILL leaves a folder that replays up to its last
// complete frame; truncated CSV rows, missing and corrupt frame files are skipped with a problem.
#include "recordings/recording.hpp"

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <thread>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::recordings {
namespace {

namespace fs = std::filesystem;

// A frame whose content identifies it: a gradient plus a bright square at a frame-dependent place.
cv::Mat test_image(int64_t frame) {
  cv::Mat img(120, 160, CV_8UC3);
  for (int y = 0; y < img.rows; ++y) {
    for (int x = 0; x < img.cols; ++x) {
      img.at<cv::Vec3b>(y, x) = cv::Vec3b(uint8_t(x), uint8_t(y * 2), uint8_t((x + y) / 2));
    }
  }
  cv::rectangle(img, cv::Rect(int(10 + 7 * frame) % 140, 20, 15, 15), cv::Scalar(255, 255, 255),
                cv::FILLED);
  return img;
}

PoseRow truth_row(const std::string& board, double z) {
  PoseRow r;
  r.board = board;
  r.t[0] = 1.5;
  r.t[1] = -2.25;
  r.t[2] = z;
  r.q[0] = std::sqrt(0.5);
  r.q[3] = std::sqrt(0.5);
  return r;
}

// Rows that end in a newline, the header excluded: a row still being written is not counted.
size_t count_complete_rows(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto newlines = size_t(std::count(text.begin(), text.end(), '\n'));
  return newlines > 0 ? newlines - 1 : 0;
}

TEST(Recording, WritesAndReadsFramesTimestampsTruthAndSession) {
  const fs::path dir = test::fresh_path("roundtrip");
  SessionInfo info;
  info.source = "synthetic:scene.json";
  info.plan = "plan/";
  info.boards = {{"boards", nlohmann::json::array({{{"name", "patient"}}})}};
  {
    RecordingWriter w(dir.string(), info, "png", 95, true);
    // Frame 2 was dropped: frame numbers 0, 1, 3, 4.
    for (int64_t f : {0, 1, 3, 4}) {
      w.add_frame(f, 1000000000 + f * 33333333, test_image(f),
                  {truth_row("patient", 500.0 + double(f)), truth_row("needle", 300.0)});
    }
    EXPECT_EQ(w.frame_count(), 4);
    w.finish();
  }
  RecordingReader r(dir.string());
  EXPECT_TRUE(r.problems().empty()) << r.problems().front();
  ASSERT_EQ(r.entries().size(), 4u);
  EXPECT_EQ(r.entries()[2].frame, 3);
  EXPECT_EQ(r.entries()[2].timestamp_ns, 1000000000 + 3 * 33333333);
  EXPECT_EQ(r.entries()[2].file, "frames/000003.png");
  for (size_t i = 0; i < 4; ++i) {
    const RecordingReader::Loaded l = r.load(i);
    ASSERT_TRUE(l.problem.empty()) << l.problem;
    // PNG is lossless: the same pixels.
    EXPECT_EQ(cv::norm(l.image, test_image(r.entries()[i].frame), cv::NORM_INF), 0.0) << i;
  }
  ASSERT_TRUE(r.has_ground_truth());
  const std::vector<PoseRow> t3 = r.ground_truth(3);
  ASSERT_EQ(t3.size(), 2u);
  EXPECT_EQ(t3[0].board, "patient");
  EXPECT_EQ(t3[0].timestamp_ns, 1000000000 + 3 * 33333333);
  EXPECT_NEAR(t3[0].t[2], 503.0, 1e-6);
  EXPECT_NEAR(t3[0].t[1], -2.25, 1e-6);
  EXPECT_NEAR(t3[0].q[3], std::sqrt(0.5), 1e-12);
  EXPECT_EQ(t3[1].board, "needle");
  EXPECT_TRUE(r.ground_truth(2).empty());
  EXPECT_EQ(r.session().at("complete"), true);
  EXPECT_EQ(r.session().at("frame_count"), 4);
  EXPECT_EQ(r.session().at("source"), "synthetic:scene.json");
  EXPECT_EQ(r.session().at("ground_truth"), "ground_truth.csv");
  EXPECT_EQ(r.session().at("boards")[0].at("name"), "patient");
  EXPECT_FALSE(r.boards_path().empty());
  EXPECT_TRUE(r.camera_path().empty());  // the caller writes camera.yaml
  // No temporary files are left behind.
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    EXPECT_EQ(e.path().filename().string().rfind(".tmp", 0), std::string::npos) << e.path();
  }
}

TEST(Recording, JpegFramesDecodeCloseToTheOriginal) {
  const fs::path dir = test::fresh_path("jpeg");
  RecordingWriter w(dir.string(), SessionInfo{}, "jpg", 95);
  w.add_frame(0, 0, test_image(0));
  w.finish();
  RecordingReader r(dir.string());
  const RecordingReader::Loaded l = r.load(0);
  ASSERT_TRUE(l.problem.empty()) << l.problem;
  EXPECT_GT(cv::PSNR(l.image, test_image(0)), 35.0);
  EXPECT_EQ(r.entries()[0].file, "frames/000000.jpg");
}

TEST(Recording, WriterRefusesNonEmptyFolderAndDecreasingFrames) {
  const fs::path dir = test::fresh_path("refuse");
  fs::create_directories(dir);
  std::ofstream(dir / "something") << "x";
  EXPECT_THROW(RecordingWriter(dir.string(), SessionInfo{}), Error);
  const fs::path dir2 = test::fresh_path("refuse2");
  RecordingWriter w(dir2.string(), SessionInfo{});
  w.add_frame(5, 0, test_image(0));
  EXPECT_THROW(w.add_frame(5, 1, test_image(0)), Error);
  EXPECT_THROW(RecordingWriter(test::fresh_path("fmt").string(), SessionInfo{}, "bmp"), Error);
}

// The recorder is a child process killed with SIGKILL while it writes as fast as it can.
TEST(Recording, KilledRecorderReplaysUpToItsLastCompleteFrame) {
  const fs::path dir = test::fresh_path("killed");
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    try {
      RecordingWriter w(dir.string(), SessionInfo{}, "jpg", 90, true);
      const cv::Mat img = test_image(1);
      for (int64_t f = 0; f < 1000000; ++f) {
        w.add_frame(f, f * 1000, img, {truth_row("patient", 400.0)});
      }
    } catch (...) {
    }
    _exit(1);  // never return into the test runner from the child
  }
  // Wait until a few frames exist, then kill.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (std::chrono::steady_clock::now() < deadline &&
         (!fs::exists(dir / "frames.csv") || count_complete_rows(dir / "frames.csv") < 30)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  kill(pid, SIGKILL);
  int status = 0;
  waitpid(pid, &status, 0);
  ASSERT_TRUE(WIFSIGNALED(status));

  RecordingReader r(dir.string());
  ASSERT_GE(r.entries().size(), 30u);
  EXPECT_EQ(r.session().at("complete"), false);
  for (size_t i = 0; i < r.entries().size(); ++i) {
    EXPECT_EQ(r.entries()[i].frame, int64_t(i));
    const RecordingReader::Loaded l = r.load(i);
    EXPECT_TRUE(l.problem.empty()) << "frame " << i << ": " << l.problem;
    EXPECT_EQ(r.ground_truth(int64_t(i)).size(), 1u) << "frame " << i;
  }
}

TEST(Recording, TruncatedRowsMissingAndCorruptFilesAreProblemsNotCrashes) {
  const fs::path dir = test::fresh_path("damaged");
  {
    RecordingWriter w(dir.string(), SessionInfo{}, "jpg", 90);
    for (int64_t f = 0; f < 6; ++f) w.add_frame(f, f * 1000, test_image(f));
    // Not finished: as if killed.
  }
  // The CSV ends mid-line, the last complete frame lost its file, frame 2 is a truncated JPEG.
  std::ofstream(dir / "frames.csv", std::ios::app) << "6,6000,frames/0000";
  fs::remove(dir / "frames" / "000005.jpg");
  const fs::path f2 = dir / "frames" / "000002.jpg";
  fs::resize_file(f2, fs::file_size(f2) / 2);
  // And a malformed row in the middle is skipped as well.
  {
    std::ifstream in(dir / "frames.csv");
    std::stringstream s;
    s << in.rdbuf();
    std::string text = s.str();
    text.insert(text.find("3,3000"), "garbage,row\n");
    std::ofstream(dir / "frames.csv", std::ios::trunc) << text;
  }
  RecordingReader r(dir.string());
  ASSERT_EQ(r.entries().size(), 6u);
  bool saw_incomplete = false, saw_malformed = false;
  for (const std::string& p : r.problems()) {
    saw_incomplete |= p.find("incomplete") != std::string::npos;
    saw_malformed |= p.find("malformed") != std::string::npos;
  }
  EXPECT_TRUE(saw_incomplete);
  EXPECT_TRUE(saw_malformed);
  EXPECT_TRUE(r.load(0).problem.empty());
  const RecordingReader::Loaded corrupt = r.load(2);
  EXPECT_TRUE(corrupt.image.empty());
  EXPECT_NE(corrupt.problem.find("corrupt JPEG"), std::string::npos) << corrupt.problem;
  EXPECT_NE(corrupt.problem.find("000002.jpg"), std::string::npos) << corrupt.problem;
  const RecordingReader::Loaded missing = r.load(5);
  EXPECT_TRUE(missing.image.empty());
  EXPECT_NE(missing.problem.find("missing"), std::string::npos) << missing.problem;
  EXPECT_FALSE(r.load(4).image.empty());
}

TEST(Recording, DecodeImageReportsCorruptData) {
  std::string problem;
  EXPECT_TRUE(decode_image({}, &problem).empty());
  EXPECT_FALSE(problem.empty());
  std::vector<uint8_t> jpeg;
  cv::imencode(".jpg", test_image(3), jpeg);
  EXPECT_FALSE(decode_image(jpeg, &problem).empty());
  EXPECT_TRUE(problem.empty());
  // Zero padding after the end-of-image marker, as some cameras send, is accepted.
  std::vector<uint8_t> padded = jpeg;
  padded.resize(padded.size() + 100, 0);
  EXPECT_FALSE(decode_image(padded, &problem).empty());
  std::vector<uint8_t> truncated(jpeg.begin(), jpeg.begin() + long(jpeg.size() * 2 / 3));
  EXPECT_TRUE(decode_image(truncated, &problem).empty());
  EXPECT_NE(problem.find("corrupt JPEG"), std::string::npos) << problem;
  std::vector<uint8_t> noise(5000);
  for (size_t i = 0; i < noise.size(); ++i) noise[i] = uint8_t(i * 7919 % 251);
  EXPECT_TRUE(decode_image(noise, &problem).empty());
  EXPECT_FALSE(problem.empty());
}

// A JPEG that libjpeg decodes only with a warning ("Corrupt JPEG data: premature end of data
// segment": the entropy-coded data cut short but an end-of-image marker present) is a corrupt
// frame, not a picture; a header claiming 30000 x 30000 pixels is skipped before decoding.
TEST(Recording, JpegThatDecodesWithAWarningIsACorruptFrame) {
  std::vector<uint8_t> jpeg;
  cv::imencode(".jpg", test_image(3), jpeg);
  std::string problem;
  ASSERT_FALSE(decode_image(jpeg, &problem).empty());
  std::vector<uint8_t> cut(jpeg.begin(), jpeg.begin() + long(jpeg.size() * 2 / 3));
  cut.push_back(0xFF);
  cut.push_back(0xD9);
  EXPECT_TRUE(decode_image(cut, &problem).empty());
  EXPECT_NE(problem.find("corrupt JPEG"), std::string::npos) << problem;
  EXPECT_NE(problem.find("Corrupt JPEG data"), std::string::npos) << problem;
  // OpenCV hands this frame back as an image (only printing the warning).
  EXPECT_FALSE(cv::imdecode(cut, cv::IMREAD_COLOR).empty());

  std::vector<uint8_t> huge = jpeg;
  size_t sof = 2;
  while (sof + 9 < huge.size() && !(huge[sof] == 0xFF && huge[sof + 1] == 0xC0)) ++sof;
  ASSERT_LT(sof + 9, huge.size()) << "no SOF0 marker";
  for (size_t at : {sof + 5, sof + 7}) {  // height, then width, big-endian
    huge[at] = uint8_t(30000 >> 8);
    huge[at + 1] = uint8_t(30000 & 0xFF);
  }
  EXPECT_TRUE(decode_image(huge, &problem).empty());
  EXPECT_NE(problem.find("30000x30000"), std::string::npos) << problem;
}

TEST(Recording, PoseCsvRejectsWrongHeaderAndSkipsBadRows) {
  const fs::path dir = test::fresh_path("posecsv");
  fs::create_directories(dir);
  std::ofstream(dir / "bad.csv") << "frame,time\n1,2\n";
  EXPECT_THROW(read_pose_csv((dir / "bad.csv").string()), Error);
  std::ofstream(dir / "ok.csv") << kPoseCsvHeader << "\n"
                                << format_pose_row(truth_row("patient", 450)) << "\n"
                                << "1,2,needle,lost,x,0,0,1,0,0,0,0\n"
                                << "2,3,needle";
  const PoseCsv csv = read_pose_csv((dir / "ok.csv").string());
  ASSERT_EQ(csv.rows.size(), 1u);
  EXPECT_NEAR(csv.rows[0].t[2], 450.0, 1e-9);
  EXPECT_EQ(csv.problems.size(), 2u);
}

}  // namespace
}  // namespace crepuscular::recordings
