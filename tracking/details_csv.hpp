// Tracking details CSV (`crepuscular track --details`): what the detector found in every frame and
// why a board was or was not measured. One row per frame, board and tag of the board seen (one row
// without a tag when none was), and one row per tag that belongs to no board (board empty):
//   frame,timestamp_ns,board,state,tags,rms_px,reason,family,tag_id,decision_margin,hamming,
//   x0,y0,x1,y1,x2,y2,x3,y3
// state: measured (this frame's tags gave a pose), held (the last pose, still young enough) or
// lost; reason: why the board was not measured (empty when it was; "ambiguous: ..." when one tag
// fitted two poses about equally well). Corners in pixels (OpenCV's convention), in the order of
// tracking::Detection.
#pragma once

#include <string>
#include <vector>

#include "foundation/output_files.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::tracking {

inline constexpr const char* kDetailsCsvHeader =
    "frame,timestamp_ns,board,state,tags,rms_px,reason,family,tag_id,decision_margin,hamming,"
    "x0,y0,x1,y1,x2,y2,x3,y3";

// The rows of one frame (each ending in a newline), for `boards` in the tracker's order.
std::string format_details_rows(const TrackResult& result, const std::vector<Board>& boards);

// Writes a details CSV under a temporary name beside `path`; finish() renames it to `path`. A
// writer destroyed without finish() (a failed run) removes its temporary file.
class DetailsCsvWriter {
 public:
  explicit DetailsCsvWriter(const std::string& path);

  void write(const TrackResult& result, const std::vector<Board>& boards);
  void finish();
  const std::string& path() const { return output_.path(); }

 private:
  PendingTextFile output_;
};

}  // namespace crepuscular::tracking
