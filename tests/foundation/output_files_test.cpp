// Tests of foundation/output_files: a file or folder appears complete or not at all, and a failed
// write leaves nothing behind.
#include "foundation/output_files.hpp"
#include "foundation/interruptions.hpp"

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
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

// Ctrl-C or SIGTERM during a run removes its staged folder and temporary files and ends it with
// 128 + the signal; the earlier output stays as it was.
TEST(OutputFiles, InterruptedRunRemovesItsPartialOutput) {
  for (const int sig : {SIGTERM, SIGINT}) {
    const fs::path root = temp_dir(sig == SIGTERM ? "term" : "int");
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
