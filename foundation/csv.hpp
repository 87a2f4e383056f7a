// CSV fields: splitting a line (quotes as RFC 4180 has them), quoting a field for writing, and
// whole-field numbers whose errors name the file, the line and the column.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

namespace crepuscular {

// The fields of one line, split at `separator`. A field in double quotes may hold separators
// and doubled quotes (""); carriage returns outside quotes are dropped. With `trim`, spaces and
// tabs around each field are removed. An empty line gives one empty field.
std::vector<std::string> split_csv_line(std::string_view line, char separator = ',',
                                        bool trim = false);

// A field as CSV writes it: in double quotes (inner quotes doubled) when it holds a comma, a
// quote or a newline; unchanged otherwise.
std::string quote_csv_field(std::string_view text);

// Whole-field numbers (strtoll / strtod): false when the field is empty, has text after the
// number, overflows, or (for doubles) is not finite.
bool parse_int64(std::string_view text, int64_t* value);
bool parse_double(std::string_view text, double* value);

// Where a field was read, for messages: "PATH: line N".
struct CsvLocation {
  std::string file;
  int64_t line = 0;  // 1-based
  std::string describe() const;
};

// The number in `field` (column `column`, e.g. "timestamp_ns"); throws Error
// "PATH: line N: COLUMN 'TEXT' is not an integer" (or "... not a number").
int64_t csv_int64(const std::string& field, const std::string& column, const CsvLocation& at);
double csv_double(const std::string& field, const std::string& column, const CsvLocation& at);

// Throws Error "PATH: header is 'FOUND', expected 'EXPECTED'" unless the two are the same.
void check_csv_header(const std::string& path, const std::string& found,
                      const std::string& expected);

}  // namespace crepuscular
