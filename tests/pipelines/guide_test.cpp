// `guide` end to end, headless: the demo's scenario on a 4 mm phantom plan, recorded at 10 fps, is
// replayed through tracking, the overlay and the renderer from the calibration files written for
// it. The overlay video has every frame; the per-frame log says safe along the safe approach and
// dangerous along the vessel-crossing one (the needle's colour switches as it crosses the vessel);
// snapshots are written; a corrupt and a dropped frame are shown as such with no overlay; an
// unusable input leaves no output behind.
#include "pipelines/guide.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <map>
#include <thread>
#include <atomic>
#include <set>
#include <sstream>

#include <igtlClientSocket.h>
#include <igtlMessageHeader.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>

#include "foundation/error.hpp"
#include "igtl/messages.hpp"
#include "igtl/server.hpp"
#include "pipelines/demo_scenario.hpp"
#include "planning/simulation/phantom.hpp"
#include "pipelines/plan.hpp"
#include "tests/support/cli.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/network.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"
#include "recordings/plus_sequence.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {
using namespace overlay;  // NOLINT
namespace {

std::vector<std::vector<std::string>> read_csv(const std::string& path) {
  std::vector<std::vector<std::string>> rows;
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    std::vector<std::string> fields;
    std::string field;
    bool quoted = false;
    for (char c : line) {
      if (c == '"') {
        quoted = !quoted;
      } else if (c == ',' && !quoted) {
        fields.push_back(field);
        field.clear();
      } else {
        field += c;
      }
    }
    fields.push_back(field);
    rows.push_back(fields);
  }
  return rows;
}

class GuideTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TemporaryFolder;
    planning::PhantomOptions po;
    po.spacing_mm = 4.0;
    planning::write_phantom(planning::make_phantom(po), (*dir_ / "phantom").string());
    const PlanRequest r =
        test::phantom_plan_request(*dir_ / "phantom", (*dir_ / "plan").string());
    run_plan(r);
    plan_ = new planning::PlanData(planning::load_plan(r.out_dir));
    GuidanceScenarioOptions so;
    so.fps = 10;
    scenario_ = new GuidanceScenario(make_guidance_scenario(*plan_, so));
    // One corrupt frame in the middle of the safe approach, one dropped frame after it.
    tracking::SyntheticScene scene = scenario_->scene;
    corrupt_ = int64_t(std::lround(0.5 * (scenario_->safe.start_s + scenario_->safe.end_s) * so.fps));
    scene.corrupt_frames = {corrupt_};
    scene.dropped_frames = {corrupt_ + 2};
    write_guidance_setup(*scenario_, (*dir_ / "setup").string());
    tracking::RecordOptions ro;
    std::vector<tracking::Board> boards;
    for (const auto& b : scene.boards) boards.push_back(b.board);
    ro.boards_json = tracking::boards_json_text(boards);
    auto source = tracking::make_synthetic_source(scene, "test scenario");
    tracking::record_to_folder(*source, (*dir_ / "recording").string(), ro);
    frames_ = scene.frame_count - 1;  // one dropped
  }
  static void TearDownTestSuite() {
    delete scenario_;
    delete plan_;
    delete dir_;
  }

  static GuideRequest request(const std::string& out) {
    GuideRequest g;
    g.setup = read_guidance_setup((*dir_ / "setup/camera.yaml").string(),
                                  (*dir_ / "setup/registration.yaml").string(),
                                  (*dir_ / "setup/needle.yaml").string());
    g.boards = tracking::read_boards((*dir_ / "recording/boards.json").string());
    g.source = "recording:" + (*dir_ / "recording").string();
    g.video = out + "/overlay.avi";
    g.log = out + "/overlay.csv";
    g.video_fps = 10;
    g.snapshot_dir = out;
    g.options.ray_directions = 1000;
    return g;
  }

  static test::TemporaryFolder* dir_;
  static planning::PlanData* plan_;
  static GuidanceScenario* scenario_;
  static int64_t corrupt_, frames_;
};
test::TemporaryFolder* GuideTest::dir_ = nullptr;
planning::PlanData* GuideTest::plan_ = nullptr;
GuidanceScenario* GuideTest::scenario_ = nullptr;
int64_t GuideTest::corrupt_ = 0;
int64_t GuideTest::frames_ = 0;

