// Atomic output files and staged output folders.
#include "foundation/output_files.hpp"

#include <signal.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <system_error>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/interruptions.hpp"

namespace fs = std::filesystem;

namespace crepuscular {

namespace {

std::atomic<int> g_counter{0};

void remove_quietly(const std::string& path) {
  std::error_code ignored;
  fs::remove(path, ignored);
}

}  // namespace

void check_file_size_limit(const std::string& temporary, const std::string& path) {
  rlimit limit{};
  if (::getrlimit(RLIMIT_FSIZE, &limit) != 0 || limit.rlim_cur == RLIM_INFINITY) return;
  std::error_code ec;
  const auto size = fs::file_size(temporary, ec);
  if (ec || size < limit.rlim_cur) return;
  throw Error(path + ": cannot write: file size limit reached (ulimit -f: " +
              std::to_string(limit.rlim_cur) + " bytes); nothing was written");
}

std::string temporary_sibling(const std::string& path) {
  const fs::path p(path);
  const fs::path dir = p.has_parent_path() ? p.parent_path() : fs::path(".");
  const std::string name = ".tmp-" + std::to_string(::getpid()) + "-" +
                           std::to_string(++g_counter) + "-" + p.filename().string();
  return (dir / name).string();
}

void commit_file(const std::string& temporary, const std::string& path) {
  std::error_code ec;
  fs::rename(temporary, path, ec);
  if (ec) {
    remove_quietly(temporary);
    throw Error(path + ": cannot write file (" + ec.message() + ")");
  }
}

// ---------------------------------------------------------------------------------------------

PendingFile::PendingFile(std::string path)
    : path_(std::move(path)), temporary_(temporary_sibling(path_)) {
  // Said before any work: the rename at the end could never replace a folder.
  std::error_code ec;
  if (fs::is_directory(path_, ec)) {
    throw Error(path_ + ": cannot be written (it is a folder; give the name of a file)");
  }
  const fs::path parent = fs::path(path_).has_parent_path() ? fs::path(path_).parent_path()
                                                            : fs::path(".");
  if (!fs::is_directory(parent, ec)) {
    throw Error(path_ + ": cannot be written (its folder " + parent.string() + " does not exist)");
  }
  register_partial_output(temporary_);
}

PendingFile::~PendingFile() {
  if (!committed_) remove_quietly(temporary_);
  unregister_partial_output(temporary_);
}

void PendingFile::commit() {
  if (committed_) return;
  check_file_size_limit(temporary_, path_);
  commit_file(temporary_, path_);
  committed_ = true;
  unregister_partial_output(temporary_);
}

PendingTextFile::PendingTextFile(const std::string& path, std::string what,
                                 std::string_view header)
    : file_(path), what_(std::move(what)) {
  out_ = std::fopen(file_.temporary().c_str(), "wb");
  if (!out_) throw Error(path + ": cannot create the " + what_ + " (" + std::strerror(errno) + ")");
  write(std::string(header) + "\n");
}

PendingTextFile::~PendingTextFile() {
  if (out_) std::fclose(out_);  // the temporary goes with file_
}

void PendingTextFile::write(std::string_view text) {
  if (!out_) throw Error(path() + ": " + what_ + " already finished");
  if (std::fwrite(text.data(), 1, text.size(), out_) != text.size()) {
    const int error = errno;
    check_file_size_limit(file_.temporary(), path());
    throw Error(path() + ": cannot write the " + what_ + " (" + std::strerror(error) + ")");
  }
}

void PendingTextFile::commit() {
  if (!out_) return;
  const bool failed = std::ferror(out_) != 0;
  int error = errno;
  const bool closed = std::fclose(out_) == 0;
  if (!closed) error = errno;
  out_ = nullptr;
  if (failed || !closed) {
    check_file_size_limit(file_.temporary(), path());
    throw Error(path() + ": cannot write the " + what_ + " (" + std::strerror(error) + ")");
  }
  file_.commit();
}

void write_file_atomically(const std::string& path,
                           const std::function<void(const std::string& temporary)>& write) {
  PendingFile file(path);
  try {
    write(file.temporary());
  } catch (...) {
    check_file_size_limit(file.temporary(), path);  // the writer's own message may not say why
    throw;
  }
  file.commit();
}

void write_binary_file(const std::string& path, const void* data, std::size_t size) {
  write_file_atomically(path, [&](const std::string& temporary) {
    std::FILE* f = std::fopen(temporary.c_str(), "wb");
    if (!f) throw Error(path + ": cannot open for writing");
    const bool written = size == 0 || std::fwrite(data, 1, size, f) == size;
    if (std::fclose(f) != 0 || !written) {
      throw Error(path + ": write failed (" + std::strerror(errno) + ")");
    }
  });
}

void write_text_file(const std::string& path, std::string_view text) {
  write_binary_file(path, text.data(), text.size());
}

// ---------------------------------------------------------------------------------------------

namespace {

constexpr const char* kMarkerFirstLine = "crepuscular output folder";
constexpr const char* kMarkerMadeBy = "// made by crepuscular ";

std::string g_output_command;  // set before the work, on the main thread

// Staging folders of this process (absolute) -> their final paths.
std::mutex g_staging_mutex;
std::map<fs::path, fs::path>& staging_to_final() {
  static std::map<fs::path, fs::path> paths;
  return paths;
}

fs::path absolute_normal(const fs::path& p) {
  std::error_code ec;
  const fs::path a = fs::absolute(p, ec);
  return (ec ? p : a).lexically_normal();
}

// `path` relative to `folder` when it lies in it (or is it: "."), else nullopt.
std::optional<fs::path> relative_within(const fs::path& path, const fs::path& folder) {
  auto f = folder.begin();
  auto p = path.begin();
  for (; f != folder.end(); ++f, ++p) {
    if (f->empty()) continue;  // a trailing separator
    if (p == path.end() || *p != *f) return std::nullopt;
  }
  fs::path rest;
  for (; p != path.end(); ++p) rest /= *p;
  return rest.empty() ? fs::path(".") : rest;
}

// The process id in a name of a killed run's leftovers, ".tmp-PID-N-NAME" or
// ".NAME.partial-PID[.old]"; 0 when `name` is neither.
pid_t leftover_pid(const std::string& name) {
  const auto digits = [](const std::string& t) {
    return !t.empty() && t.size() <= 9 && t.find_first_not_of("0123456789") == std::string::npos;
  };
  if (name.rfind(".tmp-", 0) == 0) {
    const size_t a = name.find('-', 5);
    const size_t b = a == std::string::npos ? a : name.find('-', a + 1);
    if (b == std::string::npos || b + 1 >= name.size()) return 0;
    const std::string pid = name.substr(5, a - 5);
    if (!digits(pid) || !digits(name.substr(a + 1, b - a - 1))) return 0;
    return pid_t(std::stol(pid));
  }
  const size_t at = name.rfind(".partial-");
  if (name.size() < 2 || name[0] != '.' || at == std::string::npos || at < 2) return 0;
  std::string pid = name.substr(at + 9);
  if (pid.size() > 4 && pid.compare(pid.size() - 4, 4, ".old") == 0) pid.resize(pid.size() - 4);
  return digits(pid) ? pid_t(std::stol(pid)) : 0;
}

// The entries of `dir` (names), empty when it cannot be read.
std::vector<std::string> entries_of(const fs::path& dir) {
  std::vector<std::string> names;
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    names.push_back(it->path().filename().string());
  }
  std::sort(names.begin(), names.end());
  return names;
}

// Why an existing folder may not be replaced, or "" when it may: it is empty, or this tool made
// it and it holds nothing else (the marker lists what the tool wrote).
std::string why_not_replaceable(const fs::path& dir) {
  const std::vector<std::string> present = entries_of(dir);
  if (present.empty()) return "";
  std::ifstream marker(dir / kOutputMarker);
  std::string line;
  if (!marker || !std::getline(marker, line) || line != kMarkerFirstLine) {
    return "exists and was not written by crepuscular (it has no " + std::string(kOutputMarker) +
           "); it is left as it is: choose a new folder, or empty or remove this one yourself";
  }
  std::set<std::string> made = {kOutputMarker};
  while (std::getline(marker, line)) {
    if (line.rfind("//", 0) != 0) made.insert(line);
  }
  std::vector<std::string> others;
  for (const std::string& name : present) {
    if (!made.count(name)) others.push_back(name);
  }
  if (others.empty()) return "";
  std::string list;
  for (size_t i = 0; i < others.size() && i < 5; ++i) list += (i ? ", " : "") + others[i];
  if (others.size() > 5) list += ", ...";
  return "holds files crepuscular did not write (" + list +
         "); it is left as it is: choose a new folder, or move those files away";
}

}  // namespace

