// The command line's outputs never replace its inputs or another command's folder, and a run cut
// short (file size limit) or killed leaves nothing that a later run does not remove. The inputs
// of every refused run are checked to be there afterwards, byte for byte.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <string>

#include "tests/support/cli.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular {
namespace {

namespace fs = std::filesystem;
using test::run_cli;

// Every file under `dir` (relative name -> content).
std::map<std::string, std::string> contents(const fs::path& dir) {
  std::map<std::string, std::string> files;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    std::ifstream in(e.path(), std::ios::binary);
    std::stringstream s;
    s << in.rdbuf();
    files[e.path().lexically_relative(dir).string()] = s.str();
  }
  return files;
}

// Names in `dir` left by a run in progress or cut short.
std::string leftovers(const fs::path& dir) {
  std::string found;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    const std::string name = e.path().filename().string();
    if (name.find(".partial") != std::string::npos || name.rfind(".tmp-", 0) == 0) {
      found += e.path().string() + " ";
    }
  }
  return found;
}

// A folder as `plan` makes it (its marker names the command); the check comes before the plan is
// read, so a stand-in plan.json does.
void plan_folder(const fs::path& dir) {
  fs::create_directories(dir);
  std::ofstream(dir / "plan.json") << "{\"stand-in\": true}\n";
  std::ofstream(dir / ".crepuscular-output")
      << "crepuscular output folder\n// made by crepuscular plan\nplan.json\n";
}

class OutputSafetyTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    folder_ = new test::TemporaryFolder();
    phantom_ = folder_->file("phantom");
    std::string err;
    ASSERT_EQ(run_cli("phantom --spacing 6 --out " + phantom_, &err, test::Capture::kStderr), 0)
        << err;
  }
  static void TearDownTestSuite() { delete folder_; }

  static test::TemporaryFolder* folder_;
  static std::string phantom_;
};
test::TemporaryFolder* OutputSafetyTest::folder_ = nullptr;
std::string OutputSafetyTest::phantom_;

// `plan --out` onto the phantom folder it reads would replace it, label map and CT included.
TEST_F(OutputSafetyTest, PlanOntoItsInputsFolderIsRefused) {
  const auto before = contents(phantom_);
  std::string err;
  EXPECT_EQ(run_cli("plan --labels " + phantom_ + "/labels.nii.gz --tumor " + phantom_ +
                        "/tumor.nii.gz --preset phantom --radius 10 --device cpu --out " + phantom_,
                    &err, test::Capture::kStderr),
            1);
  EXPECT_EQ(err.rfind("error: --out " + phantom_ + ": holds the input --", 0), 0u) << err;
  EXPECT_EQ(contents(phantom_), before);
  // --overwrite never lets an output replace an input.
  EXPECT_EQ(run_cli("plan --labels " + phantom_ + "/labels.nii.gz --tumor " + phantom_ +
                        "/tumor.nii.gz --preset phantom --overwrite --out " + phantom_ + "/",
                    &err, test::Capture::kStderr),
            1);
  EXPECT_NE(err.find("holds the input"), std::string::npos) << err;
  EXPECT_EQ(contents(phantom_), before);
}

// `slices --out` onto the plan it draws, and `phantom --out` onto a plan.
TEST_F(OutputSafetyTest, SlicesOntoItsPlanAndPhantomOntoAPlanAreRefused) {
  const fs::path plan = *folder_ / "plan";
  plan_folder(plan);
  const auto before = contents(plan);
  std::string err;
  EXPECT_EQ(run_cli("slices --plan " + plan.string() + " --ct " + phantom_ + "/ct.nii.gz --out " +
                        plan.string(),
                    &err, test::Capture::kStderr),
            1);
  EXPECT_NE(err.find("error: --out " + plan.string() + ": is the input --plan"),
            std::string::npos)
      << err;
  EXPECT_EQ(contents(plan), before);
  EXPECT_EQ(run_cli("phantom --spacing 6 --out " + plan.string(), &err, test::Capture::kStderr), 1);
  EXPECT_NE(err.find("made by `crepuscular plan`"), std::string::npos) << err;
  EXPECT_NE(err.find("--overwrite"), std::string::npos) << err;
  EXPECT_EQ(contents(plan), before);
  // Said so, it is replaced.
  EXPECT_EQ(run_cli("phantom --spacing 6 --overwrite --out " + plan.string(), &err,
                    test::Capture::kStderr),
            0)
      << err;
  EXPECT_TRUE(fs::exists(plan / "ct.nii.gz"));
  EXPECT_FALSE(fs::exists(plan / "plan.json"));
  // And its own folder a command replaces without being told.
  EXPECT_EQ(run_cli("phantom --spacing 6 --out " + plan.string(), &err, test::Capture::kStderr), 0)
      << err;
}

