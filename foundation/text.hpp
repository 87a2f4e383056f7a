// Text every module writes the same way: timestamps and lists of integers. Other formatting goes
// through fmt directly (fmt::format, fmt::format_to), which foundation links publicly.
#pragma once

#include <string>
#include <vector>

namespace crepuscular {

// The current UTC time as ISO 8601, e.g. "2026-11-23T10:47:36Z".
std::string utc_now_iso8601();

// Sorted unique integers as ranges: "1-12, 15, 20-22"; "" when there are none.
std::string format_ranges(const std::vector<int>& sorted_values);

}  // namespace crepuscular
