// Tests of foundation/csv: quoted fields, trimming, whole-field numbers, and errors that name the
// file, the line and the column.
#include "foundation/csv.hpp"

#include <gtest/gtest.h>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"

namespace crepuscular {
namespace {

using test::expect_error_containing;

using Fields = std::vector<std::string>;

TEST(Csv, SplitsAtSeparatorsOutsideQuotes) {
  EXPECT_EQ(split_csv_line("1,2,abc"), (Fields{"1", "2", "abc"}));
  EXPECT_EQ(split_csv_line("a,,b,"), (Fields{"a", "", "b", ""}));
  EXPECT_EQ(split_csv_line(""), Fields{""});
  EXPECT_EQ(split_csv_line("x,y\r"), (Fields{"x", "y"}));  // Windows line ends
  EXPECT_EQ(split_csv_line("\"a, first\",\"say \"\"hi\"\"\",3"),
            (Fields{"a, first", "say \"hi\"", "3"}));
  EXPECT_EQ(split_csv_line(" a ;\tb", ';', true), (Fields{"a", "b"}));
  EXPECT_EQ(split_csv_line(" a , b "), (Fields{" a ", " b "}));  // untrimmed by default
}

TEST(Csv, QuotingRoundTrips) {
  for (const std::string text : {"plain", "a, first", "say \"hi\"", ""}) {
    EXPECT_EQ(split_csv_line(quote_csv_field(text) + ",x"), (Fields{text, "x"})) << text;
  }
  EXPECT_EQ(quote_csv_field("plain"), "plain");
  EXPECT_EQ(quote_csv_field("a,b"), "\"a,b\"");
}

TEST(Csv, NumbersMustFillTheField) {
  int64_t i = 0;
  double d = 0;
  EXPECT_TRUE(parse_int64("-42", &i));
  EXPECT_EQ(i, -42);
  EXPECT_FALSE(parse_int64("", &i));
  EXPECT_FALSE(parse_int64("4x", &i));
  EXPECT_FALSE(parse_int64("1.5", &i));
  EXPECT_FALSE(parse_int64("99999999999999999999", &i));  // overflow
  EXPECT_TRUE(parse_double("1e-3", &d));
  EXPECT_DOUBLE_EQ(d, 1e-3);
  EXPECT_FALSE(parse_double("", &d));
  EXPECT_FALSE(parse_double("2 mm", &d));
  EXPECT_FALSE(parse_double("inf", &d));
  EXPECT_FALSE(parse_double("nan", &d));
}

TEST(Csv, ErrorsNameFileLineAndColumn) {
  const CsvLocation at{"poses.csv", 3};
  EXPECT_EQ(csv_int64("17", "frame", at), 17);
  EXPECT_DOUBLE_EQ(csv_double("0.25", "tz", at), 0.25);
  expect_error_containing([&] { csv_int64("x", "frame", at); },
                          {"poses.csv", "line 3", "frame", "'x'", "not an integer"});
  expect_error_containing([&] { csv_double("", "tz", at); },
                          {"poses.csv", "line 3", "tz", "not a number"});
  check_csv_header("f.csv", "a,b", "a,b");
  expect_error_containing([&] { check_csv_header("f.csv", "a,c", "a,b"); },
                          {"f.csv", "'a,c'", "expected 'a,b'"});
}

}  // namespace
}  // namespace crepuscular
