// Poses CSV (`crepuscular track --out`): one row per frame and board,
// `frame,timestamp_ns,board,state,tx,ty,tz,qw,qx,qy,qz,rms_px` with T_cam_board in mm and a unit
// quaternion; state `tracked` or `lost`. A lost row leaves the pose fields empty, so that no
// reader can take a lost board's old pose for a current one. Tracked rows are formatted exactly as
// recordings::format_pose_row writes ground_truth.csv.
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <cstdio>
#include <string>
#include <vector>

#include "foundation/output_files.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::tracking {

struct PoseRecord {
  int64_t frame = 0;
  int64_t timestamp_ns = 0;
  std::string board;
  bool tracked = false;
  Eigen::Isometry3d T_cam_board = Eigen::Isometry3d::Identity();  // when tracked
  double rms_px = 0;                                               // when tracked
};

// The CSV line of one board's status in one frame (no newline).
std::string format_pose_record(const PoseRecord& record);
PoseRecord to_record(const TrackResult& result, const BoardStatus& status);

// Writes a poses CSV under a temporary name beside `path`; finish() renames it to `path`. A writer
// destroyed without finish() (a failed run) removes its temporary file.
class PosesCsvWriter {
 public:
  explicit PosesCsvWriter(const std::string& path);

  void write(const PoseRecord& record);
  void write(const TrackResult& result);  // one row per board
  void finish();
  const std::string& path() const { return output_.path(); }

 private:
  PendingTextFile output_;
};

// Reads a poses CSV (tracked and lost rows; ground_truth.csv as well). Throws Error naming the file
// and line for a wrong header or a malformed row.
std::vector<PoseRecord> read_poses_csv(const std::string& path);

}  // namespace crepuscular::tracking
