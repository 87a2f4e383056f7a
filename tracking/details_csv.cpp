// Tracking details CSV (see details_csv.hpp).
#include "tracking/details_csv.hpp"

#include <fmt/format.h>

#include "foundation/csv.hpp"
#include "foundation/error.hpp"

namespace crepuscular::tracking {

namespace {

std::string tag_fields(const Detection& d) {
  std::string out = fmt::format("{},{},{:.2f},{}", quote_csv_field(d.family), d.id, d.decision_margin,
                                d.hamming);
  for (const Eigen::Vector2d& c : d.corners) out += fmt::format(",{:.4f},{:.4f}", c.x(), c.y());
  return out;
}

constexpr const char* kNoTag = ",,,,,,,,,,,,";  // the 12 fields family .. y3, empty

}  // namespace

std::string format_details_rows(const TrackResult& r, const std::vector<Board>& boards) {
  std::string out;
  std::vector<bool> on_a_board(r.detections.size(), false);
  for (size_t b = 0; b < r.boards.size() && b < boards.size(); ++b) {
    const BoardStatus& s = r.boards[b];
    const char* state = s.measured ? "measured" : s.tracked ? "held" : "lost";
    std::string reason = s.measured ? "" : s.problem;
    if (s.measured && s.ambiguous) {
      reason = "ambiguous: two poses explain the tags about equally well (the one nearer the "
               "previous pose was kept)";
    }
    const std::string head =
        fmt::format("{},{},{},{},{},{},{}", r.frame, r.timestamp_ns, quote_csv_field(s.board), state,
                    s.tags, s.measured ? fmt::format("{:.4f}", s.rms_px) : "", quote_csv_field(reason));
    bool any = false;
    for (size_t i = 0; i < r.detections.size(); ++i) {
      const Detection& d = r.detections[i];
      if (!belongs_to(boards[b], d)) continue;
      on_a_board[i] = true;
      out += head + "," + tag_fields(d) + "\n";
      any = true;
    }
    if (!any) out += head + kNoTag + "\n";
  }
  for (size_t i = 0; i < r.detections.size(); ++i) {
    if (on_a_board[i]) continue;
    out += fmt::format("{},{},,,,,not on any board,{}\n", r.frame, r.timestamp_ns,
                       tag_fields(r.detections[i]));
  }
  return out;
}

DetailsCsvWriter::DetailsCsvWriter(const std::string& path)
    : output_(path, "details CSV", kDetailsCsvHeader) {}

void DetailsCsvWriter::write(const TrackResult& result, const std::vector<Board>& boards) {
  output_.write(format_details_rows(result, boards));
}

void DetailsCsvWriter::finish() { output_.commit(); }

}  // namespace crepuscular::tracking
