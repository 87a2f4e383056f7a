// Tests of foundation/json_fields: typed getters accept what they promise, and every error names
// the source and the field's full path.
#include "foundation/json_fields.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular {
namespace {

using test::expect_error_containing;

using nlohmann::json;

const json kDoc = json::parse(R"({
  "name": "patient", "count": 3, "scale": 2.5, "flag": true,
  "levels": [{"level": 0, "name": "none"}, {"level": "1"}],
  "origin": [1, 2, 3]
})");

// A coefficient of 1e400 gave the library's exception text; now the file and a plain reason.
TEST(JsonFields, ParseErrorsNameTheSourceWithoutTheLibrarysTag) {
  try {
    parse_json_text("{\"blocking_per_mm\": 1e400}", "table.json");
    FAIL() << "1e400 accepted";
  } catch (const Error& e) {
    const std::string message = e.what();
    EXPECT_EQ(message.rfind("table.json: not valid JSON (number overflow parsing '1e400'", 0), 0u)
        << message;
    EXPECT_EQ(message.find("json.exception"), std::string::npos) << message;
  }
  expect_error_containing([] { parse_json_text("{\"a\": [1, 2", "t.json"); },
                          {"t.json: not valid JSON (parse error at line 1"});
}

TEST(JsonFields, PathsJoinKeysAndIndices) {
  const JsonPath root("t.json");
  EXPECT_EQ(root.describe(), "t.json");
  const JsonPath p = root.key("levels").index(1).key("level");
  EXPECT_EQ(p.field(), "levels[1].level");
  EXPECT_EQ(p.describe(), "t.json: field 'levels[1].level'");
}

TEST(JsonFields, TypedGettersReturnTheValues) {
  const JsonPath at("t.json");
  EXPECT_EQ(required_string(kDoc, "name", at), "patient");
  EXPECT_EQ(required_integer(kDoc, "count", at, 0, 10), 3);
  EXPECT_DOUBLE_EQ(required_number(kDoc, "scale", at), 2.5);
  EXPECT_DOUBLE_EQ(required_number(kDoc, "count", at), 3.0);  // an integer is a number
  EXPECT_TRUE(required_bool(kDoc, "flag", at));
  EXPECT_EQ(as_numbers(kDoc["origin"], at.key("origin"), 3, 3, "[x, y, z]"),
            (std::vector<double>{1, 2, 3}));
  EXPECT_DOUBLE_EQ(optional_number(kDoc, "absent", at, 7.0), 7.0);
  EXPECT_EQ(optional_string(kDoc, "absent", at, "x"), "x");
  EXPECT_EQ(optional_integer(kDoc, "count", at, 9), 3);
  EXPECT_FALSE(optional_bool(kDoc, "absent", at, false));
  EXPECT_EQ(unknown_fields(kDoc, {"name", "count", "scale", "flag", "levels"}, at),
            std::vector<std::string>{"origin"});
}

TEST(JsonFields, ErrorsNameTheFileTheFieldAndWhatWasExpected) {
  const JsonPath at("t.json");
  expect_error_containing([&] { required_field(kDoc, "missing", at); },
                          {"t.json", "'missing'", "is missing"});
  const JsonPath level = at.key("levels").index(1);
  expect_error_containing([&] { required_string(kDoc["levels"][1], "name", level); },
                          {"t.json", "levels[1].name", "missing"});
  expect_error_containing([&] { required_integer(kDoc["levels"][1], "level", level); },
                          {"t.json", "levels[1].level", "a string \"1\"", "expected an integer"});
  expect_error_containing([&] { required_integer(kDoc, "scale", at); },
                          {"t.json", "'scale'", "2.5", "integer"});
  expect_error_containing([&] { required_integer(kDoc, "count", at, 5, 10); },
                          {"t.json", "'count'", "is 3", "5 to 10"});
  expect_error_containing([&] { required_number(kDoc, "name", at); },
                          {"t.json", "'name'", "a string", "expected a number"});
  expect_error_containing([&] { optional_number(kDoc, "flag", at, 1.0); },
                          {"t.json", "'flag'", "a boolean", "number"});
  expect_error_containing(
      [&] { as_numbers(kDoc["origin"], at.key("origin"), 2, 2, "[x, y] in mm"); },
      {"t.json", "'origin'", "[1,2,3]", "expected [x, y] in mm"});
  expect_error_containing([&] { required_field(kDoc["origin"], "x", at.key("origin")); },
                          {"t.json", "'origin'", "an array", "object"});
}

TEST(JsonFields, NonFiniteAndHugeNumbersAreRefused) {
  const JsonPath at("code");
  json j;
  j["nan"] = std::numeric_limits<double>::quiet_NaN();
  j["big"] = std::numeric_limits<unsigned long long>::max();
  expect_error_containing([&] { required_number(j, "nan", at); }, {"code", "'nan'", "finite"});
  expect_error_containing([&] { required_integer(j, "big", at, 0, 65535); },
                          {"code", "'big'", "18446744073709551615", "0 to 65535"});
}

TEST(JsonFields, FilesNameThePathAndTheParsePosition) {
  const test::TemporaryFolder dir;
  const std::string bad = (dir / "bad.json").string();
  std::ofstream(bad) << "{\n  \"a\": 1,\n  \"b\": [,]\n}\n";
  expect_error_containing([&] { read_json_file(bad, "table"); },
                          {"bad.json", "not valid JSON", "line 3"});
  expect_error_containing([&] { read_json_file((dir / "absent.json").string(), "scene file"); },
                          {"absent.json", "cannot open scene file"});
  const std::string good = (dir / "good.json").string();
  std::ofstream(good) << R"({"a": 1})";
  EXPECT_EQ(read_json_file(good, "table").at("a"), 1);
}

// Every JSON reader (tables, boards, scenes, plan.json) goes through read_json_file: a file nested
// 100 000 deep is refused from its text, with its line, before a parser recurses into it.
TEST(JsonFields, DeeplyNestedJsonIsRefused) {
  const test::TemporaryFolder dir;
  const std::string deep = (dir / "deep.json").string();
  std::ofstream(deep) << "{\n\"a\": " << std::string(100000, '[') << std::string(100000, ']')
                      << "}\n";
  expect_error_containing([&] { read_json_file(deep, "table"); },
                          {"deep.json", "line 2", "nest deeper than 64"});
  const std::string ok = (dir / "ok.json").string();
  std::ofstream(ok) << "{\"s\": \"[[[[ \\\" {{{\", \"a\": [[[1]]]}";
  EXPECT_EQ(read_json_file(ok, "table").at("a")[0][0][0], 1);
}

}  // namespace
}  // namespace crepuscular