void set_output_command(const std::string& command) { g_output_command = command; }
const std::string& output_command() { return g_output_command; }

OutputCommandScope::OutputCommandScope(const std::string& command)
    : previous_(g_output_command) {
  g_output_command = command;
}
OutputCommandScope::~OutputCommandScope() { g_output_command = previous_; }

std::optional<std::string> output_folder_maker(const std::string& dir) {
  std::ifstream marker(fs::path(dir) / kOutputMarker);
  std::string line;
  if (!marker || !std::getline(marker, line) || line != kMarkerFirstLine) return std::nullopt;
  const std::string made_by = kMarkerMadeBy;
  while (std::getline(marker, line)) {
    if (line.rfind(made_by, 0) == 0) return line.substr(made_by.size());
  }
  return std::string();
}

void remove_stale_outputs(const std::string& dir) {
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    const pid_t pid = leftover_pid(it->path().filename().string());
    if (pid <= 0 || pid == ::getpid()) continue;
    if (::kill(pid, 0) == 0 || errno != ESRCH) continue;  // alive, or not ours to judge
    std::error_code rm;
    fs::remove_all(it->path(), rm);
  }
}

namespace {

// `path` moved from staging to final paths (`to_final`) or back, nested folders included.
std::string mapped_path(const std::string& path, bool to_final) {
  fs::path p = absolute_normal(path);
  bool mapped = false;
  {
    std::lock_guard<std::mutex> lock(g_staging_mutex);
    for (int levels = 0, again = 1; again && levels < 16; ++levels) {
      again = 0;
      // Backwards: a folder staged inside another comes before it.
      for (auto it = staging_to_final().rbegin(); it != staging_to_final().rend(); ++it) {
        const fs::path& from = to_final ? it->first : it->second;
        const fs::path& to = to_final ? it->second : it->first;
        if (const auto rest = relative_within(p, from)) {
          p = *rest == "." ? to : (to / *rest).lexically_normal();
          mapped = true;
          again = 1;
          break;
        }
      }
    }
  }
  if (!mapped) return path;
  if (fs::path(path).is_relative()) {
    std::error_code ec;
    const fs::path relative = p.lexically_relative(fs::current_path(ec));
    if (!ec && !relative.empty()) return relative.string();
  }
  std::string text = p.string();
  while (text.size() > 1 && text.back() == '/') text.pop_back();
  return text;
}

}  // namespace

