// Poses CSV writer and reader.
#include "tracking/poses_csv.hpp"

#include <unistd.h>

#include <cerrno>
#include <cinttypes>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "kernels/error.hpp"
#include "recordings/recording.hpp"

namespace crepuscular::tracking {

PoseRecord to_record(const TrackResult& result, const BoardStatus& status) {
  PoseRecord r;
  r.frame = result.frame;
  r.timestamp_ns = result.timestamp_ns;
  r.board = status.board;
  r.tracked = status.tracked;
  if (status.tracked) {
    r.T_cam_board = status.T_cam_board;
    r.rms_px = status.rms_px;
  }
  return r;
}

std::string format_pose_record(const PoseRecord& rec) {
  if (!rec.tracked) {
    char buf[256];
    std::snprintf(buf, sizeof buf, "%" PRId64 ",%" PRId64 ",%s,lost,,,,,,,,", rec.frame,
                  rec.timestamp_ns, rec.board.c_str());
    return buf;
  }
  recordings::PoseRow row;
  row.frame = rec.frame;
  row.timestamp_ns = rec.timestamp_ns;
  row.board = rec.board;
  row.state = "tracked";
  const Eigen::Vector3d t = rec.T_cam_board.translation();
  Eigen::Quaterniond q(rec.T_cam_board.linear());
  q.normalize();
  if (q.w() < 0) q.coeffs() *= -1.0;
  for (int k = 0; k < 3; ++k) row.t[k] = t[k];
  row.q[0] = q.w();
  row.q[1] = q.x();
  row.q[2] = q.y();
  row.q[3] = q.z();
  row.rms_px = rec.rms_px;
  return recordings::format_pose_row(row);
}

PosesCsvWriter::PosesCsvWriter(const std::string& path) : path_(path) {
  const std::filesystem::path p(path);
  std::ostringstream name;
  name << ".tmp-" << ::getpid() << "-" << p.filename().string();
  temporary_ = (p.parent_path() / name.str()).string();
  file_ = std::fopen(temporary_.c_str(), "wb");
  if (!file_) {
    throw Error(path + ": cannot create the poses CSV (" + std::strerror(errno) + ")");
  }
  std::fprintf(file_, "%s\n", recordings::kPoseCsvHeader);
}

PosesCsvWriter::~PosesCsvWriter() {
  if (file_) {
    std::fclose(file_);
    std::error_code ec;
    std::filesystem::remove(temporary_, ec);
  }
}

void PosesCsvWriter::write(const PoseRecord& record) {
  if (!file_) throw Error(path_ + ": poses CSV already finished");
  if (std::fprintf(file_, "%s\n", format_pose_record(record).c_str()) < 0) {
    throw Error(path_ + ": cannot write the poses CSV");
  }
}

void PosesCsvWriter::write(const TrackResult& result) {
  for (const BoardStatus& s : result.boards) write(to_record(result, s));
}

void PosesCsvWriter::finish() {
  if (!file_) return;
  const bool ok = std::fflush(file_) == 0 && std::fclose(file_) == 0;
  file_ = nullptr;
  std::error_code ec;
  if (!ok) {
    std::filesystem::remove(temporary_, ec);
    throw Error(path_ + ": cannot write the poses CSV");
  }
  std::filesystem::rename(temporary_, path_, ec);
  if (ec) {
    std::filesystem::remove(temporary_, ec);
    throw Error(path_ + ": cannot rename the finished poses CSV into place");
  }
}

std::vector<PoseRecord> read_poses_csv(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path + ": cannot open the poses CSV");
  std::string line;
  if (!std::getline(in, line)) throw Error(path + ": empty file, expected a poses CSV header");
  if (!line.empty() && line.back() == '\r') line.pop_back();
  if (line != recordings::kPoseCsvHeader) {
    throw Error(path + ": header is '" + line + "', expected '" + recordings::kPoseCsvHeader + "'");
  }
  std::vector<PoseRecord> out;
  int64_t number = 1;
  while (std::getline(in, line)) {
    ++number;
    if (line.empty() || line == "\r") continue;
    const std::vector<std::string> f = recordings::split_fields(line, ',');
    const std::string where = path + ": line " + std::to_string(number) + ": ";
    if (f.size() != 12) {
      throw Error(where + std::to_string(f.size()) + " fields, expected 12");
    }
    PoseRecord r;
    if (!recordings::parse_int64(f[0], &r.frame)) throw Error(where + "frame '" + f[0] + "' is not an integer");
    if (!recordings::parse_int64(f[1], &r.timestamp_ns)) {
      throw Error(where + "timestamp_ns '" + f[1] + "' is not an integer");
    }
    r.board = f[2];
    if (f[3] == "lost") {
      r.tracked = false;
    } else if (f[3] == "tracked") {
      r.tracked = true;
      double v[8];
      static const char* names[8] = {"tx", "ty", "tz", "qw", "qx", "qy", "qz", "rms_px"};
      for (int k = 0; k < 8; ++k) {
        if (!recordings::parse_double(f[size_t(4 + k)], &v[k])) {
          throw Error(where + names[k] + " '" + f[size_t(4 + k)] + "' is not a number");
        }
      }
      Eigen::Quaterniond q(v[3], v[4], v[5], v[6]);
      if (std::abs(q.norm() - 1.0) > 1e-6) {
        throw Error(where + "quaternion norm " + std::to_string(q.norm()) + ", expected 1");
      }
      r.T_cam_board.linear() = q.normalized().toRotationMatrix();
      r.T_cam_board.translation() = Eigen::Vector3d(v[0], v[1], v[2]);
      r.rms_px = v[7];
    } else {
      throw Error(where + "state '" + f[3] + "', expected tracked or lost");
    }
    out.push_back(r);
  }
  return out;
}

}  // namespace crepuscular::tracking
