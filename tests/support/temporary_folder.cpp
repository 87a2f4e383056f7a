#include "tests/support/temporary_folder.hpp"

#include <gtest/gtest.h>
#include <unistd.h>

#include <atomic>
#include <string>

namespace crepuscular::test {
namespace {

// The running test's "Suite.Name", the suite alone between tests, or "" outside any suite, with
// characters that do not belong in a file name (parameterised tests' '/') replaced.
std::string test_name() {
  const ::testing::UnitTest* unit = ::testing::UnitTest::GetInstance();
  std::string name;
  if (const ::testing::TestInfo* info = unit->current_test_info()) {
    name = std::string(info->test_suite_name()) + "." + info->name();
  } else if (const ::testing::TestSuite* suite = unit->current_test_suite()) {
    name = suite->name();
  }
  for (char& c : name) {
    if (c == '/' || c == ' ') c = '_';
  }
  return name;
}

}  // namespace

TemporaryFolder::TemporaryFolder() {
  static std::atomic<int> counter{0};
  const std::string name = test_name();
  path_ = std::filesystem::temp_directory_path() /
          ("crepuscular_test_" + (name.empty() ? std::string() : name + "_") +
           std::to_string(::getpid()) + "_" + std::to_string(counter++));
  std::filesystem::remove_all(path_);
  std::filesystem::create_directories(path_);
}

TemporaryFolder::~TemporaryFolder() {
  std::error_code ignored;
  std::filesystem::remove_all(path_, ignored);
}

std::filesystem::path fresh_path(const std::string& name) {
  static const TemporaryFolder folder;
  const std::filesystem::path path = folder / name;
  std::filesystem::remove_all(path);
  std::filesystem::remove_all(path.string() + ".partial");
  return path;
}

}  // namespace crepuscular::test
