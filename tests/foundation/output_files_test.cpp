// Tests of foundation/output_files: a file or folder appears complete or not at all, and a failed
// write leaves nothing behind.
#include "foundation/output_files.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/interruptions.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <cstdio>
#include <fstream>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular {
namespace {

using test::expect_error_containing;

namespace fs = std::filesystem;

// A fresh empty folder (no ".partial" sibling) in this program's temporary folder.
fs::path temp_dir(const std::string& name) {
  const fs::path dir = test::fresh_path(name);
  fs::create_directories(dir);
  return dir;
}

std::vector<std::string> entries(const fs::path& dir) {
  std::vector<std::string> names;
  for (const auto& e : fs::directory_iterator(dir)) names.push_back(e.path().filename().string());
  std::sort(names.begin(), names.end());
  return names;
}

std::string read(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

TEST(OutputFiles, TemporarySiblingKeepsFolderAndExtension) {
  const std::string t = temporary_sibling("some/dir/plan.nii.gz");
  EXPECT_EQ(fs::path(t).parent_path(), fs::path("some/dir"));
  EXPECT_EQ(t.rfind(".nii.gz"), t.size() - 7);
  EXPECT_EQ(fs::path(t).filename().string().rfind(".tmp-", 0), 0u);
  EXPECT_NE(temporary_sibling("plan.json"), temporary_sibling("plan.json"));  // unique
}

TEST(OutputFiles, TextAndBinaryFilesAreWrittenAndReplaced) {
  const fs::path dir = temp_dir("text");
  write_text_file((dir / "a.txt").string(), "first\n");
  write_text_file((dir / "a.txt").string(), "second\n");
  EXPECT_EQ(read(dir / "a.txt"), "second\n");
  const unsigned char bytes[4] = {0xFF, 0xD8, 0x00, 0x01};
  write_binary_file((dir / "b.bin").string(), bytes, sizeof bytes);
  EXPECT_EQ(read(dir / "b.bin"), std::string("\xFF\xD8\x00\x01", 4));
  EXPECT_EQ(entries(dir), (std::vector<std::string>{"a.txt", "b.bin"}));
}

TEST(OutputFiles, FailedWriterLeavesNothingAndKeepsTheOldFile) {
  const fs::path dir = temp_dir("writer");
  const std::string path = (dir / "camera.yaml").string();
  write_text_file(path, "old\n");
  expect_error_containing(
      [&] {
        write_file_atomically(path, [&](const std::string& temporary) {
          std::ofstream(temporary) << "half a fil";
          throw Error(path + ": the writer failed");
        });
      },
      {"camera.yaml", "writer failed"});
  EXPECT_EQ(entries(dir), std::vector<std::string>{"camera.yaml"});
  EXPECT_EQ(read(path), "old\n");
}

TEST(OutputFiles, WriterGetsASiblingWithTheSameExtension) {
  const fs::path dir = temp_dir("sibling");
  const std::string path = (dir / "out.png").string();
  write_file_atomically(path, [&](const std::string& temporary) {
    EXPECT_EQ(fs::path(temporary).parent_path(), dir);
    EXPECT_EQ(fs::path(temporary).extension(), ".png");
    std::ofstream(temporary) << "png";
  });
  EXPECT_EQ(read(path), "png");
}

TEST(OutputFiles, FailedRenameNamesTheFileAndLeavesNoTemporary) {
  const fs::path dir = temp_dir("rename");
  fs::create_directories(dir / "taken.txt" / "inside");  // a non-empty folder has the name
  expect_error_containing([&] { write_text_file((dir / "taken.txt").string(), "x"); },
                          {"taken.txt"});
  EXPECT_EQ(entries(dir), std::vector<std::string>{"taken.txt"});
}

TEST(OutputFiles, MissingFolderIsAnErrorNamingTheFile) {
  const fs::path dir = temp_dir("missing");
  expect_error_containing(
      [&] { write_text_file((dir / "no" / "such" / "plan.json").string(), "{}"); }, {"plan.json"});
  EXPECT_TRUE(entries(dir).empty());
}

// `track --out DIR` tracked a whole recording before the rename onto the folder failed: a file
// that cannot take its name is refused when it is opened, before any work.
TEST(OutputFiles, PendingFileOntoAFolderOrIntoNoFolderIsRefusedAtOnce) {
  const fs::path dir = temp_dir("pending_folder");
  fs::create_directories(dir / "poses");
  expect_error_containing([&] { PendingFile f((dir / "poses").string()); },
                          {"poses", "it is a folder"});
  expect_error_containing([&] { PendingFile f((dir / "none" / "poses.csv").string()); },
                          {"poses.csv", "does not exist"});
  EXPECT_EQ(entries(dir), std::vector<std::string>{"poses"});
}

TEST(OutputFiles, PendingFileIsRemovedUnlessCommitted) {
  const fs::path dir = temp_dir("pending");
  {
    PendingFile f((dir / "log.csv").string());
    std::ofstream(f.temporary()) << "a,b\n";
    EXPECT_EQ(entries(dir).size(), 1u);
  }
  EXPECT_TRUE(entries(dir).empty());
  PendingFile f((dir / "log.csv").string());
  std::ofstream(f.temporary()) << "a,b\n";
  f.commit();
  EXPECT_TRUE(f.committed());
  EXPECT_EQ(entries(dir), std::vector<std::string>{"log.csv"});
}

TEST(OutputFiles, StagedDirectoryAppearsOnlyOnCommitAndReplaces) {
  const fs::path root = temp_dir("staged");
  const std::string final_path = (root / "plan").string();
  {
    StagedDirectory out(final_path);
    write_text_file(out.file("plan.json"), "{}\n");
    EXPECT_FALSE(fs::exists(final_path));
  }
  EXPECT_TRUE(entries(root).empty());  // never committed: nothing left
  {
    StagedDirectory out(final_path);
    write_text_file(out.file("a.txt"), "1");
    out.commit();
  }
  {
    StagedDirectory out(final_path + "/");
    write_text_file(out.file("b.txt"), "2");
    out.commit();
  }
  EXPECT_EQ(entries(root), std::vector<std::string>{"plan"});
  // Replaced as a whole; the marker names what was written.
  EXPECT_EQ(entries(final_path), (std::vector<std::string>{".crepuscular-output", "b.txt"}));
  std::ifstream marker(final_path + "/.crepuscular-output");
  std::string first, second;
  std::getline(marker, first);
  std::getline(marker, second);
  EXPECT_EQ(first, "crepuscular output folder");
  EXPECT_EQ(second, "b.txt");
}

// --out naming a folder the user owns never deletes it: only an empty folder or one this tool
// wrote whole is replaced; the refusal comes before any work and names the folder and the files.
TEST(OutputFiles, StagedDirectoryNeverReplacesWhatItDidNotWrite) {
  const fs::path root = temp_dir("owned");
  const std::string mine = (root / "patient").string();
  fs::create_directories(mine);
  write_text_file(mine + "/ct.nii.gz", "scan");
  expect_error_containing([&] { StagedDirectory out(mine); },
                          {"patient", "not written by crepuscular"});
  EXPECT_EQ(entries(mine), std::vector<std::string>{"ct.nii.gz"});
  // A plan folder to which the user added a file.
  const std::string plan = (root / "plan").string();
  {
    StagedDirectory out(plan);
    write_text_file(out.file("plan.json"), "{}");
    out.commit();
  }
  write_text_file(plan + "/notes.txt", "mine");
  expect_error_containing([&] { StagedDirectory out(plan); }, {"plan", "notes.txt"});
  // Added while a run was working: refused at commit, and the staged output goes.
  fs::remove(plan + "/notes.txt");
  {
    StagedDirectory out(plan);
    write_text_file(out.file("plan.json"), "{\"new\": 1}");
    write_text_file(plan + "/notes.txt", "mine");
    expect_error_containing([&] { out.commit(); }, {"notes.txt"});
  }
  EXPECT_EQ(entries(plan), (std::vector<std::string>{".crepuscular-output", "notes.txt", "plan.json"}));
  for (const std::string& e : entries(root)) EXPECT_EQ(e.find(".partial"), std::string::npos) << e;
  // An empty folder is taken.
  const std::string empty = (root / "empty").string();
  fs::create_directories(empty);
  StagedDirectory out(empty);
  write_text_file(out.file("a.txt"), "1");
  out.commit();
  EXPECT_EQ(entries(empty), (std::vector<std::string>{".crepuscular-output", "a.txt"}));
}

// A run killed before it committed leaves its hidden staging folder; the next run removes it
// when its process is gone, and leaves the staging of a live process alone.
TEST(OutputFiles, StagingOfADeadProcessIsRemovedByTheNextRun) {
  const fs::path root = temp_dir("stale");
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) _exit(0);
  int status = 0;
  waitpid(child, &status, 0);  // a pid that no longer runs
  const fs::path dead = root / (".plan.partial-" + std::to_string(child));
  const fs::path alive = root / (".plan.partial-" + std::to_string(getppid()));
  fs::create_directories(dead);
  fs::create_directories(alive);
  write_text_file((dead / "big.nii").string(), "x");
  {
    StagedDirectory out((root / "plan").string());
    out.commit();
  }
  EXPECT_FALSE(fs::exists(dead));
  EXPECT_TRUE(fs::exists(alive));
}

// A process id that no longer runs: a child that has exited and been waited for.
pid_t dead_pid() {
  const pid_t child = fork();
  if (child == 0) _exit(0);
  int status = 0;
  waitpid(child, &status, 0);
  return child;
}

// What killed runs left (temporary siblings, staging folders) goes; a live process's and the
// user's files that merely look alike stay.
TEST(OutputFiles, LeftoversOfDeadRunsAreRemovedAndNothingElse) {
  const fs::path root = temp_dir("leftovers");
  const std::string dead = std::to_string(dead_pid());
  const std::string alive = std::to_string(getppid());
  const std::vector<std::string> gone = {".tmp-" + dead + "-3-overlay.mp4",
                                         ".tmp-" + dead + "-1-log.csv"};
  const std::vector<std::string> kept = {".tmp-" + alive + "-3-overlay.mp4",
                                         ".tmp-notes.txt",
                                         ".tmp-" + dead + "-x-log.csv",
                                         "tmp-" + dead + "-1-log.csv",
                                         ".plan.partial-" + alive,
                                         "plan.partial-" + dead,
                                         "rec.partial"};
  for (const auto& n : gone) write_text_file((root / n).string(), "x");
  for (const auto& n : kept) write_text_file((root / n).string(), "x");
  fs::create_directories(root / (".plan.partial-" + dead));
  fs::create_directories(root / (".plan.partial-" + dead + ".old"));
  remove_stale_outputs(root.string());
  std::vector<std::string> expected = kept;
  std::sort(expected.begin(), expected.end());
  EXPECT_EQ(entries(root), expected);
}

// The marker names the command that made the folder; markers without it still count as ours.
TEST(OutputFiles, MarkerNamesTheCommand) {
  const fs::path root = temp_dir("maker");
  EXPECT_EQ(output_folder_maker(root.string()), std::nullopt);
  {
    const OutputCommandScope as_plan("plan");
    StagedDirectory out((root / "plan").string());
    write_text_file(out.file("plan.json"), "{}");
    out.commit();
  }
  EXPECT_EQ(output_folder_maker((root / "plan").string()), std::optional<std::string>("plan"));
  EXPECT_EQ(output_command(), "");
  fs::create_directories(root / "old");
  write_text_file((root / "old" / kOutputMarker).string(), "crepuscular output folder\na.txt\n");
  write_text_file((root / "old" / "a.txt").string(), "a");
  EXPECT_EQ(output_folder_maker((root / "old").string()), std::optional<std::string>(""));
  StagedDirectory again((root / "old").string());  // still replaceable: all of it is ours
  again.commit();
}

// Paths recorded while a folder is staged (nested, as the demo's plan inside the demo) name the
// final place; read back during the run they lead to the staging.
TEST(OutputFiles, RecordedPathsNameFinalFolders) {
  const fs::path root = temp_dir("final");
  StagedDirectory demo((root / "demo").string());
  StagedDirectory plan(demo.file("plan"));
  const std::string labels = demo.file("phantom/labels.nii.gz");
  EXPECT_EQ(final_path_of(labels), (root / "demo/phantom/labels.nii.gz").string());
  EXPECT_EQ(final_path_of(plan.file("plan.json")), (root / "demo/plan/plan.json").string());
  EXPECT_EQ(final_path_of(plan.path()), (root / "demo/plan").string());
  EXPECT_EQ(final_path_of("elsewhere/x.nii"), "elsewhere/x.nii");
  EXPECT_EQ(fs::path(staged_path_of((root / "demo/plan/plan.json").string())),
            fs::path(plan.file("plan.json")).lexically_normal());
  EXPECT_EQ(final_path_of(labels).find(".partial-"), std::string::npos);
  // A document written into the staged plan (plan.json's preprocessing, tumor source, scan
  // grids) records the final paths wherever they are nested; other strings stay.
  nlohmann::json doc = {{"file", labels},
                        {"grids", {labels, "a label map"}},
                        {"tumor", {{"file", demo.file("phantom/tumor.nii.gz")}, {"voxels", 12}}}};
  record_final_paths(doc);
  EXPECT_EQ(doc["file"], (root / "demo/phantom/labels.nii.gz").string());
  EXPECT_EQ(doc["grids"][0], (root / "demo/phantom/labels.nii.gz").string());
  EXPECT_EQ(doc["grids"][1], "a label map");
  EXPECT_EQ(doc["tumor"]["file"], (root / "demo/phantom/tumor.nii.gz").string());
  EXPECT_EQ(doc["tumor"]["voxels"], 12);
  EXPECT_EQ(doc.dump().find(".partial-"), std::string::npos) << doc.dump();
}

// A write that meets the file size limit (ulimit -f) fails with an error that says so, and leaves
// nothing (SIGXFSZ ignored, as watch_interruptions does).
TEST(OutputFiles, FileSizeLimitIsAnErrorThatLeavesNothing) {
  const fs::path root = temp_dir("fsize");
  int report[2];
  ASSERT_EQ(pipe(report), 0);
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    signal(SIGXFSZ, SIG_IGN);
    const rlimit limit{4096, 4096};
    setrlimit(RLIMIT_FSIZE, &limit);
    std::string message = "no error";
    try {
      StagedDirectory out((root / "plan").string());
      write_text_file(out.file("big.nii"), std::string(10000, 'x'));
      out.commit();
    } catch (const Error& e) {
      message = e.what();
    }
    try {
      PendingFile log((root / "log.csv").string());
      std::FILE* f = std::fopen(log.temporary().c_str(), "w");
      for (int i = 0; i < 1000; ++i) std::fputs("a row of the log\n", f);
      std::fclose(f);
      log.commit();
      message += " | no error";
    } catch (const Error& e) {
      message += std::string(" | ") + e.what();
    }
    if (::write(report[1], message.data(), message.size()) < 0) _exit(2);
    _exit(0);
  }
  close(report[1]);
  int status = 0;
  waitpid(child, &status, 0);
  char buffer[2048] = {};
  const std::string message(buffer, std::max<ssize_t>(0, ::read(report[0], buffer, sizeof buffer)));
  close(report[0]);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  EXPECT_NE(message.find("big.nii: cannot write: file size limit reached"), std::string::npos)
      << message;
  EXPECT_NE(message.find("log.csv: cannot write: file size limit reached"), std::string::npos)
      << message;
  EXPECT_TRUE(entries(root).empty()) << entries(root).front();
}

