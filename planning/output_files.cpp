// Atomic output files and staged output folders.
#include "planning/output_files.hpp"

#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <system_error>

#include "kernels/error.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {

namespace {
std::atomic<int> g_counter{0};
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
    fs::remove(temporary, ec);
    throw Error(path + ": cannot write file (" + ec.message() + ")");
  }
}

void write_text_file(const std::string& path, const std::string& text) {
  const std::string tmp = temporary_sibling(path);
  {
    std::ofstream out(tmp, std::ios::binary);
    if (!out) throw Error(path + ": cannot open for writing");
    out << text;
    out.flush();
    if (!out) {
      out.close();
      std::error_code ec;
      fs::remove(tmp, ec);
      throw Error(path + ": write failed (disk full?)");
    }
  }
  commit_file(tmp, path);
}

StagedDirectory::StagedDirectory(std::string final_path) : final_(std::move(final_path)) {
  while (final_.size() > 1 && final_.back() == '/') final_.pop_back();
  fs::path fp(final_);
  const fs::path parent = fp.has_parent_path() ? fp.parent_path() : fs::path(".");
  std::error_code ec;
  if (fs::exists(fp, ec) && !fs::is_directory(fp, ec)) {
    throw Error(final_ + ": exists and is not a folder");
  }
  fs::create_directories(parent, ec);
  if (ec) throw Error(parent.string() + ": cannot create folder (" + ec.message() + ")");
  staging_ = (parent / ("." + fp.filename().string() + ".partial-" + std::to_string(::getpid())))
                 .string();
  fs::remove_all(staging_, ec);
  fs::create_directory(staging_, ec);
  if (ec) throw Error(staging_ + ": cannot create folder (" + ec.message() + ")");
}

StagedDirectory::~StagedDirectory() {
  if (!committed_) {
    std::error_code ec;
    fs::remove_all(staging_, ec);
  }
}

void StagedDirectory::commit() {
  std::error_code ec;
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

}  // namespace crepuscular::planning
