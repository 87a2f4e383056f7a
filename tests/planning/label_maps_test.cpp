// Tests of several label maps combined (planning/preprocessing/label_maps.hpp), the scanned volume
// they span (planning/imaging/scan_coverage.hpp), the TotalSegmentator presets, and the real
// TotalSegmentator label map of tests/data/totalsegmentator-ct-3mm/.
#include "planning/preprocessing/label_maps.hpp"

#include <gtest/gtest.h>

#include <cstdint>
#include <fstream>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <vector>

#include "planning/imaging/lesions.hpp"
#include "planning/imaging/scan_coverage.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/preprocessing/blocking.hpp"
#include "tests/support/errors.hpp"

namespace crepuscular::planning {
namespace {

using test::expect_error_containing;

const std::string kData = std::string(CREPUSCULAR_TEST_DATA) + "/totalsegmentator-ct-3mm/";

// Five levels on the presets' scale; labels: 1 muscle (1), 2 fat (0), 3 vessel (3), 4 bone (4).
VulnerabilityTable five_levels(const std::string& name) {
  VulnerabilityTable t = VulnerabilityTable::preset("phantom");
  t.name = name;
  t.labels = {{1, "muscle", 1}, {2, "fat", 0}, {3, "vessel", 3}, {4, "bone", 4}};
  return t;
}

int level_at(const CombinedLabels& c, int64_t i, int64_t j, int64_t k) {
  const int32_t v = c.labels(i, j, k);
  return v == 0 ? -1 : c.table.levels[size_t(v - 1)].level;
}

// Map 1: 10^3 voxels of 1 mm at the origin; muscle (level 1) where i < 5, fat (0) elsewhere.
// Map 2: 4^3 voxels of 2 mm, voxel (0,0,0) at (2,2,2) mm, so its extent is [1, 9] mm on each axis;
// a vessel (3) in its voxel (1,1,1), i.e. map 1's voxels 3..4 on each axis (centres within 1 mm of
// 4 mm; 5 mm is a tie that rounds away from zero, to map 2's voxel 2), fat (0) in its other voxels.
struct TwoMaps {
  VulnerabilityTable t1 = five_levels("map1"), t2 = five_levels("map2");
  Volume<int32_t> m1, m2;
  TwoMaps() {
    ImageGeometry g1;
    g1.dims = {10, 10, 10};
    m1 = Volume<int32_t>(g1, 2);
    for (int k = 0; k < 10; ++k)
      for (int j = 0; j < 10; ++j)
        for (int i = 0; i < 5; ++i) m1(i, j, k) = 1;
    ImageGeometry g2;
    g2.dims = {4, 4, 4};
    g2.spacing = Eigen::Vector3d::Constant(2.0);
    g2.origin = Eigen::Vector3d::Constant(2.0);
    m2 = Volume<int32_t>(g2, 2);
    m2(1, 1, 1) = 3;
  }
  std::vector<LabelMapInput> inputs() const {
    return {{&m1, &t1, "map1.nii.gz"}, {&m2, &t2, "map2.nii.gz"}};
  }
};

TEST(LabelMaps, HigherLevelOfASecondMapOverridesAndOutsideItTheFirstStays) {
  const TwoMaps s;
  const CombinedLabels c = combine_label_maps(s.inputs());
  EXPECT_TRUE(c.labels.geometry().same_grid(s.m1.geometry()));
  ASSERT_EQ(c.table.levels.size(), 5u);
  for (int64_t k = 0; k < 10; ++k) {
    for (int64_t j = 0; j < 10; ++j) {
      for (int64_t i = 0; i < 10; ++i) {
        const bool vessel = i >= 3 && i <= 4 && j >= 3 && j <= 4 && k >= 3 && k <= 4;
        // Map 2's fat (0) never lowers map 1's muscle (1): the higher level wins, not the later
        // map.
        const int expected = vessel ? 3 : (i < 5 ? 1 : 0);
        EXPECT_EQ(level_at(c, i, j, k), expected) << i << " " << j << " " << k;
      }
    }
  }
  EXPECT_EQ(level_at(c, 0, 0, 0), 1);  // outside map 2: map 1's muscle
  EXPECT_EQ(level_at(c, 9, 9, 9), 0);  // outside map 2: map 1's fat
  EXPECT_EQ(c.voxels_per_level[3], 8);
  EXPECT_EQ(c.voxels_per_level[1], 5 * 10 * 10 - 8);

  // Blocking: per level the union of the maps' masks; the vessel's coefficient inside it.
  MarginOptions margin;
  margin.fwhm_mm = 0.0;
  const Volume<float> b = blocking_from_labels(c.labels, c.table, margin, "combined");
  EXPECT_FLOAT_EQ(b(3, 3, 3), 1.0f);
  EXPECT_FLOAT_EQ(b(0, 0, 0), 0.02f);
  EXPECT_FLOAT_EQ(b(9, 9, 9), 0.0f);
}

TEST(LabelMaps, ScannedVolumeIsTheIntersectionOfTheMapsExtents) {
  const TwoMaps s;
  const CombinedLabels c = combine_label_maps(s.inputs());
  ASSERT_EQ(c.coverage.grids().size(), 2u);
  EXPECT_EQ(c.coverage.grids()[1].source, "map2.nii.gz");
  EXPECT_TRUE(c.coverage.contains(Eigen::Vector3d(5, 5, 5)));
  EXPECT_TRUE(c.coverage.contains(Eigen::Vector3d(1, 9, 1)));     // on map 2's extent
  EXPECT_FALSE(c.coverage.contains(Eigen::Vector3d(0, 5, 5)));    // in map 1 only
  EXPECT_FALSE(c.coverage.contains(Eigen::Vector3d(5, 5, 9.6)));  // beyond both
  const Eigen::AlignedBox3d box = c.coverage.bounding_box();
  EXPECT_TRUE(box.min().isApprox(Eigen::Vector3d::Constant(1.0)));
  EXPECT_TRUE(box.max().isApprox(Eigen::Vector3d::Constant(9.0)));
  // Map 1's voxel centres 1..9 on each axis lie in [1, 9].
  const Volume<uint8_t> mask = c.coverage.mask(s.m1.geometry());
  int64_t covered = 0;
  for (const uint8_t x : mask.values()) covered += x;
  EXPECT_EQ(covered, 9 * 9 * 9);
  EXPECT_EQ(mask(0, 5, 5), 0);
  EXPECT_EQ(mask(1, 5, 9), 1);

  // No grid: everything is covered. A grid that does not overlap the others (a CT of another
  // patient or frame) is refused, naming both, rather than leaving the whole plan unknown.
  ScanCoverage none;
  EXPECT_TRUE(none.contains(Eigen::Vector3d(1e6, 0, 0)));
  ImageGeometry far;
  far.dims = {2, 2, 2};
  far.origin = Eigen::Vector3d(100, 0, 0);
  ScanCoverage disjoint = c.coverage;
  test::expect_error_containing([&] { disjoint.add(far, "far.nii.gz"); },
                                {"far.nii.gz", "does not overlap", "map1.nii.gz", "mm apart"});
  EXPECT_EQ(disjoint.grids().size(), c.coverage.grids().size());
}

TEST(LabelMaps, OneMapGivesExactlyItsOwnBlocking) {
  const TwoMaps s;
  const CombinedLabels c = combine_label_maps({{&s.m1, &s.t1, "map1.nii.gz"}});
  for (const double fwhm : {0.0, 5.0}) {
    MarginOptions margin;
    margin.fwhm_mm = fwhm;
    EXPECT_EQ(blocking_from_labels(c.labels, c.table, margin, "combined").values(),
              blocking_from_labels(s.m1, s.t1, margin, "map1.nii.gz").values())
        << "FWHM " << fwhm;
  }
}

TEST(LabelMaps, OutputGridMayBeGiven) {
  // On map 2's coarser grid: map 1 sampled at its centres (2, 4, 6, 8 mm: muscle at 2 and 4).
  const TwoMaps s;
  const CombinedLabels c = combine_label_maps(s.inputs(), s.m2.geometry());
  EXPECT_TRUE(c.labels.geometry().same_grid(s.m2.geometry()));
  EXPECT_EQ(level_at(c, 1, 1, 1), 3);
  EXPECT_EQ(level_at(c, 0, 0, 0), 1);
  EXPECT_EQ(level_at(c, 3, 0, 0), 0);
}

TEST(LabelMaps, ErrorsNameTheMapAndTheTables) {
  TwoMaps s;
  s.m2(0, 0, 0) = 9;
  expect_error_containing([&] { combine_label_maps(s.inputs()); },
                          {"map2.nii.gz", "label 9", "'map2'"});
  s.m2(0, 0, 0) = 2;
  s.t2.levels[3].blocking_per_mm = 2.0;
  expect_error_containing([&] { combine_label_maps(s.inputs()); },
                          {"level 3", "map1.nii.gz (table 'map1')", "map2.nii.gz (table 'map2')",
                           "1 per mm", "2 per mm"});
  expect_error_containing([&] { combine_label_maps({}); }, "none given");
}

TEST(TotalSegmentatorPresets, LiverVesselsAsInTotalSegmentatorsClassMap) {
  // TotalSegmentator's map_to_binary.py: class_map["liver_vessels"] = {1: "liver_vessels",
  // 2: "liver_tumor"}.
  const VulnerabilityTable t = VulnerabilityTable::preset("totalsegmentator_liver_vessels");
  ASSERT_EQ(t.labels.size(), 2u);
  EXPECT_EQ(t.find_label(1)->name, "liver_vessels");
  EXPECT_EQ(t.find_label(2)->name, "liver_tumor");
  EXPECT_EQ(t.find_label(2)->level, 0);
  // Vessels rated as the 'total' preset rates the portal vein, on the same scale of levels.
  const VulnerabilityTable total = VulnerabilityTable::preset("totalsegmentator");
  EXPECT_EQ(t.find_label(1)->level, total.find_label(64)->level);
  ASSERT_EQ(t.levels.size(), total.levels.size());
  for (size_t l = 0; l < t.levels.size(); ++l) {
    EXPECT_EQ(t.levels[l].level, total.levels[l].level);
    EXPECT_EQ(t.levels[l].blocking_per_mm, total.levels[l].blocking_per_mm);
  }
}

std::map<int, std::string> class_map() {
  std::ifstream in(kData + "totalsegmentator_v2_total_classmap.json");
  EXPECT_TRUE(in) << kData;
  const nlohmann::json j = nlohmann::json::parse(in);
  std::map<int, std::string> names;
  for (const auto& [key, value] : j.items()) names[std::stoi(key)] = value.get<std::string>();
  return names;
}

TEST(TotalSegmentatorData, PresetNamesMatchTheClassMapForEveryLabelPresent) {
  const Volume<int32_t> labels = read_label_map(kData + "example_seg_fast_force_split.nii.gz");
  const std::set<int32_t> present(labels.values().begin(), labels.values().end());
  EXPECT_EQ(present.size(), 62u);  // 61 structures and background
  const std::map<int, std::string> names = class_map();
  const VulnerabilityTable total = VulnerabilityTable::preset("totalsegmentator");
  for (const int32_t value : present) {
    if (value == 0) continue;
    ASSERT_EQ(names.count(value), 1u) << value;
    const LabelClass* label = total.find_label(value);
    ASSERT_NE(label, nullptr) << value << " " << names.at(value);
    EXPECT_EQ(label->name, names.at(value)) << value;
  }
  // And every entry of the class map, present here or not.
  for (const auto& [value, name] : names) {
    ASSERT_NE(total.find_label(value), nullptr) << value;
    EXPECT_EQ(total.find_label(value)->name, name) << value;
  }
}

TEST(TotalSegmentatorData, RealMapCombinedWithAFinerMapOfTheLiver) {
  // The real 'total' map (3 mm) and a liver_vessels map on a finer grid (1.5 mm) over the liver's
  // largest component, with a 'vessel' ball of radius 6 mm at its centroid.
  const Volume<int32_t> total = read_label_map(kData + "example_seg_fast_force_split.nii.gz");
  const SelectedLesion liver =
      select_lesion(label_mask(total, 5, "total"), LesionSelection::by_rank(1), "total label 5");
  EXPECT_GT(liver.lesion.volume_ml, 500.0);  // an adult liver, partly cut by the scan's top
  ImageGeometry fine;
  fine.dims = {40, 40, 40};
  fine.spacing = Eigen::Vector3d::Constant(1.5);
  fine.direction = total.geometry().direction;
  fine.origin =
      liver.lesion.centroid - fine.index_to_physical_matrix() * Eigen::Vector3d::Constant(19.5);
  Volume<int32_t> vessels(fine, 0);
  for (int64_t k = 0; k < 40; ++k)
    for (int64_t j = 0; j < 40; ++j)
      for (int64_t i = 0; i < 40; ++i)
        if ((fine.index_to_physical(i, j, k) - liver.lesion.centroid).norm() <= 6.0)
          vessels(i, j, k) = 1;
  const VulnerabilityTable total_table = VulnerabilityTable::preset("totalsegmentator");
  const VulnerabilityTable vessel_table =
      VulnerabilityTable::preset("totalsegmentator_liver_vessels");
  const CombinedLabels c = combine_label_maps(
      {{&total, &total_table, "total"}, {&vessels, &vessel_table, "liver_vessels"}});

  // At the liver's centroid: high (the vessel), in the liver away from it: none (liver), at a
  // vertebra (label 31, L1): impassable, untouched by the second map.
  const Index3 centre = total.geometry().nearest_index(liver.lesion.centroid);
  EXPECT_EQ(level_at(c, centre[0], centre[1], centre[2]), 3);
  const Volume<uint8_t> liver_mask = liver.mask;
  int64_t liver_voxels_high = 0, liver_voxels = 0;
  for (int64_t v = 0; v < total.voxel_count(); ++v) {
    if (!liver_mask[v]) continue;
    ++liver_voxels;
    const Index3 ijk = total.geometry().index_of_offset(v);
    liver_voxels_high += level_at(c, ijk[0], ijk[1], ijk[2]) == 3;
  }
  // The 6 mm ball covers about 4/3 pi 6^3 / 27 = 33.5 voxels of 3 mm.
  EXPECT_GT(liver_voxels_high, 20);
  EXPECT_LT(liver_voxels_high, 50);
  EXPECT_GT(liver_voxels, 20000);
  for (int64_t v = 0; v < total.voxel_count(); ++v) {
    if (total[v] == 31) {
      const Index3 ijk = total.geometry().index_of_offset(v);
      ASSERT_EQ(level_at(c, ijk[0], ijk[1], ijk[2]), 4);
      break;
    }
  }
  // The scanned volume is the finer map's cube, 60 mm on a side around the liver's centroid.
  EXPECT_TRUE(c.coverage.contains(liver.lesion.centroid));
  EXPECT_FALSE(c.coverage.contains(liver.lesion.centroid + Eigen::Vector3d(0, 0, 31)));
  const Volume<uint8_t> covered = c.coverage.mask(total.geometry());
  int64_t n = 0;
  for (const uint8_t x : covered.values()) n += x;
  EXPECT_NEAR(double(n), 20.0 * 20 * 20, 0.15 * 8000.0);  // 60 mm / 3 mm = 20 voxels per axis
}

}  // namespace
}  // namespace crepuscular::planning
