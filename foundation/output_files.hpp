// Outputs that appear complete or not at all (docs/ARCHITECTURE.md §3): files are written under a
// temporary name in the same folder and renamed; whole output folders are staged beside their final
// place. Every module writes its outputs through these; errors name the final path.
#pragma once

#include <cstddef>
#include <cstdio>
#include <functional>
#include <optional>
#include <string>
#include <string_view>

namespace crepuscular {

// A temporary path in the folder of `path` whose name ends with the file name of `path` (so
// format detection by extension still works), e.g. "dir/.tmp-1234-1-plan.json".
std::string temporary_sibling(const std::string& path);

// Renames `temporary` onto `path` (atomic within one file system); on failure removes
// `temporary` and throws Error naming `path`.
void commit_file(const std::string& temporary, const std::string& path);

// Throws Error naming `path` when `temporary`, its file in progress, has reached the file size
// limit (RLIMIT_FSIZE, `ulimit -f`; SIGXFSZ is ignored, foundation/interruptions.hpp): the write
// stopped there, whether or not the writer noticed. A file of exactly the limit counts as cut.
// write_file_atomically and PendingFile::commit check it.
void check_file_size_limit(const std::string& temporary, const std::string& path);

// Writes `path` through a temporary sibling: `write(temporary)` creates the file at the path it
// is given (a temporary_sibling of `path`, same extension), which then takes the name `path`.
// For files written by other libraries (OpenCV FileStorage, imwrite, ITK writers). If `write`
// throws, the temporary is removed and the exception passes on: its message should name `path`.
void write_file_atomically(const std::string& path,
                           const std::function<void(const std::string& temporary)>& write);

// Writes text or bytes to `path` through a temporary sibling; throws Error naming the path on
// failure (nothing is left behind then).
void write_text_file(const std::string& path, std::string_view text);
void write_binary_file(const std::string& path, const void* data, std::size_t size);

// A file written piece by piece (a CSV log, a video) under a temporary sibling name; commit()
// gives it its final name. If commit() is never called (a failed run), the destructor removes
// the temporary file.
class PendingFile {
 public:
  explicit PendingFile(std::string path);
  ~PendingFile();
  PendingFile(const PendingFile&) = delete;
  PendingFile& operator=(const PendingFile&) = delete;

  // Where to write until commit().
  const std::string& temporary() const { return temporary_; }
  const std::string& path() const { return path_; }
  bool committed() const { return committed_; }
  // Renames the temporary onto path() (the writer must have closed it); throws Error naming
  // path() on failure, after removing the temporary.
  void commit();

 private:
  std::string path_;
  std::string temporary_;
  bool committed_ = false;
};

// A text file (a CSV, a log) written piece by piece through a PendingFile: `header` is its first
// line; commit() closes it and gives it its final name, a writer destroyed without commit() (a
// failed run) leaves nothing. Errors name the path and `what` ("poses CSV"): "PATH: cannot write
// the poses CSV (reason)", a write past the file size limit said as such.
class PendingTextFile {
 public:
  PendingTextFile(const std::string& path, std::string what, std::string_view header);
  ~PendingTextFile();
  PendingTextFile(const PendingTextFile&) = delete;
  PendingTextFile& operator=(const PendingTextFile&) = delete;

  void write(std::string_view text);  // as given: lines end with their own '\n'
  void commit();
  const std::string& path() const { return file_.path(); }

 private:
  PendingFile file_;  // declared first: removed after the stream has closed it
  std::string what_;
  std::FILE* out_ = nullptr;
};

// The file a staged folder gets on commit (kRemove): it names what the tool wrote there. Only an
// empty folder, or one whose entries are all named by its marker, is ever replaced. Its lines:
// "crepuscular output folder", then "// made by crepuscular COMMAND" (a line no file name can be:
// readers before it take it for one more name), then one line per entry written.
constexpr const char* kOutputMarker = ".crepuscular-output";

// The command whose folders this process makes ("plan"), named in the marker of every folder it
// commits; "" (the start) names none. Set once before the work (apps/run_paths).
void set_output_command(const std::string& command);
const std::string& output_command();

// While it lives, committed folders name `command` instead (the demo's phantom/, plan/ and
// slices/ are those commands' folders); the earlier name comes back after.
class OutputCommandScope {
 public:
  explicit OutputCommandScope(const std::string& command);
  ~OutputCommandScope();
  OutputCommandScope(const OutputCommandScope&) = delete;
  OutputCommandScope& operator=(const OutputCommandScope&) = delete;

 private:
  std::string previous_;
};

// What the marker of `dir` says made it: nullopt when `dir` has no marker (not crepuscular's),
// "" when the marker names no command (written before markers named one), else the command.
std::optional<std::string> output_folder_maker(const std::string& dir);

// Removes from `dir` what killed runs left there: temporary siblings ".tmp-PID-N-NAME" and
// staging folders ".NAME.partial-PID" (and their ".old") of processes that no longer run. Files of
// a live process, and names not of these forms, stay.
void remove_stale_outputs(const std::string& dir);

// The path `path` will have once the staged folders of this process that hold it are committed
// (for paths a file records: a registration's inputs, a session's plan); other paths unchanged.
std::string final_path_of(const std::string& path);
// The reverse, for reading back a recorded path during the run: where a final path of a folder
// this process still stages is now (its staging); other paths unchanged.
std::string staged_path_of(const std::string& path);

// A folder written in full before it takes its final name.
class StagedDirectory {
 public:
  // What becomes of a staged folder that is never committed.
  enum class OnFailure {
    // Staged as the hidden ".NAME.partial-PID" beside the final path and removed by the
    // destructor (and by a later run, when a killed process left it); commit() replaces an
    // earlier folder of the final name only when it is empty or this tool wrote all of it
    // (kOutputMarker); anything else is refused with Error, before any work.
    kRemove,
    // Staged as "FINAL.partial", which stays where it is (usable as it is, e.g. an interrupted
    // recording that replays). Neither FINAL nor FINAL.partial may exist beforehand (Error);
    // commit() renames FINAL.partial to FINAL.
    kKeep,
  };

  explicit StagedDirectory(std::string final_path, OnFailure on_failure = OnFailure::kRemove);
  ~StagedDirectory();
  StagedDirectory(const StagedDirectory&) = delete;
  StagedDirectory& operator=(const StagedDirectory&) = delete;

  // The staging folder: where outputs go until commit().
  const std::string& path() const { return staging_; }
  std::string file(const std::string& name) const { return staging_ + "/" + name; }
  const std::string& final_path() const { return final_; }
  bool committed() const { return committed_; }
  // Moves the staging folder to the final name; throws Error on failure (kKeep: the complete
  // output then stays under the staging name, which the message says).
  void commit();

 private:
  std::string final_;
  std::string staging_;
  OnFailure on_failure_;
  bool committed_ = false;
};

}  // namespace crepuscular
