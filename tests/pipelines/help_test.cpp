// The command line's own help: `crepuscular --help` lists each command in one line, and each
// command's --help keeps its whole description and options.
#include <gtest/gtest.h>

#include <set>
#include <sstream>
#include <string>

#include "tests/support/cli.hpp"

namespace crepuscular {
namespace {

const std::set<std::string> kCommands = {"phantom",  "plan",      "area",     "slices", "view",
                                         "render",   "evaluate",  "synth",    "record", "track",
                                         "calibrate", "register", "guide",    "demo"};

TEST(Help, TopLevelListsEachCommandInOneLine) {
  std::string out;
  ASSERT_EQ(test::run_cli("--help", &out), 0) << out;
  std::istringstream in(out);
  std::string line;
  bool listing = false;
  std::set<std::string> listed;
  int lines = 0;
  while (std::getline(in, line)) {
    if (line == "Subcommands:") {
      listing = true;
      continue;
    }
    if (!listing || line.empty()) continue;
    ++lines;
    ASSERT_EQ(line.rfind("  ", 0), 0u) << line;
    const std::string name = line.substr(2, line.find(' ', 2) - 2);
    EXPECT_TRUE(kCommands.count(name)) << "not a command line: " << line;
    listed.insert(name);
    EXPECT_LE(line.size(), 160u) << line;
  }
  EXPECT_EQ(listed, kCommands);
  EXPECT_EQ(lines, int(kCommands.size()));  // one line each, nothing of their descriptions beyond
}

TEST(Help, EachCommandKeepsItsWholeDescription) {
  std::string out;
  ASSERT_EQ(test::run_cli("track --help", &out), 0) << out;
  EXPECT_NE(out.find("frame,timestamp_ns,board,state"), std::string::npos) << out;
  EXPECT_NE(out.find("--details"), std::string::npos);
  EXPECT_NE(out.find("--no-refine-edges"), std::string::npos);
  ASSERT_EQ(test::run_cli("calibrate --help", &out), 0) << out;
  EXPECT_NE(out.find("pivot"), std::string::npos);
}

}  // namespace
}  // namespace crepuscular
