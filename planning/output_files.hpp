// Outputs that appear complete or not at all: files are written under a temporary name in the
// same folder and renamed; whole output folders are staged beside their final place.
#pragma once

#include <string>

namespace crepuscular::planning {

// A temporary path in the folder of `path` whose name ends with the file name of `path` (so
// format detection by extension still works), e.g. "dir/.tmp-1234-1-plan.json".
std::string temporary_sibling(const std::string& path);

// Renames `temporary` onto `path` (atomic within one file system); throws Error on failure.
void commit_file(const std::string& temporary, const std::string& path);

// Writes text to `path` through a temporary sibling; throws Error naming the path on failure.
void write_text_file(const std::string& path, const std::string& text);

// A folder written in full before it takes its final name. Outputs go to path(); commit() moves
// it to the final name (replacing an earlier folder of that name); if commit() is never called,
// the destructor removes everything that was written.
class StagedDirectory {
 public:
  explicit StagedDirectory(std::string final_path);
  ~StagedDirectory();
  StagedDirectory(const StagedDirectory&) = delete;
  StagedDirectory& operator=(const StagedDirectory&) = delete;

  const std::string& path() const { return staging_; }
  std::string file(const std::string& name) const { return staging_ + "/" + name; }
  const std::string& final_path() const { return final_; }
  void commit();

 private:
  std::string final_;
  std::string staging_;
  bool committed_ = false;
};

}  // namespace crepuscular::planning
