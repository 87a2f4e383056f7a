// A fresh folder for one test (or one suite), removed with everything in it when the object goes.
#pragma once

#include <filesystem>
#include <string>

namespace crepuscular::test {

class TemporaryFolder {
 public:
  // Creates an empty folder under the system's temporary directory whose name holds the running
  // test's suite and name (the suite alone in SetUpTestSuite), the process id and a counter, so
  // that parallel test programs and several folders in one test never meet.
  TemporaryFolder();
  ~TemporaryFolder();  // removes the folder, ignoring errors
  TemporaryFolder(const TemporaryFolder&) = delete;
  TemporaryFolder& operator=(const TemporaryFolder&) = delete;

  const std::filesystem::path& path() const { return path_; }
  operator const std::filesystem::path&() const { return path_; }  // NOLINT: used as a path
  std::filesystem::path operator/(const std::filesystem::path& name) const { return path_ / name; }
  std::string string() const { return path_.string(); }
  // The path of `name` inside the folder, as a string (what the libraries' file arguments take).
  std::string file(const std::string& name) const { return (path_ / name).string(); }

 private:
  std::filesystem::path path_;
};

// A path `name` (not created) in a temporary folder of this test program, removed at its exit:
// for outputs that must not exist beforehand. Whatever was at `name`, or at its staging sibling
// `name`.partial, is removed first.
std::filesystem::path fresh_path(const std::string& name);

}  // namespace crepuscular::test
