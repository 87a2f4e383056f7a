// Tests of foundation/run_paths: the one rule on where a run may write, as a table of runs and
// the refusal each must meet (or none).
#include "foundation/run_paths.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "foundation/output_files.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular {
namespace {

namespace fs = std::filesystem;

// A folder crepuscular made: its marker names `command` ("" : an older marker that names none).
void made_folder(const fs::path& dir, const std::string& command) {
  fs::create_directories(dir);
  std::ofstream(dir / "plan.json") << "{}\n";
  std::ofstream marker(dir / kOutputMarker);
  marker << "crepuscular output folder\n";
  if (!command.empty()) marker << "// made by crepuscular " << command << "\n";
  marker << "plan.json\n";
}

TEST(RunPaths, RefusesOutputsThatReplaceInputsEachOtherOrAnotherCommandsFolder) {
  const test::TemporaryFolder tmp;
  const fs::path phantom = tmp / "phantom";
  fs::create_directories(phantom);
  std::ofstream(phantom / "labels.nii.gz") << "labels";
  made_folder(tmp / "plan", "plan");
  made_folder(tmp / "old", "");
  fs::create_directory_symlink(phantom, tmp / "link");
  const std::string labels = (phantom / "labels.nii.gz").string();
  const std::string plan = (tmp / "plan").string();
  using K = OutputKind;
  struct Row {
    const char* what;
    RunPaths run;
    std::vector<std::string> refusal;  // parts of the message; empty: allowed
  };
  const std::vector<Row> rows = {
      {"output folder beside the inputs",
       {"plan", {{"--labels", labels}}, {{"--out", tmp.file("new"), K::kFolder}}},
       {}},
      {"output folder holding an input",
       {"plan", {{"--labels", labels}}, {{"--out", phantom.string(), K::kFolder}}},
       {"--out " + phantom.string(), "holds the input --labels"}},
      {"holding an input through a symlink",
       {"plan", {{"--labels", labels}}, {{"--out", tmp.file("link"), K::kFolder}}},
       {"holds the input --labels"}},
      {"written as the input itself, spelled with ..",
       {"slices", {{"--plan", plan}}, {{"--out", tmp.file("phantom/../plan"), K::kFolder}}},
       {"is the input --plan"}},
      {"an output file inside an input folder",
       {"evaluate", {{"--plan", plan}}, {{"--out", plan + "/results.csv"}}},
       {"lies inside the input --plan"}},
      {"an output file onto an input file",
       {"track", {{"--camera", labels}}, {{"--out", labels}}},
       {"is the input --camera"}},
      {"snapshots into a folder that holds inputs: never replaced",
       {"guide", {{"--plan", plan}}, {{"--snapshots", tmp.string(), K::kFilesInFolder}}},
       {}},
      {"snapshots into an input folder",
       {"guide", {{"--plan", plan}}, {{"--snapshots", plan + "/shots", K::kFilesInFolder}}},
       {"--snapshots", "lies inside the input --plan"}},
      {"two outputs at one path",
       {"guide", {}, {{"--out", tmp.file("v.mp4")}, {"--log", tmp.file("v.mp4")}}},
       {"--out " + tmp.file("v.mp4"), "is also --log"}},
      {"a file inside a folder the run replaces",
       {"guide", {}, {{"--log", tmp.file("rec/log.csv")}, {"--record", tmp.file("rec"), K::kFolder}}},
       {"--log", "lies inside --record"}},
      {"video and log in the snapshot folder",
       {"guide", {}, {{"--out", tmp.file("v.mp4")}, {"--snapshots", tmp.string(), K::kFilesInFolder}}},
       {}},
      {"the command's own folder",
       {"plan", {}, {{"--out", plan, K::kFolder}}},
       {}},
      {"another command's folder",
       {"phantom", {}, {{"--out", plan, K::kFolder}}},
       {"made by `crepuscular plan`", "--overwrite"}},
      {"another command's folder with --overwrite",
       {"phantom", {}, {{"--out", plan, K::kFolder}}, true},
       {}},
      {"a folder of an older crepuscular (its marker names no command)",
       {"plan", {}, {{"--out", tmp.file("old"), K::kFolder}}},
       {"older crepuscular", "--overwrite"}},
      {"--overwrite never lets an output replace an input",
       {"plan", {{"--labels", labels}}, {{"--out", phantom.string(), K::kFolder}}, true},
       {"holds the input --labels"}},
  };
  for (const Row& row : rows) {
    const std::string why = why_run_refused(row.run);
    if (row.refusal.empty()) {
      EXPECT_EQ(why, "") << row.what;
    } else {
      EXPECT_FALSE(why.empty()) << row.what;
      for (const std::string& part : row.refusal) {
        EXPECT_NE(why.find(part), std::string::npos) << row.what << ": " << why;
      }
    }
  }
}

}  // namespace
}  // namespace crepuscular