std::string final_path_of(const std::string& path) { return mapped_path(path, true); }
std::string staged_path_of(const std::string& path) { return mapped_path(path, false); }

StagedDirectory::StagedDirectory(std::string final_path, OnFailure on_failure)
    : final_(std::move(final_path)), on_failure_(on_failure) {
  while (final_.size() > 1 && final_.back() == '/') final_.pop_back();
  const fs::path fp(final_);
  const fs::path parent = fp.has_parent_path() ? fp.parent_path() : fs::path(".");
  std::error_code ec;
  if (on_failure_ == OnFailure::kKeep) {
    staging_ = final_ + ".partial";
    if (fs::exists(fp, ec)) throw Error(final_ + ": exists; choose another folder or remove it");
    if (fs::exists(staging_, ec)) {
      throw Error(staging_ + ": exists (left by an interrupted run); move or remove it first");
    }
  } else {
    if (fs::exists(fp, ec) && !fs::is_directory(fp, ec)) {
      throw Error(final_ + ": exists and is not a folder");
    }
    if (fs::is_directory(fp, ec)) {
      const std::string why = why_not_replaceable(fp);
      if (!why.empty()) throw Error(final_ + ": " + why);
    }
    remove_stale_outputs(parent.string());
    staging_ = (parent / ("." + fp.filename().string() + ".partial-" + std::to_string(::getpid())))
                   .string();
  }
  fs::create_directories(parent, ec);
  if (ec) throw Error(parent.string() + ": cannot create folder (" + ec.message() + ")");
  if (on_failure_ == OnFailure::kRemove) fs::remove_all(staging_, ec);
  fs::create_directory(staging_, ec);
  if (ec) throw Error(staging_ + ": cannot create folder (" + ec.message() + ")");
  if (on_failure_ == OnFailure::kRemove) register_partial_output(staging_);
  std::lock_guard<std::mutex> lock(g_staging_mutex);
  staging_to_final()[absolute_normal(staging_)] = absolute_normal(final_);
}

StagedDirectory::~StagedDirectory() {
  if (!committed_ && on_failure_ == OnFailure::kRemove) {
    std::error_code ec;
    fs::remove_all(staging_, ec);
  }
  unregister_partial_output(staging_);
  std::lock_guard<std::mutex> lock(g_staging_mutex);
  staging_to_final().erase(absolute_normal(staging_));
}

void StagedDirectory::commit() {
  if (committed_) return;
  std::error_code ec;
  if (on_failure_ == OnFailure::kKeep) {
    fs::rename(staging_, final_, ec);
    if (ec) {
      throw Error(staging_ + ": cannot rename to " + final_ + " (" + ec.message() +
                  "); the output is complete under the first name");
    }
    committed_ = true;
    return;
  }
  // The marker: what this run wrote, so that a later run may replace exactly that.
  {
    std::ofstream marker(fs::path(staging_) / kOutputMarker, std::ios::trunc);
    marker << kMarkerFirstLine << "\n";
    if (!g_output_command.empty()) marker << kMarkerMadeBy << g_output_command << "\n";
    for (const std::string& name : entries_of(staging_)) {
      if (name != kOutputMarker) marker << name << "\n";
    }
    if (!marker.flush()) {
      throw Error(staging_ + "/" + kOutputMarker + ": cannot write");
    }
  }
  const std::string old = staging_ + ".old";
  const bool had_old = fs::exists(final_, ec);
  if (had_old) {
    const std::string why = why_not_replaceable(final_);
    if (!why.empty()) throw Error(final_ + ": " + why);
    fs::remove_all(old, ec);
    fs::rename(final_, old, ec);
    if (ec) throw Error(final_ + ": cannot replace the existing folder (" + ec.message() + ")");
  }
  fs::rename(staging_, final_, ec);
  if (ec) {
    if (had_old) fs::rename(old, final_, ec);
    throw Error(final_ + ": cannot move the finished output into place (" + ec.message() + ")");
  }
  committed_ = true;
  unregister_partial_output(staging_);
  if (had_old) fs::remove_all(old, ec);
}

}  // namespace crepuscular
