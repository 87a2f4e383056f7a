// Atomic output files and staged output folders.
#include "foundation/output_files.hpp"

#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <filesystem>
#include <system_error>

#include "foundation/error.hpp"

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
    : path_(std::move(path)), temporary_(temporary_sibling(path_)) {}

PendingFile::~PendingFile() {
  if (!committed_) remove_quietly(temporary_);
}

void PendingFile::commit() {
  if (committed_) return;
  commit_file(temporary_, path_);
  committed_ = true;
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
    staging_ = (parent / ("." + fp.filename().string() + ".partial-" + std::to_string(::getpid())))
                   .string();
  }
  fs::create_directories(parent, ec);
  if (ec) throw Error(parent.string() + ": cannot create folder (" + ec.message() + ")");
  if (on_failure_ == OnFailure::kRemove) fs::remove_all(staging_, ec);
  fs::create_directory(staging_, ec);
  if (ec) throw Error(staging_ + ": cannot create folder (" + ec.message() + ")");
}

StagedDirectory::~StagedDirectory() {
  if (!committed_ && on_failure_ == OnFailure::kRemove) {
    std::error_code ec;
    fs::remove_all(staging_, ec);
  }
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
  const std::string old = staging_ + ".old";
  const bool had_old = fs::exists(final_, ec);
  if (had_old) {
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
  if (had_old) fs::remove_all(old, ec);
}

}  // namespace crepuscular