TEST_F(GuideTest, HeadlessRunShowsSafeThenDangerousAndWritesEveryOutput) {
  const std::string out = (*dir_ / "out").string();
  fs::create_directories(out);
  GuideRequest g = request(out);
  const int64_t safe_frame = int64_t(std::floor(scenario_->safe.end_s * 10));
  const int64_t dangerous_frame = int64_t(std::floor(scenario_->dangerous.end_s * 10));
  g.snapshots = {{safe_frame, "safe.png"}, {dangerous_frame, "dangerous.png"}};
  g.record = out + "/session";
  g.record_poses = out + "/session.igs.mha";
  GuideSummary s;
  try {
    s = run_guide(*plan_, g);
  } catch (const Error& e) {
    if (std::string(e.what()).find("OpenGL") != std::string::npos) GTEST_SKIP() << e.what();
    throw;
  }
  EXPECT_EQ(s.frames, frames_);
  EXPECT_EQ(s.frames_without_image, 1);
  EXPECT_EQ(s.dropped, 1);
  EXPECT_GT(s.latency_median_ms, 0.0);

  // The video holds every frame shown, at the camera's size.
  cv::VideoCapture video(out + "/overlay.avi");
  ASSERT_TRUE(video.isOpened());
  EXPECT_EQ(int64_t(video.get(cv::CAP_PROP_FRAME_COUNT)), frames_);
  EXPECT_EQ(int(video.get(cv::CAP_PROP_FRAME_WIDTH)), g.setup.camera.width);
  for (const char* name : {"safe.png", "dangerous.png"}) {
    const cv::Mat snap = cv::imread(out + "/" + name);
    EXPECT_EQ(snap.cols, g.setup.camera.width) << name;
  }

  // The log: one row per frame; along each approach (tip outside and inside the body alike) the
  // needle is safe, then dangerous; the corrupt frame has no image and nothing drawn.
  const auto rows = read_csv(out + "/overlay.csv");
  ASSERT_EQ(int64_t(rows.size()), frames_ + 1);
  const auto& header = rows[0];
  auto col = [&](const std::string& name) {
    return size_t(std::find(header.begin(), header.end(), name) - header.begin());
  };
  int safe_rows = 0, dangerous_rows = 0, bad = 0, vessel_rows = 0;
  bool corrupt_seen = false;
  for (size_t i = 1; i < rows.size(); ++i) {
    const auto& row = rows[i];
    ASSERT_EQ(row.size(), header.size()) << "row " << i;
    const int64_t frame = std::stoll(row[col("frame")]);
    const double t = double(frame) / 10.0;
    if (frame == corrupt_) {
      corrupt_seen = true;
      EXPECT_EQ(row[col("image")], "0");
      EXPECT_EQ(row[col("anatomy_drawn")], "0");
      EXPECT_EQ(row[col("needle_safety")], "");
      EXPECT_NE(row[col("warnings")].find("NO CAMERA IMAGE"), std::string::npos);
      continue;
    }
    EXPECT_EQ(row[col("anatomy_drawn")], "1") << "frame " << frame;
    const std::string safety = row[col("needle_safety")];
    // Approach windows, less one frame at each end (tracker restart, motion between keyframes).
    if (t > scenario_->safe.start_s + 0.1 && t < scenario_->safe.end_s - 0.1) {
      ++safe_rows;
      if (safety != "safe") ++bad;
    }
    if (t > scenario_->dangerous.start_s + 0.1 && t < scenario_->dangerous.end_s - 0.1) {
      ++dangerous_rows;
      if (safety != "dangerous") ++bad;
      // The vessel crossing is short (~4 mm at this spacing): a tracked pose 1-2 mm off may pass
      // beside it, but most frames list it.
      if (row[col("structures")].find("vessels") != std::string::npos) ++vessel_rows;
    }
  }
  EXPECT_TRUE(corrupt_seen);
  EXPECT_GT(safe_rows, 15);
  EXPECT_GT(dangerous_rows, 15);
  EXPECT_EQ(bad, 0);
  EXPECT_GT(vessel_rows, dangerous_rows / 2);
  // The session's own recording replays the frames that came with an image, with the boards.
  {
    auto replay = tracking::open_recording_source(out + "/session");
    int64_t n = 0;
    while (auto f = replay->next()) n += f->image.empty() ? 0 : 1;
    EXPECT_EQ(n, frames_ - 1);
    EXPECT_EQ(tracking::read_boards(out + "/session/boards.json").size(), 2u);
  }
  // The poses as a PLUS sequence file, read back frame for frame against the log: a frame per row,
  // its timestamp, the needle in the CT valid exactly where the log has a needle reading, and
  // within 3 mm (tip) of the scenario's true needle.
  {
    const recordings::PlusSequence seq = recordings::read_plus_sequence(out + "/session.igs.mha");
    ASSERT_EQ(int64_t(seq.frames.size()), frames_);
    EXPECT_EQ(seq.transform_names(),
              (std::vector<std::string>{"NeedleToCT", "NeedleToCamera", "PatientToCamera"}));
    int compared = 0;
    for (size_t i = 1; i < rows.size(); ++i) {
      const recordings::PlusFrame& f = seq.frames[i - 1];
      const int64_t frame = std::stoll(rows[i][col("frame")]);
      EXPECT_EQ(f.field("FrameNumber"), rows[i][col("frame")]);
      EXPECT_NEAR(f.timestamp_s, double(std::stoll(rows[i][col("timestamp_ns")])) * 1e-9, 1e-6);
      const recordings::PlusTransform& n = f.transforms.at("NeedleToCT");
      EXPECT_EQ(n.valid, !rows[i][col("needle_safety")].empty()) << "frame " << frame;
      // The corrupt frame holds the pose before it (younger than the limit): valid there too.
      EXPECT_TRUE(f.transforms.at("PatientToCamera").valid) << "frame " << frame;
      if (!n.valid) continue;
      EXPECT_EQ(f.field("NeedleSafety"), rows[i][col("needle_safety")]) << "frame " << frame;
      Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
      T.matrix() = n.matrix;
      const Eigen::Isometry3d truth = scenario_->T_ct_needle_at(double(frame) / 10.0);
      EXPECT_LT((T * tracking::kNeedleTipInNeedle - truth * tracking::kNeedleTipInNeedle).norm(), 3.0)
          << "frame " << frame;
      ++compared;
    }
    EXPECT_GT(compared, 30);
    // Replayed as the poses of `guide --poses plus:FILE` (the boards' camera poses as the tracker's
    // tools): every frame's needle in the CT is the recorded one, and so is its class.
    GuideRequest replay;
    replay.setup = g.setup;
    replay.options = g.options;
    replay.poses = "plus:" + out + "/session.igs.mha";
    replay.poses_needle = "NeedleToCamera";
    replay.poses_patient = "PatientToCamera";
    replay.log = out + "/replay.csv";
    replay.record_poses = out + "/replay.igs.mha";
    run_guide(*plan_, replay);
    const recordings::PlusSequence again = recordings::read_plus_sequence(out + "/replay.igs.mha");
    ASSERT_EQ(again.frames.size(), seq.frames.size());
    int same = 0;
    for (size_t f = 0; f < seq.frames.size(); ++f) {
      const auto& a = seq.frames[f].transforms.at("NeedleToCT");
      const auto& b = again.frames[f].transforms.at("NeedleToCT");
      // The corrupt frame: its held poses replay as a frame with an image (a virtual one).
      if (int64_t(f) == corrupt_ || !a.valid) continue;
      EXPECT_TRUE(b.valid) << "frame " << f;
      EXPECT_LT((a.matrix - b.matrix).cwiseAbs().maxCoeff(), 1e-5) << "frame " << f;
      EXPECT_EQ(again.frames[f].field("NeedleSafety"), seq.frames[f].field("NeedleSafety"))
          << "frame " << f;
      ++same;
    }
    EXPECT_GT(same, 30);
  }
  // No temporary file is left beside the outputs.
  for (const auto& e : fs::directory_iterator(out)) {
    EXPECT_EQ(e.path().filename().string().rfind(".tmp", 0), std::string::npos) << e.path();
  }
}

