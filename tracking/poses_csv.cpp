// Poses CSV writer and reader.
#include "tracking/poses_csv.hpp"

#include <fmt/format.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>

#include "foundation/csv.hpp"
#include "foundation/error.hpp"
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
    return fmt::format("{},{},{},lost,,,,,,,,", rec.frame, rec.timestamp_ns, rec.board);
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

PosesCsvWriter::PosesCsvWriter(const std::string& path)
    : output_(path, "poses CSV", recordings::kPoseCsvHeader) {}

void PosesCsvWriter::write(const PoseRecord& record) {
  output_.write(format_pose_record(record) + "\n");
}

void PosesCsvWriter::write(const TrackResult& result) {
  for (const BoardStatus& s : result.boards) write(to_record(result, s));
}

void PosesCsvWriter::finish() { output_.commit(); }

std::vector<PoseRecord> read_poses_csv(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path + ": cannot open the poses CSV");
  std::string line;
  if (!std::getline(in, line)) throw Error(path + ": empty file, expected a poses CSV header");
  if (!line.empty() && line.back() == '\r') line.pop_back();
  check_csv_header(path, line, recordings::kPoseCsvHeader);
  std::vector<PoseRecord> out;
  CsvLocation at{path, 1};
  while (std::getline(in, line)) {
    ++at.line;
    if (line.empty() || line == "\r") continue;
    const recordings::PoseRow row = recordings::parse_pose_row(split_csv_line(line), at);
    PoseRecord r;
    r.frame = row.frame;
    r.timestamp_ns = row.timestamp_ns;
    r.board = row.board;
    r.tracked = row.state == "tracked";
    if (r.tracked) {
      Eigen::Quaterniond q(row.q[0], row.q[1], row.q[2], row.q[3]);
      if (std::abs(q.norm() - 1.0) > 1e-6) {
        throw Error(at.describe() + ": quaternion norm " + std::to_string(q.norm()) +
                    ", expected 1");
      }
      r.T_cam_board.linear() = q.normalized().toRotationMatrix();
      r.T_cam_board.translation() = Eigen::Vector3d(row.t[0], row.t[1], row.t[2]);
      r.rms_px = row.rms_px;
    }
    out.push_back(r);
  }
  return out;
}

}  // namespace crepuscular::tracking
