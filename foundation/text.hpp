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

// Throws Error naming `path` when brackets ([ and {, outside quoted strings) nest deeper than
// `max_depth`. Parsers that recurse (OpenCV's YAML reader) overflow the stack on 100 000 levels;
// no file of ours nests deeper than a handful.
void check_nesting_depth(const std::string& path, const std::string& text, int max_depth = 64);

// The whole file as text, or "" when it cannot be read (the caller's parser says why).
std::string read_text_or_empty(const std::string& path);

}  // namespace crepuscular
