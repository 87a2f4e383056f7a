// Tests of frame sources (tracking/frame_source.hpp): source URIs and their errors, recording
// replay (as fast as possible, recorded timing, looping, ground truth, corrupt and missing frames),
// and recording a synthetic source into a folder that replays with the same truth.
#include "tracking/frame_source.hpp"

#include "recordings/plus_sequence.hpp"

#include <gtest/gtest.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <thread>

#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"
#include "recordings/recording.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::tracking {
namespace {

using test::expect_error_containing;

namespace fs = std::filesystem;

TEST(FrameSource, UrisSplitIntoKindPathAndOptions) {
  const SourceUri u = parse_source_uri("v4l2:/dev/video0?width=1280&height=720&fps=60");
  EXPECT_EQ(u.scheme, "v4l2");
  EXPECT_EQ(u.path, "/dev/video0");
  ASSERT_EQ(u.options.size(), 3u);
  EXPECT_EQ(u.options[2].first, "fps");
  EXPECT_EQ(u.options[2].second, "60");
  EXPECT_TRUE(parse_source_uri("recording:some/dir").options.empty());
  expect_error_containing([] { parse_source_uri("/dev/video0"); }, {"/dev/video0", "KIND:WHERE"});
  expect_error_containing([] { parse_source_uri("recording:dir?loop"); }, {"'loop'", "key=value"});
  expect_error_containing([] { parse_source_uri("recording:"); }, {"nothing after"});
}

TEST(FrameSource, BadSourcesAreClearErrors) {
  expect_error_containing([] { open_frame_source("camera:/dev/video0"); },
                          {"unknown kind 'camera'", "v4l2:"});
  expect_error_containing([] { open_frame_source("recording:/nonexistent/rec"); },
                          {"/nonexistent/rec", "not found"});
  const fs::path dir = test::fresh_path("opts");
  fs::create_directories(dir);
  expect_error_containing([&] { open_frame_source("recording:" + dir.string() + "?speed=2"); },
                          {"unknown option 'speed'"});
  expect_error_containing([&] { open_frame_source("recording:" + dir.string() + "?loop=maybe"); },
                          {"loop=maybe"});
  expect_error_containing([] { open_frame_source("synthetic:builtin?fps=3"); }, {"no options"});
  expect_error_containing([] { open_frame_source("synthetic:/nonexistent/scene.json"); },
                          {"/nonexistent/scene.json"});
  expect_error_containing([] { open_frame_source("v4l2:/dev/video_missing?width=640"); },
                          {"/dev/video_missing", "cannot open"});
  expect_error_containing([] { open_frame_source("v4l2:/dev/video0?width=-1"); }, {"width=-1"});
}

// A small recording: 4 frames 50 ms apart with a pose each, camera.yaml, frame 2 corrupt.
fs::path write_recording(const std::string& name) {
  const fs::path dir = test::fresh_path(name);
  {
    recordings::RecordingWriter w(dir.string(), recordings::SessionInfo{}, "png", 95, true);
    for (int64_t f = 0; f < 4; ++f) {
      cv::Mat img(60, 80, CV_8UC3, cv::Scalar(double(40 * f), 100, 200));
      recordings::PoseRow r;
      r.board = "patient";
      r.t[2] = 400.0 + double(f);
      r.q[0] = std::cos(0.1 * double(f));
      r.q[3] = std::sin(0.1 * double(f));
      if (f == 2) {
        std::vector<uint8_t> bad = {0xFF, 0xD8, 0xFF, 0xE0, 1, 2, 3};
        w.add_encoded(f, 1000 + f * 50000000, bad, "jpg", {r});
      } else {
        w.add_frame(f, 1000 + f * 50000000, img, {r});
      }
    }
    w.finish();
  }
  SyntheticScene s;
  s.camera.write_yaml((dir / "camera.yaml").string());
  return dir;
}

TEST(FrameSource, RecordingReplaysFramesTruthAndProblems) {
  const fs::path dir = write_recording("replay");
  auto src = open_frame_source("recording:" + dir.string());
  ASSERT_TRUE(src->camera().has_value());
  EXPECT_EQ(src->camera()->width, 1280);
  int n = 0;
  while (auto f = src->next()) {
    EXPECT_EQ(f->index, n);
    EXPECT_EQ(f->timestamp_ns, 1000 + n * 50000000);
    ASSERT_EQ(f->truth.size(), 1u);
    EXPECT_EQ(f->truth[0].board, "patient");
    EXPECT_NEAR(f->truth[0].T_cam_board.translation().z(), 400.0 + n, 1e-6);
    EXPECT_NEAR(Eigen::AngleAxisd(f->truth[0].T_cam_board.linear()).angle(), 0.2 * n, 1e-9);
    if (n == 2) {
      EXPECT_TRUE(f->image.empty());
      EXPECT_NE(f->problem.find("corrupt JPEG"), std::string::npos) << f->problem;
    } else {
      ASSERT_FALSE(f->image.empty()) << f->problem;
      EXPECT_EQ(f->image.at<cv::Vec3b>(5, 5)[0], 40 * n);
    }
    ++n;
  }
  EXPECT_EQ(n, 4);
}

TEST(FrameSource, RecordingHonoursRecordedTimingAndLoops) {
  const fs::path dir = write_recording("timing");
  auto src = open_frame_source("recording:" + dir.string() + "?realtime=1&loop=1");
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<Frame> frames;
  for (int i = 0; i < 6; ++i) frames.push_back(*src->next());
  const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  // Frames 0..3 then 0..1 of the second loop: 5 intervals of 50 ms.
  EXPECT_GE(elapsed, 0.245);
  EXPECT_LT(elapsed, 1.0);
  EXPECT_EQ(frames[4].index, 4);
  EXPECT_EQ(frames[5].index, 5);
  EXPECT_EQ(frames[4].timestamp_ns, 1000 + 4 * 50000000);
  EXPECT_NEAR(frames[5].truth[0].T_cam_board.translation().z(), 401.0, 1e-6);

  auto fast = open_frame_source("recording:" + dir.string());
  const auto t1 = std::chrono::steady_clock::now();
  int n = 0;
  while (fast->next()) ++n;
  EXPECT_EQ(n, 4);
  EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count(), 0.1);
}

