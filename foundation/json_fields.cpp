// Typed JSON field access with messages that name the source and the field.
#include "foundation/json_fields.hpp"
#include "foundation/output_files.hpp"
#include "foundation/text.hpp"

#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "foundation/error.hpp"

namespace crepuscular {

using nlohmann::json;

namespace {

// "a string \"3\"", "an array [1,2]", "null": the type and (shortened) the value.
std::string found(const json& value) {
  if (value.is_null()) return "null";
  std::string text = value.dump();
  constexpr size_t kMax = 60;
  if (text.size() > kMax) text = text.substr(0, kMax - 3) + "...";
  return json_type_name(value) + " " + text;
}

[[noreturn]] void wrong_type(const json& value, const JsonPath& at, const std::string& expected) {
  at.fail("is " + found(value) + ", expected " + expected);
}

}  // namespace

JsonPath::JsonPath(std::string source, std::string field)
    : source_(std::move(source)), field_(std::move(field)) {}

JsonPath JsonPath::key(const std::string& key) const {
  return JsonPath(source_, field_.empty() ? key : field_ + "." + key);
}

JsonPath JsonPath::index(size_t i) const {
  return JsonPath(source_, field_ + "[" + std::to_string(i) + "]");
}

std::string JsonPath::describe() const {
  return field_.empty() ? source_ : source_ + ": field '" + field_ + "'";
}

void JsonPath::fail(const std::string& problem) const { throw Error(describe() + " " + problem); }

std::string json_type_name(const json& v) {
  if (v.is_null()) return "null";
  if (v.is_boolean()) return "a boolean";
  if (v.is_number_integer()) return "an integer";
  if (v.is_number()) return "a number";
  if (v.is_string()) return "a string";
  if (v.is_array()) return "an array";
  if (v.is_object()) return "an object";
  return "a " + std::string(v.type_name());
}

std::string as_string(const json& value, const JsonPath& at) {
  if (!value.is_string()) wrong_type(value, at, "a string");
  return value.get<std::string>();
}

double as_number(const json& value, const JsonPath& at) {
  if (!value.is_number()) wrong_type(value, at, "a number");
  const double v = value.get<double>();
  if (!std::isfinite(v)) at.fail("is not finite, expected a finite number");
  return v;
}

int64_t as_integer(const json& value, const JsonPath& at, int64_t lo, int64_t hi) {
  if (!value.is_number_integer()) wrong_type(value, at, "an integer");
  // Unsigned JSON integers above the signed range compare correctly as unsigned.
  const bool too_big =
      value.is_number_unsigned() && value.get<unsigned long long>() > (unsigned long long)hi;
  const int64_t v = too_big ? hi : value.get<int64_t>();
  if (too_big || v < lo || v > hi) {
    at.fail("is " + value.dump() + ", expected " + std::to_string(lo) + " to " +
            std::to_string(hi));
  }
  return v;
}

bool as_bool(const json& value, const JsonPath& at) {
  if (!value.is_boolean()) wrong_type(value, at, "true or false");
  return value.get<bool>();
}

const json& as_object(const json& value, const JsonPath& at) {
  if (!value.is_object()) wrong_type(value, at, "an object");
  return value;
}

const json& as_array(const json& value, const JsonPath& at) {
  if (!value.is_array()) wrong_type(value, at, "an array");
  return value;
}

std::vector<double> as_numbers(const json& value, const JsonPath& at, size_t min_size,
                               size_t max_size, const std::string& expected) {
  if (!value.is_array() || value.size() < min_size || value.size() > max_size) {
    wrong_type(value, at, expected);
  }
  std::vector<double> out;
  for (size_t i = 0; i < value.size(); ++i) {
    if (!value[i].is_number()) wrong_type(value, at, expected);
    out.push_back(as_number(value[i], at.index(i)));
  }
  return out;
}

bool has_field(const json& object, const std::string& key) {
  return object.is_object() && object.contains(key);
}

const json& required_field(const json& object, const std::string& key, const JsonPath& at) {
  if (!object.is_object()) wrong_type(object, at, "an object with a field '" + key + "'");
  const auto it = object.find(key);
  if (it == object.end()) at.key(key).fail("is missing");
  return *it;
}

std::string required_string(const json& object, const std::string& key, const JsonPath& at) {
  return as_string(required_field(object, key, at), at.key(key));
}

double required_number(const json& object, const std::string& key, const JsonPath& at) {
  return as_number(required_field(object, key, at), at.key(key));
}

int64_t required_integer(const json& object, const std::string& key, const JsonPath& at, int64_t lo,
                         int64_t hi) {
  return as_integer(required_field(object, key, at), at.key(key), lo, hi);
}

bool required_bool(const json& object, const std::string& key, const JsonPath& at) {
  return as_bool(required_field(object, key, at), at.key(key));
}

std::string optional_string(const json& object, const std::string& key, const JsonPath& at,
                            const std::string& fallback) {
  return has_field(object, key) ? as_string(object[key], at.key(key)) : fallback;
}

double optional_number(const json& object, const std::string& key, const JsonPath& at,
                       double fallback) {
  return has_field(object, key) ? as_number(object[key], at.key(key)) : fallback;
}

int64_t optional_integer(const json& object, const std::string& key, const JsonPath& at,
                         int64_t fallback, int64_t lo, int64_t hi) {
  return has_field(object, key) ? as_integer(object[key], at.key(key), lo, hi) : fallback;
}

bool optional_bool(const json& object, const std::string& key, const JsonPath& at, bool fallback) {
  return has_field(object, key) ? as_bool(object[key], at.key(key)) : fallback;
}

std::vector<std::string> unknown_fields(const json& object, const std::set<std::string>& known,
                                        const JsonPath& at) {
  std::vector<std::string> out;
  if (!object.is_object()) return out;
  for (auto it = object.begin(); it != object.end(); ++it) {
    if (known.count(it.key()) == 0) out.push_back(at.key(it.key()).field());
  }
  return out;
}

json parse_json_text(const std::string& text, const std::string& source) {
  try {
    return json::parse(text);
  } catch (const json::exception& e) {
    // e.what() names the position ("parse error at line 3, column 5: syntax error ...") after
    // the library's own tag ("[json.exception.parse_error.101] "), which says nothing to a user.
    std::string why = e.what();
    const size_t tag_end = why.rfind("] ", why.find(' ') == std::string::npos ? 0 : why.find(' '));
    if (!why.empty() && why.front() == '[' && tag_end != std::string::npos) why.erase(0, tag_end + 2);
    if (why.rfind("number overflow", 0) == 0) why += " (a number beyond +-1.8e308)";
    throw Error(source + ": not valid JSON (" + why + ")");
  }
}

json read_json_file(const std::string& path, const std::string& what) {
  errno = 0;
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    const int err = errno;
    throw Error(path + ": cannot open " + what + " (" +
                (err != 0 ? std::strerror(err) : "unreadable") + ")");
  }
  std::stringstream text;
  text << in.rdbuf();
  check_nesting_depth(path, text.str());
  return parse_json_text(text.str(), path);
}

void record_final_paths(nlohmann::json& doc) {
  if (doc.is_string()) {
    doc = final_path_of(doc.get<std::string>());
  } else if (doc.is_structured()) {
    for (auto& item : doc) record_final_paths(item);
  }
}

}  // namespace crepuscular
