// Atomic output files and staged output folders.
#include "foundation/output_files.hpp"

#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdio>
#include <filesystem>
#include <fstream>
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
  commit_file(temporary_, path_);
  committed_ = true;
  unregister_partial_output(temporary_);
}

void write_file_atomically(const std::string& path,
                           const std::function<void(const std::string& temporary)>& write) {
  PendingFile file(path);
  write(file.temporary());
  file.commit();
}

void write_binary_file(const std::string& path, const void* data, std::size_t size) {
  write_file_atomically(path, [&](const std::string& temporary) {
    std::FILE* f = std::fopen(temporary.c_str(), "wb");
    if (!f) throw Error(path + ": cannot open for writing");
    const bool written = size == 0 || std::fwrite(data, 1, size, f) == size;
    if (std::fclose(f) != 0 || !written) throw Error(path + ": write failed (disk full?)");
  });
}

void write_text_file(const std::string& path, std::string_view text) {
  write_binary_file(path, text.data(), text.size());
}

// ---------------------------------------------------------------------------------------------

namespace {

constexpr const char* kMarkerFirstLine = "crepuscular output folder";

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
  while (std::getline(marker, line)) made.insert(line);
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

// Staging folders ".NAME.partial-PID" beside `final_path` whose process no longer runs (a killed
// run's): removed, since nothing else ever will.
void remove_stale_staging(const fs::path& parent, const std::string& name) {
  const std::string prefix = "." + name + ".partial-";
  std::error_code ec;
  for (fs::directory_iterator it(parent, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string entry = it->path().filename().string();
    if (entry.rfind(prefix, 0) != 0) continue;
    std::string pid_text = entry.substr(prefix.size());
    if (pid_text.size() > 4 && pid_text.compare(pid_text.size() - 4, 4, ".old") == 0) {
      pid_text.resize(pid_text.size() - 4);
    }
    if (pid_text.empty() ||
        pid_text.find_first_not_of("0123456789") != std::string::npos || pid_text.size() > 9) {
      continue;
    }
    const pid_t pid = pid_t(std::stol(pid_text));
    if (pid == ::getpid()) continue;
    if (::kill(pid, 0) == 0 || errno != ESRCH) continue;  // alive, or not ours to judge
    std::error_code rm;
    fs::remove_all(it->path(), rm);
  }
}

}  // namespace

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
    remove_stale_staging(parent, fp.filename().string());
    staging_ = (parent / ("." + fp.filename().string() + ".partial-" + std::to_string(::getpid())))
                   .string();
  }
  fs::create_directories(parent, ec);
  if (ec) throw Error(parent.string() + ": cannot create folder (" + ec.message() + ")");
  if (on_failure_ == OnFailure::kRemove) fs::remove_all(staging_, ec);
  fs::create_directory(staging_, ec);
  if (ec) throw Error(staging_ + ": cannot create folder (" + ec.message() + ")");
  if (on_failure_ == OnFailure::kRemove) register_partial_output(staging_);
}

StagedDirectory::~StagedDirectory() {
  if (!committed_ && on_failure_ == OnFailure::kRemove) {
    std::error_code ec;
    fs::remove_all(staging_, ec);
  }
  unregister_partial_output(staging_);
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