TEST(FrameSource, SyntheticRecordingReplaysWithItsTruth) {
  SyntheticScene s;
  s.camera.width = 320;
  s.camera.height = 240;
  s.camera.fx = s.camera.fy = 300;
  s.camera.cx = 159.5;
  s.camera.cy = 119.5;
  SceneBoard b;
  b.board = make_grid_board("patient", 1, 2, 40, 10, 0);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.translation() = Eigen::Vector3d(0, 0, 400);
  b.keyframes = {{0.0, T}};
  T.translation() = Eigen::Vector3d(20, -10, 450);
  T.linear() = Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitY()).matrix();
  b.keyframes.push_back({0.5, T});
  s.boards = {b};
  s.frame_count = 8;
  s.fps = 10;
  s.dropped_frames = {3};
  s.corrupt_frames = {5};
  auto src = make_synthetic_source(s, "synthetic:test");
  const fs::path out = test::fresh_path("synth");
  RecordOptions o;
  o.boards_json = boards_json_text({b.board});
  const RecordSummary sum = record_to_folder(*src, out.string(), o);
  EXPECT_EQ(sum.frames, 7);  // 8 minus the dropped one; the corrupt one is kept as it came
  EXPECT_EQ(sum.problems, 1);
  EXPECT_EQ(sum.truth_rows, 7);
  EXPECT_TRUE(fs::exists(out / "boards.json"));
  EXPECT_TRUE(fs::exists(out / "camera.yaml"));
  EXPECT_TRUE(fs::exists(out / "ground_truth.csv"));
  EXPECT_FALSE(fs::exists(out.string() + ".partial"));
  EXPECT_EQ(read_boards((out / "boards.json").string())[0].tags.size(), 2u);

  auto replay = open_frame_source("recording:" + out.string());
  SyntheticRenderer renderer(s);
  std::vector<int64_t> indices;
  while (auto f = replay->next()) {
    indices.push_back(f->index);
    ASSERT_EQ(f->truth.size(), 1u);
    const Eigen::Isometry3d expected = pose_at(s.boards[0], f->index / 10.0);
    EXPECT_LT((f->truth[0].T_cam_board.translation() - expected.translation()).norm(), 1e-5);
    EXPECT_TRUE(f->truth[0].T_cam_board.linear().isApprox(expected.linear(), 1e-9));
    if (f->index == 5) {
      EXPECT_NE(f->problem.find("corrupt JPEG"), std::string::npos) << f->problem;
    } else {
      ASSERT_FALSE(f->image.empty()) << f->problem;
      // JPEG at quality 95 of the same rendering.
      EXPECT_GT(cv::PSNR(f->image, renderer.render(f->index)), 30.0) << f->index;
    }
  }
  EXPECT_EQ(indices, (std::vector<int64_t>{0, 1, 2, 4, 5, 6, 7}));
  // A second recording to the same place is refused.
  auto again = make_synthetic_source(s, "synthetic:test");
  expect_error_containing([&] { record_to_folder(*again, out.string(), o); }, {"exists"});
}