// A recording with every fault a camera gives: blank frames whose timestamps stop advancing, then
// go backwards; a corrupt JPEG (it decodes, with libjpeg's warning); a frame of another size.
// Frame by frame, the log shows that nothing is drawn from a pose that is not current.
TEST_F(GuideTest, CommandLineTakesSeveralSnapshotFrames) {
  // `--snapshot-at` is repeatable, as its help says: two frames, two pictures, from the command
  // line as a user types it.
  test::TemporaryFolder out;
  const fs::path d = *dir_;
  std::string output;
  const int code = test::run_cli(
      "guide --plan " + (d / "plan").string() + " --camera " + (d / "setup/camera.yaml").string() +
          " --registration " + (d / "setup/registration.yaml").string() + " --needle " +
          (d / "setup/needle.yaml").string() + " --source recording:" +
          (d / "recording").string() + " --headless --max-frames 6 --rays 500 --snapshots " +
          out.path().string() +
          " --snapshot-at 2:first.png --snapshot-at 5:second.png --snapshot-at 40:late.png",
      &output);
  ASSERT_EQ(code, 0) << output;
  for (const char* name : {"first.png", "second.png"}) {
    const cv::Mat picture = cv::imread((out.path() / name).string());
    ASSERT_FALSE(picture.empty()) << name << "\n" << output;
    EXPECT_EQ(picture.cols, request(out.path().string()).setup.camera.width) << name;
  }
  // A frame beyond the six shown is said, not passed over in silence.
  EXPECT_FALSE(fs::exists(out.path() / "late.png"));
  EXPECT_NE(output.find("snapshot late.png at frame 40 not taken: the frames shown ended at frame 5"),
            std::string::npos)
      << output;
}

