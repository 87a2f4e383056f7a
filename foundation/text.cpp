// Timestamps and integer ranges as text.
#include "foundation/text.hpp"

#include <ctime>

namespace crepuscular {

std::string utc_now_iso8601() {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&now, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

std::string format_ranges(const std::vector<int>& sorted_values) {
  std::string out;
  size_t i = 0;
  while (i < sorted_values.size()) {
    size_t j = i;
    while (j + 1 < sorted_values.size() && sorted_values[j + 1] == sorted_values[j] + 1) ++j;
    if (!out.empty()) out += ", ";
    out += std::to_string(sorted_values[i]);
    if (j > i) out += "-" + std::to_string(sorted_values[j]);
    i = j + 1;
  }
  return out;
}

}  // namespace crepuscular
