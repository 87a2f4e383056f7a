// Timestamps and integer ranges as text.
#include "foundation/text.hpp"
#include "foundation/error.hpp"

#include <fstream>
#include <sstream>

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

void check_nesting_depth(const std::string& path, const std::string& text, int max_depth) {
  int depth = 0, line = 1;
  char quote = 0;
  for (size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (c == '\n') ++line;
    if (quote) {
      if (c == '\\' && quote == '"') {
        ++i;
      } else if (c == quote) {
        quote = 0;
      }
      continue;
    }
    if (c == '"' || c == '\'') {
      quote = c;
    } else if (c == '[' || c == '{') {
      if (++depth > max_depth) {
        throw Error(path + ": line " + std::to_string(line) + ": brackets nest deeper than " +
                    std::to_string(max_depth) + " levels; not a file this tool wrote or reads");
      }
    } else if ((c == ']' || c == '}') && depth > 0) {
      --depth;
    }
  }
}

std::string read_text_or_empty(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return {};
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace crepuscular