TEST_F(GuideTest, FaultsNeverDrawFromAPoseThatIsNotCurrent) {
  const fs::path faulty = *dir_ / "faulty_recording";
  fs::remove_all(faulty);
  fs::copy(*dir_ / "recording", faulty, fs::copy_options::recursive);
  auto rows = read_csv((faulty / "frames.csv").string());
  ASSERT_GT(rows.size(), 60u);
  // Faults in the safe approach, after the corrupt and dropped frames of the scenario.
  const size_t first_blank = size_t(corrupt_) + 6;  // row index = frame + 1 before the drop
  size_t row_of_blank = 0;
  for (size_t i = 1; i < rows.size(); ++i) {
    if (std::stoll(rows[i][0]) == int64_t(first_blank)) row_of_blank = i;
  }
  ASSERT_GT(row_of_blank, 1u);
  const int64_t frozen = std::stoll(rows[row_of_blank - 1][1]);
  const cv::Mat gray(720, 1280, CV_8UC3, cv::Scalar(128, 128, 128));
  std::set<int64_t> blank, corrupt, wrong_size;
  for (size_t n = 0; n < 12; ++n) {
    auto& row = rows[row_of_blank + n];
    blank.insert(std::stoll(row[0]));
    // Six frames with the last good frame's timestamp, then six 533 ms before it.
    row[1] = std::to_string(n < 6 ? frozen : frozen - 533000000);
    cv::imwrite((faulty / row[2]).string(), gray);
  }
  {
    auto& row = rows[row_of_blank + 14];
    corrupt.insert(std::stoll(row[0]));
    std::ifstream in(faulty / row[2], std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    bytes.resize(bytes.size() * 6 / 10);  // "Premature end of JPEG file": decodes, grey below
    std::ofstream(faulty / row[2], std::ios::binary) << bytes;
  }
  {
    auto& row = rows[row_of_blank + 16];
    wrong_size.insert(std::stoll(row[0]));
    cv::imwrite((faulty / row[2]).string(), cv::Mat(480, 640, CV_8UC3, cv::Scalar(90, 90, 90)));
  }
  {
    std::ofstream csv(faulty / "frames.csv");
    for (const auto& row : rows) csv << row[0] << ',' << row[1] << ',' << row[2] << '\n';
  }

  const std::string out = (*dir_ / "faulty").string();
  fs::create_directories(out);
  GuideRequest g = request(out);
  g.source = "recording:" + faulty.string();
  g.video.clear();
  g.snapshot_dir.clear();
  g.record.clear();
  try {
    run_guide(*plan_, g);
  } catch (const Error& e) {
    if (std::string(e.what()).find("OpenGL") != std::string::npos) GTEST_SKIP() << e.what();
    throw;
  }
  const auto log = read_csv(out + "/overlay.csv");
  ASSERT_EQ(log.size(), rows.size());  // one row per frame: none ended the session
  const auto& header = log[0];
  auto col = [&](const std::string& name) {
    const size_t c = size_t(std::find(header.begin(), header.end(), name) - header.begin());
    EXPECT_LT(c, header.size()) << name;
    return c;
  };
  const double max_age_ms = g.tracker.max_age_ms;
  int blank_seen = 0, drawn_after = 0;
  for (size_t i = 1; i < log.size(); ++i) {
    const auto& row = log[i];
    const int64_t frame = std::stoll(row[col("frame")]);
    SCOPED_TRACE("frame " + std::to_string(frame));
    // Whatever is drawn comes from a current pose of a frame that has a picture.
    if (row[col("anatomy_drawn")] == "1") {
      EXPECT_EQ(row[col("image")], "1");
      EXPECT_EQ(row[col("patient_tracked")], "1");
      EXPECT_LE(std::stod(row[col("patient_age_ms")]), max_age_ms);
    }
    if (!row[col("needle_safety")].empty()) {
      EXPECT_EQ(row[col("anatomy_drawn")], "1");
      EXPECT_EQ(row[col("needle_tracked")], "1");
      EXPECT_LE(std::stod(row[col("needle_age_ms")]), max_age_ms);
    }
    if (blank.count(frame)) {
      // The first blank frame may still use the pose of the frame before (one frame old).
      if (blank_seen++ > 0) {
        EXPECT_EQ(row[col("anatomy_drawn")], "0");
        EXPECT_EQ(row[col("needle_safety")], "");
        EXPECT_NE(row[col("warnings")].find("PATIENT MARKER LOST"), std::string::npos);
      }
    }
    if (corrupt.count(frame) || wrong_size.count(frame)) {
      EXPECT_EQ(row[col("image")], "0");
      EXPECT_EQ(row[col("anatomy_drawn")], "0");
      EXPECT_EQ(row[col("needle_safety")], "");
      EXPECT_NE(row[col("warnings")].find("NO CAMERA IMAGE"), std::string::npos);
    }
    if (corrupt.count(frame)) {
      EXPECT_NE(row[col("problem")].find("corrupt"), std::string::npos);
    }
    if (wrong_size.count(frame)) {
      EXPECT_NE(row[col("problem")].find("640x480"), std::string::npos);
    }
    if (frame > *wrong_size.begin() + 3 && row[col("anatomy_drawn")] == "1") ++drawn_after;
  }
  EXPECT_EQ(blank_seen, 12);
  EXPECT_GT(drawn_after, 10);  // guidance comes back once the camera does
}

// `guide --igtl-server`: a client connected before the first frame receives, per frame, the
// needle in the CT (or a STATUS while a marker is lost) and the needle's safety, and first the
// on-connect messages.
TEST_F(GuideTest, OpenIgtLinkClientGetsEveryFramesNeedlePoseAndSafety) {
  const int port = test::free_loopback_port();  // served by guide

  const std::string out = (*dir_ / "igtl").string();
  fs::create_directories(out);
  GuideRequest g = request(out);
  g.video.clear();
  g.snapshot_dir.clear();
  g.igtl_port = port;
  // Replayed at its recorded timing (10 fps): the client, connecting as soon as the server
  // listens, misses at most the first frame or two.
  g.source += "?realtime=1";
  std::map<std::string, int> names;
  std::atomic<bool> stop{false};
  std::thread client([&] {
    igtl::ClientSocket::Pointer socket;
    for (int attempt = 0; !stop && attempt < 1000; ++attempt) {
      socket = igtl::ClientSocket::New();  // a fresh socket per attempt (a failed one is spent)
      if (socket->ConnectToServer("127.0.0.1", port) == 0) break;
      socket = nullptr;
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    if (socket.IsNull()) return;
    igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
    for (;;) {
      header->InitPack();
      if (socket->Receive(header->GetPackPointer(), header->GetPackSize()) !=
          header->GetPackSize()) {
        break;  // guide ended: the server closed
      }
      header->Unpack();
      ++names[std::string(header->GetDeviceType()) + " " + header->GetDeviceName()];
      socket->Skip(int(header->GetBodySizeToRead()), 1);
    }
  });
  GuideSummary s;
  try {
    s = run_guide(*plan_, g);
  } catch (const Error& e) {
    stop = true;
    client.join();
    if (std::string(e.what()).find("OpenGL") != std::string::npos) GTEST_SKIP() << e.what();
    throw;
  }
  client.join();
  EXPECT_EQ(s.igtl_connections, 1);
  EXPECT_EQ(names["TRANSFORM NeedleTipToNeedle"], 1);
  EXPECT_EQ(names["POINT Target"], 1);
  // Every frame: PatientToCT and NeedleToCT as TRANSFORM or STATUS, and NeedleSafety. The client
  // may have connected a frame or two after the first one was shown.
  const int frames = int(s.frames);
  EXPECT_GE(names["TRANSFORM NeedleToCT"] + names["STATUS NeedleToCT"], frames - 3);
  EXPECT_LE(names["TRANSFORM NeedleToCT"] + names["STATUS NeedleToCT"], frames);
  EXPECT_GE(names["STRING NeedleSafety"], frames - 3);
  EXPECT_GE(names["TRANSFORM NeedleToCT"], int(s.needle_evaluated) - 3);
  EXPECT_GT(s.igtl_messages, 0);
}

// `guide --poses igtl://...` without video: the reference library's TrackerServer example
// (100 poses at 100 Hz, then silence) drives the needle; guidance draws it from the virtual
// camera while poses arrive, and calls it lost once they stop (older than --max-age-ms).
TEST_F(GuideTest, PosesFromATrackingServerDriveGuidanceWithoutVideoAndStaleOnesAreLost) {
  const int port = test::free_loopback_port();
  const test::BackgroundProcess tracker(std::string(CREPUSCULAR_IGTL_TRACKER_SERVER) + " " +
                                       std::to_string(port) + " 100");

  const std::string out = (*dir_ / "poses").string();
  fs::create_directories(out);
  GuideRequest g = request(out);
  g.source.clear();
  g.boards.clear();
  g.video.clear();
  g.snapshot_dir.clear();
  g.poses = "igtl://127.0.0.1:" + std::to_string(port);
  g.poses_needle = "Tracker";
  g.poses_patient = "";  // the tracker's frame is the patient board's
  g.poses_fps = 30;
  g.max_frames = 60;  // 2 s: poses during the first second, silence after
  GuideSummary s;
  try {
    s = run_guide(*plan_, g);
  } catch (const Error& e) {
    if (std::string(e.what()).find("OpenGL") != std::string::npos) GTEST_SKIP() << e.what();
    throw;
  }
  EXPECT_EQ(s.frames, 60);
  EXPECT_EQ(s.patient_tracked, 60);  // the tracker's frame: always there
  // About 1 s of poses (the connection takes up to 0.2 s). How many frames that covers depends
  // on how fast the sending program runs (a loaded machine stretches its 1 s): the frame-by-frame
  // check below, and the loss at the end, are the requirement.
  EXPECT_GE(s.needle_evaluated, 15);
  EXPECT_LT(s.needle_evaluated, 60);
  // Frame by frame: the needle is drawn only from poses no older than --max-age-ms.
  const auto rows = read_csv(out + "/overlay.csv");
  ASSERT_EQ(rows.size(), 61u);
  const auto& header = rows[0];
  auto col = [&](const std::string& name) {
    return size_t(std::find(header.begin(), header.end(), name) - header.begin());
  };
  bool lost_after_tracked = false, seen = false;
  for (size_t i = 1; i < rows.size(); ++i) {
    if (rows[i][col("needle_tracked")] == "1") {
      seen = true;
      EXPECT_LE(std::stod(rows[i][col("needle_age_ms")]), g.tracker.max_age_ms);
    } else if (seen) {
      lost_after_tracked = true;
      EXPECT_EQ(rows[i][col("needle_safety")], "");
    }
  }
  EXPECT_TRUE(lost_after_tracked);
}

// `guide --source ... --poses ...`: over the video the camera tracks the patient board and the
// tracker gives the needle relative to it (here our own OpenIGTLink server sends a fixed
// NeedleToTracker pose, the tracker's frame being the patient board's): the needle in the CT is
// then T_ct_patient * NeedleToTracker in every frame, whatever the camera sees of the needle.
TEST_F(GuideTest, TrackerPosesOverTheVideoPlaceTheNeedleRelativeToThePatientBoard) {
  Eigen::Isometry3d T_patient_needle = Eigen::Isometry3d::Identity();
  T_patient_needle.linear() = Eigen::AngleAxisd(0.4, Eigen::Vector3d::UnitX()).toRotationMatrix();
  T_patient_needle.translation() = Eigen::Vector3d(20, -30, 150);
  igtlink::Server tracker(igtlink::Server::Options{0, 500});
  std::atomic<bool> stop{false};
  std::thread sending([&] {
    while (!stop) {
      tracker.publish({igtlink::transform_message("NeedleToTracker", T_patient_needle, 0)});
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
  });
  const std::string out = (*dir_ / "poses_over_video").string();
  fs::create_directories(out);
  GuideRequest g = request(out);
  g.video.clear();
  g.snapshot_dir.clear();
  g.poses = "igtl://127.0.0.1:" + std::to_string(tracker.port());
  g.poses_patient = "";
  g.tracker.max_age_ms = 200;
  GuideSummary s;
  try {
    s = run_guide(*plan_, g);
  } catch (const Error& e) {
    stop = true;
    sending.join();
    if (std::string(e.what()).find("OpenGL") != std::string::npos) GTEST_SKIP() << e.what();
    throw;
  }
  stop = true;
  sending.join();
  const auto rows = read_csv(out + "/overlay.csv");
  const auto& header = rows[0];
  auto col = [&](const std::string& name) {
    return size_t(std::find(header.begin(), header.end(), name) - header.begin());
  };
  std::vector<double> tip_to_target;
  for (size_t i = 1; i < rows.size(); ++i) {
    if (rows[i][col("needle_safety")].empty()) continue;
    tip_to_target.push_back(std::stod(rows[i][col("tip_to_target_mm")]));
  }
  // Once the receiver is connected (within a few frames), every frame with the anatomy has it.
  EXPECT_GE(int64_t(tip_to_target.size()), s.patient_tracked - 10);
  ASSERT_FALSE(tip_to_target.empty());
  const Eigen::Vector3d tip =
      g.setup.T_ct_patient * T_patient_needle * g.setup.tip_in_needle;
  for (double d : tip_to_target) {
    EXPECT_NEAR(d, (tip - plan_->tumor_centre).norm(), 0.05);
  }
}

TEST_F(GuideTest, UnusableInputLeavesNoOutput) {
  const std::string out = (*dir_ / "bad").string();
  fs::create_directories(out);
  GuideRequest g = request(out);
  g.setup.camera.width = 640;  // calibration of another camera
  g.setup.camera.height = 480;
  test::expect_error_containing([&] { run_guide(*plan_, g); }, "1280x720");
  EXPECT_TRUE(fs::is_empty(out));
  g = request(out);
  g.boards.pop_back();  // no needle board
  EXPECT_THROW(run_guide(*plan_, g), Error);
  EXPECT_TRUE(fs::is_empty(out));
}

}  // namespace
}  // namespace crepuscular::pipelines