TEST(FrameSource, RecordingStopsAtFrameAndTimeLimits) {
  const fs::path dir = write_recording("limits_src");
  auto src = open_frame_source("recording:" + dir.string() + "?loop=1");
  RecordOptions o;
  o.max_frames = 6;
  const fs::path out = test::fresh_path("limits_frames");
  // Six frames over a loop and a half, the corrupt JPEG stored as received.
  EXPECT_EQ(record_to_folder(*src, out.string(), o).frames, 6);
  auto src2 = open_frame_source("recording:" + dir.string() + "?loop=1");
  RecordOptions t;
  t.max_seconds = 0.12;  // frames at 0, 50, 100 ms
  const fs::path out2 = test::fresh_path("limits_seconds");
  const RecordSummary s2 = record_to_folder(*src2, out2.string(), t);
  EXPECT_EQ(s2.frames + s2.skipped, 3);
}

// The commands end to end: `synth` renders a scene file, `record` copies the result, and a
// recorder killed mid-way (SIGKILL) leaves DIR.partial that replays.
TEST(FrameSource, SynthAndRecordCommandsWriteReplayableRecordings) {
  const fs::path dir = test::fresh_path("cli");
  fs::create_directories(dir);
  write_boards((dir / "boards.json").string(), {make_grid_board("patient", 1, 2, 40, 10, 0)});
  std::ofstream(dir / "scene.json") << R"({"camera": {"width": 320, "height": 240, "fx": 300},
    "boards": "boards.json", "frames": 6, "corrupt_frames": [2], "dropped_frames": [4],
    "poses": {"patient": [{"t": 0, "translation_mm": [0, 0, 400]}]}})";
  const std::string bin = CREPUSCULAR_BINARY;
  const std::string rec = (dir / "rec").string();
  ASSERT_EQ(std::system((bin + " synth --scene " + (dir / "scene.json").string() + " --out " + rec +
                         " > " + (dir / "synth.log").string() + " 2>&1")
                            .c_str()),
            0);
  recordings::RecordingReader r(rec);
  EXPECT_EQ(r.entries().size(), 5u);
  EXPECT_TRUE(r.has_ground_truth());
  EXPECT_EQ(r.ground_truth(5).size(), 1u);
  EXPECT_NE(r.load(2).problem.find("corrupt JPEG"), std::string::npos);
  EXPECT_FALSE(r.camera_path().empty());
  EXPECT_FALSE(r.boards_path().empty());

  const std::string copy = (dir / "copy").string();
  ASSERT_EQ(std::system((bin + " record --source recording:" + rec + " --out " + copy +
                         " --frames 3 > /dev/null 2>&1")
                            .c_str()),
            0);
  EXPECT_EQ(recordings::RecordingReader(copy).entries().size(), 3u);
  // Refuses to overwrite; a bad source is an error, not a crash.
  EXPECT_NE(std::system((bin + " record --source recording:" + rec + " --out " + copy +
                         " > /dev/null 2>&1")
                            .c_str()),
            0);
  EXPECT_NE(std::system((bin + " record --source nothing --out " + (dir / "x").string() +
                         " > /dev/null 2>&1")
                            .c_str()),
            0);

  // Killed while recording: DIR.partial holds every complete frame and replays.
  const std::string live = (dir / "live").string();
  const std::string pid_file = (dir / "pid").string();
  const std::string live_log = (dir / "live.log").string();
  ASSERT_EQ(std::system((bin + " record --source recording:" + rec + "?realtime=1\\&loop=1 --out " +
                         live + " > " + live_log + " 2>&1 & echo $! > " + pid_file)
                            .c_str()),
            0);
  // What the recorder said, for a failure's message.
  const auto recorder_log = [&] {
    std::ifstream in(live_log);
    return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  };
  const fs::path partial_csv = fs::path(live + ".partial") / "frames.csv";
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  size_t seen = 0;
  while (std::chrono::steady_clock::now() < deadline) {
    if (fs::exists(partial_csv)) {
      try {
        seen = recordings::RecordingReader(live + ".partial").entries().size();
      } catch (const std::exception&) {
        // Caught between two files of a frame being written: look again.
      }
      if (seen >= 4) break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_GE(seen, 4u) << "the recorder wrote " << seen << " frames in 20 s; it said:\n"
                      << recorder_log();
  ASSERT_EQ(std::system(("kill -9 $(cat " + pid_file + ")").c_str()), 0);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_FALSE(fs::exists(live));
  SCOPED_TRACE("recorder log: " + recorder_log());
  auto replay = open_frame_source("recording:" + live + ".partial");
  int frames = 0;
  while (auto f = replay->next()) {
    EXPECT_EQ(f->truth.size(), 1u);
    if (f->index % 6 != 2) {  // frame 2 of each loop is corrupt on purpose
      EXPECT_TRUE(f->problem.empty()) << f->problem;
    }
    ++frames;
  }
  EXPECT_GE(frames, 4);
}

// A PLUS sequence file as a source (the PLUS toolkit's own files, tests/data): the 20 video frames
// with their timestamps (0.5 s apart), each image the sequence's pixels shown grey, the tool's
// transform beside it; the 16-bit NRRD frame scaled to 8 bits; a tracking-only sequence gives
// frames without images that say why.
TEST(FrameSource, PlusSequenceReplaysImagesTimestampsAndTransforms) {
  const std::string dir = std::string(CREPUSCULAR_TEST_DATA) + "/plus-sequence-files/";
  const recordings::PlusSequence seq = recordings::read_plus_sequence(dir + "SyntheticVideoBuffer20.igs.mha");
  auto source = open_frame_source("plus:" + dir + "SyntheticVideoBuffer20.igs.mha");
  int64_t n = 0;
  while (auto f = source->next()) {
    ASSERT_FALSE(f->image.empty()) << f->problem;
    EXPECT_EQ(f->image.cols, seq.width);
    EXPECT_EQ(f->image.rows, seq.height);
    EXPECT_EQ(f->timestamp_ns, int64_t(std::llround(seq.frames[size_t(n)].timestamp_s * 1e9)));
    const size_t bytes = size_t(seq.width) * size_t(seq.height);
    for (const int at : {0, seq.width * seq.height / 2 + 17}) {
      const cv::Vec3b px = f->image.at<cv::Vec3b>(at / seq.width, at % seq.width);
      EXPECT_EQ(px[0], seq.pixels[bytes * size_t(n) + size_t(at)]);
      EXPECT_EQ(px[2], px[0]);
    }
    ASSERT_EQ(f->truth.size(), 1u);
    EXPECT_EQ(f->truth[0].board, "ToolToTracker");
    ++n;
  }
  EXPECT_EQ(n, 20);
  auto nrrd = open_frame_source("plus:" + dir + "NrrdSample.igs.nrrd");
  const auto frame = nrrd->next();
  ASSERT_TRUE(frame && !frame->image.empty());
  double lo = 0, hi = 0;
  cv::minMaxLoc(frame->image.reshape(1), &lo, &hi);
  EXPECT_EQ(lo, 0.0);
  EXPECT_EQ(hi, 255.0);
  EXPECT_FALSE(nrrd->next());
  auto tracking = open_frame_source("plus:" + dir + "TransformInterpolationTest.igs.mha?realtime=0");
  const auto first = tracking->next();
  ASSERT_TRUE(first);
  EXPECT_FALSE(first->image.empty());  // 1 x 1 images, shown as they are
  EXPECT_EQ(first->truth.size(), 2u);
  EXPECT_THROW(open_frame_source("plus:" + dir + "TransformInterpolationTest.igs.mha?loop=1"), Error);
}

// `record --format plus`: four frames of the built-in scene (the second corrupt: no image) into
// a PLUS sequence file, read back frame for frame: timestamps, the images lossless (RGB in the file,
// the same BGR pixels when replayed through plus:), black with ImageStatus INVALID where the frame
// had none, both boards' true poses as <Board>ToCamera transforms; the pixels' scratch file is gone.
TEST(FrameSource, PlusSequenceRecordingReadsBackFrameForFrame) {
  namespace fs = std::filesystem;
  SyntheticScene scene = builtin_scene();
  scene.frame_count = 4;
  scene.corrupt_frames = {1};
  const test::TemporaryFolder dir;
  const std::string path = dir.file("session.igs.mha");
  auto source = make_synthetic_source(scene, "test");
  const RecordSummary summary = record_to_plus_sequence(*source, path, {});
  EXPECT_EQ(summary.frames, 4);
  const recordings::PlusSequence seq = recordings::read_plus_sequence(path);
  ASSERT_EQ(seq.frames.size(), 4u);
  EXPECT_EQ(seq.width, scene.camera.width);
  EXPECT_EQ(seq.channels, 3);
  SyntheticRenderer renderer(scene);
  auto replay = open_frame_source("plus:" + path);
  for (int64_t f = 0; f < 4; ++f) {
    const recordings::PlusFrame& frame = seq.frames[size_t(f)];
    EXPECT_NEAR(frame.timestamp_s, double(renderer.timestamp_ns_of(f)) * 1e-9, 1e-6);
    const auto back = replay->next();
    ASSERT_TRUE(back);
    if (f == 1) {
      EXPECT_EQ(frame.field("ImageStatus"), "INVALID");
      EXPECT_TRUE(back->image.empty());
      continue;
    }
    EXPECT_EQ(frame.field("ImageStatus"), "OK");
    std::vector<TruePose> truth;
    const cv::Mat image = renderer.render(f, &truth);
    ASSERT_FALSE(back->image.empty());
    EXPECT_EQ(cv::norm(back->image, image, cv::NORM_INF), 0.0) << "frame " << f;
    ASSERT_EQ(truth.size(), 2u);
    for (const TruePose& t : truth) {
      std::string name = t.board;
      name[0] = char(std::toupper(static_cast<unsigned char>(name[0])));
      const auto it = frame.transforms.find(name + "ToCamera");
      ASSERT_NE(it, frame.transforms.end()) << name;
      EXPECT_LT((it->second.matrix - t.T_cam_board.matrix()).cwiseAbs().maxCoeff(), 1e-4) << name;
    }
  }
  for (const auto& e : fs::directory_iterator(dir.path())) {
    EXPECT_EQ(e.path().filename().string(), "session.igs.mha") << "left behind: " << e.path();
  }
}

}  // namespace
}  // namespace crepuscular::tracking
