// CSV line splitting, field quoting and number parsing.
#include "foundation/csv.hpp"

#include <cerrno>
#include <cmath>
#include <cstdlib>

#include "foundation/error.hpp"

namespace crepuscular {

namespace {

std::string trimmed(const std::string& s) {
  const auto b = s.find_first_not_of(" \t");
  const auto e = s.find_last_not_of(" \t");
  return b == std::string::npos ? std::string() : s.substr(b, e - b + 1);
}

}  // namespace

std::vector<std::string> split_csv_line(std::string_view line, char separator, bool trim) {
  std::vector<std::string> fields(1);
  bool quoted = false;
  for (size_t i = 0; i < line.size(); ++i) {
    const char c = line[i];
    if (quoted) {
      if (c == '"' && i + 1 < line.size() && line[i + 1] == '"') {
        fields.back() += '"';
        ++i;
      } else if (c == '"') {
        quoted = false;
      } else {
        fields.back() += c;
      }
    } else if (c == '"') {
      quoted = true;
    } else if (c == separator) {
      fields.emplace_back();
    } else if (c != '\r') {
      fields.back() += c;
    }
  }
  if (trim) {
    for (auto& f : fields) f = trimmed(f);
  }
  return fields;
}

std::string quote_csv_field(std::string_view text) {
  if (text.find_first_of(",\"\n") == std::string_view::npos) return std::string(text);
  std::string q = "\"";
  for (char c : text) {
    if (c == '"') q += '"';
    q += c;
  }
  return q + "\"";
}

bool parse_int64(std::string_view text, int64_t* value) {
  if (text.empty()) return false;
  const std::string s(text);
  char* end = nullptr;
  errno = 0;
  const long long x = std::strtoll(s.c_str(), &end, 10);
  if (errno != 0 || end != s.c_str() + s.size()) return false;
  *value = int64_t(x);
  return true;
}

bool parse_double(std::string_view text, double* value) {
  if (text.empty()) return false;
  const std::string s(text);
  char* end = nullptr;
  const double x = std::strtod(s.c_str(), &end);
  if (end != s.c_str() + s.size() || !std::isfinite(x)) return false;
  *value = x;
  return true;
}

std::string CsvLocation::describe() const { return file + ": line " + std::to_string(line); }

int64_t csv_int64(const std::string& field, const std::string& column, const CsvLocation& at) {
  int64_t v = 0;
  if (!parse_int64(field, &v)) {
    throw Error(at.describe() + ": " + column + " '" + field + "' is not an integer");
  }
  return v;
}

double csv_double(const std::string& field, const std::string& column, const CsvLocation& at) {
  double v = 0;
  if (!parse_double(field, &v)) {
    throw Error(at.describe() + ": " + column + " '" + field + "' is not a number");
  }
  return v;
}

void check_csv_header(const std::string& path, const std::string& found,
                      const std::string& expected) {
  if (found != expected) {
    throw Error(path + ": header is '" + found + "', expected '" + expected + "'");
  }
}

}  // namespace crepuscular