// `guide --log` equal to `--out` wrote the CSV over the video and reported both.
TEST_F(OutputSafetyTest, GuideOutputsMustDiffer) {
  const fs::path plan = *folder_ / "guide-plan";
  plan_folder(plan);
  const std::string video = folder_->file("overlay.mp4");
  std::string err;
  EXPECT_EQ(run_cli("guide --plan " + plan.string() + " --registration r.yaml --needle n.yaml --poses igtl-server:0 --headless --out " +
                        video + " --log " + video,
                    &err, test::Capture::kStderr),
            1);
  EXPECT_EQ(err.rfind("error: --out " + video + ": is also --log", 0), 0u) << err;
  EXPECT_FALSE(fs::exists(video));
  EXPECT_EQ(run_cli("guide --plan " + plan.string() + " --registration r.yaml --needle n.yaml --poses igtl-server:0 --headless --out " +
                        plan.string() + "/overlay.mp4",
                    &err, test::Capture::kStderr),
            1);
  EXPECT_NE(err.find("lies inside the input --plan"), std::string::npos) << err;
}

// A write past the file size limit (ulimit -f) ends the run with an error that says so and
// leaves no staging folder or temporary file (SIGXFSZ, left at its default, would kill it where it
// stood).
TEST_F(OutputSafetyTest, FileSizeLimitEndsWithAnErrorAndLeavesNothing) {
  const fs::path root = *folder_ / "fsize";
  fs::create_directories(root);
  std::string out;
  const int code = test::run_command(
      "bash -c 'ulimit -f 20; exec " + std::string(CREPUSCULAR_BINARY) +
          " phantom --spacing 6 --out " + (root / "p").string() + "' 2>&1",
      &out);
  EXPECT_NE(code, 0) << out;
  EXPECT_NE(code, -1) << "killed by a signal: " << out;
  EXPECT_NE(out.find("error: "), std::string::npos) << out;
  EXPECT_NE(out.find("file size limit reached"), std::string::npos) << out;
  EXPECT_EQ(leftovers(root), "");
  EXPECT_FALSE(fs::exists(root / "p"));
}

// What a killed run left beside its output (a guide's temporary video, a staging folder) goes at
// the next run into that folder; a live process's and the user's files stay.
TEST_F(OutputSafetyTest, LeftoversOfKilledRunsAreRemovedByTheNextRun) {
  const fs::path root = *folder_ / "stale";
  fs::create_directories(root);
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) _exit(0);
  waitpid(child, nullptr, 0);
  const std::string dead = std::to_string(child);
  const std::string alive = std::to_string(getpid());
  std::ofstream(root / (".tmp-" + dead + "-2-overlay.mp4")) << "half a video";
  fs::create_directories(root / (".other.partial-" + dead));
  std::ofstream(root / (".tmp-" + alive + "-2-overlay.mp4")) << "being written";
  std::ofstream(root / ".tmp-my-notes.txt") << "the user's";
  std::string err;
  ASSERT_EQ(run_cli("phantom --spacing 6 --out " + (root / "p").string(), &err,
                    test::Capture::kStderr),
            0)
      << err;
  EXPECT_FALSE(fs::exists(root / (".tmp-" + dead + "-2-overlay.mp4")));
  EXPECT_FALSE(fs::exists(root / (".other.partial-" + dead)));
  EXPECT_TRUE(fs::exists(root / (".tmp-" + alive + "-2-overlay.mp4")));
  EXPECT_TRUE(fs::exists(root / ".tmp-my-notes.txt"));
}

}  // namespace
}  // namespace crepuscular