// Ctrl-C, SIGTERM or SIGHUP during a run removes its staged folder and temporary files and ends it with
// 128 + the signal; the earlier output stays as it was.
TEST(OutputFiles, InterruptedRunRemovesItsPartialOutput) {
  for (const int sig : {SIGTERM, SIGINT, SIGHUP}) {
    const fs::path root = temp_dir(sig == SIGTERM ? "term" : sig == SIGINT ? "int" : "hup");
    int ready[2];
    ASSERT_EQ(pipe(ready), 0);
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      watch_interruptions();
      StagedDirectory out((root / "plan").string());
      write_text_file(out.file("half.nii"), "x");
      PendingFile video((root / "video.mp4").string());
      write_text_file(video.temporary(), "frames");
      if (::write(ready[1], "r", 1) != 1) _exit(2);
      for (;;) pause();
    }
    char c = 0;
    ASSERT_EQ(::read(ready[0], &c, 1), 1);
    EXPECT_EQ(entries(root).size(), 2u);  // the staging folder and the temporary video
    kill(child, sig);
    int status = 0;
    waitpid(child, &status, 0);
    ASSERT_TRUE(WIFEXITED(status));
    EXPECT_EQ(WEXITSTATUS(status), 128 + sig);
    EXPECT_TRUE(entries(root).empty()) << entries(root).front();
    close(ready[0]);
    close(ready[1]);
  }
}

TEST(OutputFiles, KeptStagingFolderSurvivesAFailureAndMustNotExist) {
  const fs::path root = temp_dir("kept");
  const std::string final_path = (root / "rec").string();
  {
    StagedDirectory out(final_path, StagedDirectory::OnFailure::kKeep);
    EXPECT_EQ(out.path(), final_path + ".partial");
    write_text_file(out.file("frames.csv"), "frame\n");
  }
  EXPECT_EQ(entries(root), std::vector<std::string>{"rec.partial"});  // kept: replayable
  expect_error_containing(
      [&] { StagedDirectory again(final_path, StagedDirectory::OnFailure::kKeep); },
      {"rec.partial", "exists"});
  fs::remove_all(final_path + ".partial");
  StagedDirectory out(final_path, StagedDirectory::OnFailure::kKeep);
  out.commit();
  EXPECT_EQ(entries(root), std::vector<std::string>{"rec"});
  expect_error_containing(
      [&] { StagedDirectory again(final_path, StagedDirectory::OnFailure::kKeep); },
      {"rec", "exists"});
}

}  // namespace
}  // namespace crepuscular
