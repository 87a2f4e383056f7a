// 3D Slicer line markups: LPS and RAS files of the same physical line give the same points;
// files without a coordinate system are LPS (as Slicer reads them); malformed files are refused.
#include "planning/trajectories/markups.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

// A line as Slicer 5 saves it in RAS: entry at R 30 A 40 S 12, target at L 5.5 P 7 I 3.
const char* kRasFile = R"({
 "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/markups-schema-v1.0.3.json#",
 "markups": [{"type": "Line", "coordinateSystem": "RAS", "coordinateUnits": "mm",
   "locked": false, "labelFormat": "%N-%d",
   "controlPoints": [
     {"id": "1", "label": "L-1", "position": [30.0, 40.0, 12.0], "positionStatus": "defined"},
     {"id": "2", "label": "L-2", "position": [-5.5, -7.0, -3.0], "positionStatus": "defined"}],
   "measurements": [{"name": "length", "enabled": true}]}]})";

// The same physical line in LPS: x and y negated.
const char* kLpsFile = R"({"markups": [{"type": "Line", "coordinateSystem": "LPS",
   "controlPoints": [{"label": "entry", "position": [-30.0, -40.0, 12.0]},
                     {"label": "target", "position": [5.5, 7.0, -3.0]}]}]})";

// No "coordinateSystem": Slicer's reader (vtkMRMLMarkupsJsonStorageNode) takes LPS.
const char* kNoSystemFile = R"({"markups": [{"type": "Line",
   "controlPoints": [{"position": [-30.0, -40.0, 12.0]}, {"position": [5.5, 7.0, -3.0]}]}]})";

void expect_same(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  EXPECT_NEAR((a - b).norm(), 0.0, 1e-12) << a.transpose() << " vs " << b.transpose();
}

TEST(MarkupsTest, RasAndLpsFilesOfOneLineGiveTheSameLpsPoints) {
  const LineMarkup ras = parse_line_markup(nlohmann::json::parse(kRasFile), "ras.mrk.json");
  const LineMarkup lps = parse_line_markup(nlohmann::json::parse(kLpsFile), "lps.mrk.json");
  EXPECT_EQ(ras.file_coordinate_system, "RAS");
  EXPECT_EQ(lps.file_coordinate_system, "LPS");
  // R 30 = L -30, A 40 = P -40; S unchanged.
  expect_same(ras.first, Eigen::Vector3d(-30, -40, 12));
  expect_same(ras.second, Eigen::Vector3d(5.5, 7, -3));
  expect_same(ras.first, lps.first);
  expect_same(ras.second, lps.second);
  EXPECT_EQ(ras.first_label, "L-1");
  EXPECT_EQ(lps.second_label, "target");
}

TEST(MarkupsTest, FileWithoutCoordinateSystemIsLps) {
  const LineMarkup m = parse_line_markup(nlohmann::json::parse(kNoSystemFile), "old.mrk.json");
  EXPECT_EQ(m.file_coordinate_system, "LPS");
  expect_same(m.first, Eigen::Vector3d(-30, -40, 12));
  expect_same(m.second, Eigen::Vector3d(5.5, 7, -3));
}

TEST(MarkupsTest, WrittenRasFileHoldsNegatedXYAndReadsBackToTheSamePoints) {
  LineMarkup line;
  line.name = "needle";
  line.first = Eigen::Vector3d(-12.25, 33.5, 101.0);
  line.second = Eigen::Vector3d(4.0, -8.75, 90.5);
  const nlohmann::json ras = line_markup_json(line, "RAS");
  const auto& p0 = ras["markups"][0]["controlPoints"][0]["position"];
  EXPECT_DOUBLE_EQ(p0[0].get<double>(), 12.25);
  EXPECT_DOUBLE_EQ(p0[1].get<double>(), -33.5);
  EXPECT_DOUBLE_EQ(p0[2].get<double>(), 101.0);
  const test::TemporaryFolder dir;
  for (const char* system : {"LPS", "RAS"}) {
    const std::string path = (dir / (std::string(system) + ".mrk.json")).string();
    write_line_markup(path, line, system);
    const LineMarkup back = read_line_markup(path);
    EXPECT_EQ(back.file_coordinate_system, system);
    EXPECT_EQ(back.name, "needle");
    expect_same(back.first, line.first);
    expect_same(back.second, line.second);
  }
}

TEST(MarkupsTest, MalformedFilesAreRefusedWithTheFieldNamed) {
  const auto fails_with = [](const std::string& text, const std::string& expected) {
    SCOPED_TRACE(text);
    test::expect_error_containing(
        [&] { parse_line_markup(nlohmann::json::parse(text), "bad.mrk.json"); },
        {"bad.mrk.json", expected});
  };
  fails_with(R"({"markups": [{"type": "Fiducial", "controlPoints": []}]})", "Line");
  fails_with(R"({"markups": [{"type": "Line", "controlPoints": [{"position": [1, 2, 3]}]}]})",
             "controlPoints");
  fails_with(R"({"markups": [{"type": "Line", "coordinateSystem": "IJK", "controlPoints": []}]})",
             "coordinateSystem");
  fails_with(R"({"markups": [{"type": "Line", "coordinateUnits": "um", "controlPoints": []}]})",
             "coordinateUnits");
  fails_with(R"({"markups": [{"type": "Line", "controlPoints": [
      {"position": [1, 2, 3]}, {"position": [1, 2]}]}]})",
             "position");
  fails_with(R"({"markups": [{"type": "Line", "controlPoints": [
      {"position": [1, 2, 3]}, {"position": [4, 5, 6], "positionStatus": "undefined"}]}]})",
             "positionStatus");
  fails_with(R"({"points": []})", "markups");
  EXPECT_THROW(read_line_markup("/nonexistent/line.mrk.json"), Error);
}

}  // namespace
}  // namespace crepuscular::planning
