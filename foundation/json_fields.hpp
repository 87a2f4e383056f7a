// Typed fields of JSON documents read from files. Every error names the source (a file, or e.g.
// "preset 'phantom'") and the field's path in it:
//   t.json: field 'labels[2].value' is a string "3", expected an integer
//   plan.json: field 'parameters.gamma_mm' is missing
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <nlohmann/json_fwd.hpp>
#include <set>
#include <string>
#include <vector>

namespace crepuscular {

// Where a value sits: its document's source and its field path in it ("" at the root).
class JsonPath {
 public:
  explicit JsonPath(std::string source, std::string field = {});
  // The path of a member ("boards[0]" -> "boards[0].name") or of an element ("boards" ->
  // "boards[2]").
  JsonPath key(const std::string& key) const;
  JsonPath index(size_t i) const;

  const std::string& source() const { return source_; }
  const std::string& field() const { return field_; }
  // "SOURCE: field 'FIELD'", or "SOURCE" at the root: the start of a message.
  std::string describe() const;
  // Throws Error(describe() + " " + problem), e.g. fail("is empty, expected a board name").
  [[noreturn]] void fail(const std::string& problem) const;

 private:
  std::string source_;
  std::string field_;
};

// The type as a message says it: "a string", "an integer", "a number", "an array", "null", ...
std::string json_type_name(const nlohmann::json& value);

constexpr int64_t kJsonIntMin = std::numeric_limits<int64_t>::min();
constexpr int64_t kJsonIntMax = std::numeric_limits<int64_t>::max();

// A value checked for its type; `at` is the value's own path. Numbers are finite; integers are
// JSON integers (2.0 and "2" are refused, so typos do not silently change meaning) in [lo, hi].
std::string as_string(const nlohmann::json& value, const JsonPath& at);
double as_number(const nlohmann::json& value, const JsonPath& at);
int64_t as_integer(const nlohmann::json& value, const JsonPath& at, int64_t lo = kJsonIntMin,
                   int64_t hi = kJsonIntMax);
bool as_bool(const nlohmann::json& value, const JsonPath& at);
const nlohmann::json& as_object(const nlohmann::json& value, const JsonPath& at);
const nlohmann::json& as_array(const nlohmann::json& value, const JsonPath& at);
// An array of min_size to max_size finite numbers; `expected` says what it stands for in
// messages about the array ("... is [1,\"a\"], expected [x, y, z] in mm").
std::vector<double> as_numbers(const nlohmann::json& value, const JsonPath& at, size_t min_size,
                               size_t max_size, const std::string& expected);

// Fields of an object; `at` is the object's path. Required fields throw "... is missing" when
// absent; optional ones give the fallback when absent and are checked when present.
bool has_field(const nlohmann::json& object, const std::string& key);
const nlohmann::json& required_field(const nlohmann::json& object, const std::string& key,
                                     const JsonPath& at);
std::string required_string(const nlohmann::json& object, const std::string& key,
                            const JsonPath& at);
double required_number(const nlohmann::json& object, const std::string& key, const JsonPath& at);
int64_t required_integer(const nlohmann::json& object, const std::string& key, const JsonPath& at,
                         int64_t lo = kJsonIntMin, int64_t hi = kJsonIntMax);
bool required_bool(const nlohmann::json& object, const std::string& key, const JsonPath& at);
std::string optional_string(const nlohmann::json& object, const std::string& key,
                            const JsonPath& at, const std::string& fallback);
double optional_number(const nlohmann::json& object, const std::string& key, const JsonPath& at,
                       double fallback);
int64_t optional_integer(const nlohmann::json& object, const std::string& key, const JsonPath& at,
                         int64_t fallback, int64_t lo = kJsonIntMin, int64_t hi = kJsonIntMax);
bool optional_bool(const nlohmann::json& object, const std::string& key, const JsonPath& at,
                   bool fallback);

// The field paths of members not in `known` (for a warning: typos are easy to miss).
std::vector<std::string> unknown_fields(const nlohmann::json& object,
                                        const std::set<std::string>& known, const JsonPath& at);

// A document: Error "SOURCE: not valid JSON (... at line L, column C ...)" when it does not
// parse; read_json_file also "PATH: cannot open WHAT (reason)" when the file cannot be read.
nlohmann::json parse_json_text(const std::string& text, const std::string& source);
nlohmann::json read_json_file(const std::string& path, const std::string& what);

// Every string of `doc` that names a path inside a folder this process still stages, replaced by
// the path it will have once committed (output_files.hpp final_path_of): what a file records is
// where its reader will find it. Other strings are left as they are.
void record_final_paths(nlohmann::json& doc);

}  // namespace crepuscular
