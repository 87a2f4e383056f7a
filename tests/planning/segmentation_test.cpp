// Tests of 3D Slicer segmentations (planning/imaging/segmentation.hpp), of matching their segment
// names to vulnerability tables (planning/preprocessing/segment_matching.hpp) and of writing path
// safety classes as one (planning/safety/safety_classes.hpp class_labels). The .seg.nrrd files read
// are written here by hand, header text + raw voxels, in the layout 3D Slicer writes (a 'list'
// axis first for several layers).
#include "planning/imaging/segmentation.hpp"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <array>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include "planning/preprocessing/blocking.hpp"
#include "planning/preprocessing/label_maps.hpp"
#include "planning/preprocessing/segment_matching.hpp"
#include "planning/safety/safety_classes.hpp"
#include "planning/safety/unknown.hpp"
#include "planning/views/palette.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::planning {
namespace {

using test::expect_error_containing;

constexpr int kNx = 6, kNy = 5, kNz = 4;

// The scene: layer 0 holds Liver (value 1, i <= 2) and Portal vein (value 2, i == 4); layer 1
// holds Tumor (value 1) over i in 2..4, j in 1..2, k in 1..2, so it overlaps both.
uint8_t layer0(int i, int, int) { return i <= 2 ? 1 : (i == 4 ? 2 : 0); }
uint8_t layer1(int i, int j, int k) {
  return (i >= 2 && i <= 4 && j >= 1 && j <= 2 && k >= 1 && k <= 2) ? 1 : 0;
}

const char* kSegmentKeys =
    "Segment0_Color:=0.8 0.4 0.3\n"
    "Segment0_Extent:=0 5 0 4 0 3\n"
    "Segment0_ID:=Segment_1\n"
    "Segment0_LabelValue:=1\n"
    "Segment0_Layer:=0\n"
    "Segment0_Name:=Liver\n"
    "Segment1_ID:=Segment_2\n"
    "Segment1_LabelValue:=2\n"
    "Segment1_Layer:=0\n"
    "Segment1_Name:=Portal Vein\n"
    "Segment2_ID:=Segment_3\n"
    "Segment2_LabelValue:=1\n"
    "Segment2_Layer:=1\n"
    "Segment2_Name:=Tumor\n";

// A two-layer .seg.nrrd as Slicer writes it: sizes "2 6 5 4", kinds "list domain domain domain".
void write_two_layers(const std::string& path, const std::string& space = "left-posterior-superior",
                      const std::string& keys = kSegmentKeys,
                      const std::function<uint8_t(int, int, int, int)>& value = {}) {
  std::ofstream out(path, std::ios::binary);
  out << "NRRD0004\n"
      << "# Complete NRRD file format specification at:\n"
      << "# http://teem.sourceforge.net/nrrd/format.html\n"
      << "type: unsigned char\n"
      << "dimension: 4\n"
      << "space: " << space << "\n"
      << "sizes: 2 " << kNx << " " << kNy << " " << kNz << "\n"
      << "space directions: none (0.8,0,0) (0,1.3,0) (0,0,2.1)\n"
      << "kinds: list domain domain domain\n"
      << "encoding: raw\n"
      << "space origin: (10,20,30)\n"
      << "Segmentation_MasterRepresentation:=Binary labelmap\n"
      << "Segmentation_ReferenceImageExtentOffset:=0 0 0\n"
      << keys << "\n";
  for (int k = 0; k < kNz; ++k) {
    for (int j = 0; j < kNy; ++j) {
      for (int i = 0; i < kNx; ++i) {
        out.put(char(value ? value(0, i, j, k) : layer0(i, j, k)));
        out.put(char(value ? value(1, i, j, k) : layer1(i, j, k)));
      }
    }
  }
}

TEST(Segmentation, TwoLayersAsSlicerWritesThem) {
  test::TemporaryFolder dir;
  const std::string path = dir.file("liver.seg.nrrd");
  write_two_layers(path);
  const Segmentation seg = read_segmentation(path);

  ASSERT_EQ(seg.segments.size(), 3u);
  EXPECT_EQ(seg.segments[0].name, "Liver");
  EXPECT_EQ(seg.segments[0].id, "Segment_1");
  EXPECT_EQ(seg.segments[1].name, "Portal Vein");
  EXPECT_EQ(seg.segments[1].label_value, 2);
  EXPECT_EQ(seg.segments[1].layer, 0);
  EXPECT_EQ(seg.segments[2].name, "Tumor");
  EXPECT_EQ(seg.segments[2].label_value, 1);
  EXPECT_EQ(seg.segments[2].layer, 1);
  ASSERT_EQ(seg.layers.size(), 2u);

  // Geometry: the three domain axes, LPS as written.
  const ImageGeometry& g = seg.geometry();
  EXPECT_EQ(g.dims, (Index3{kNx, kNy, kNz}));
  EXPECT_NEAR(g.spacing.x(), 0.8, 1e-12);
  EXPECT_NEAR(g.spacing.y(), 1.3, 1e-12);
  EXPECT_NEAR(g.spacing.z(), 2.1, 1e-12);
  EXPECT_TRUE(g.origin.isApprox(Eigen::Vector3d(10, 20, 30)));
  EXPECT_TRUE(g.direction.isApprox(Eigen::Matrix3d::Identity()));

  // Every voxel of both layers as written (overlaps kept apart by the layers).
  for (int k = 0; k < kNz; ++k) {
    for (int j = 0; j < kNy; ++j) {
      for (int i = 0; i < kNx; ++i) {
        EXPECT_EQ(seg.layers[0](i, j, k), layer0(i, j, k)) << i << " " << j << " " << k;
        EXPECT_EQ(seg.layers[1](i, j, k), layer1(i, j, k)) << i << " " << j << " " << k;
      }
    }
  }
  const Volume<uint8_t> tumor = seg.segment_mask(seg.find_segment("tumor"));
  int64_t tumor_voxels = 0;
  for (const uint8_t x : tumor.values()) tumor_voxels += x;
  EXPECT_EQ(tumor_voxels, 3 * 2 * 2);
  EXPECT_EQ(seg.find_segment("portal_vein").index, 1);  // case and space/underscore ignored
  EXPECT_EQ(seg.find_segment("Segment_2").index, 1);    // by ID
  expect_error_containing([&] { seg.find_segment("spleen"); },
                          {path, "no segment named 'spleen'", "'Portal Vein'"});
}

TEST(Segmentation, RasSpaceBecomesLps) {
  // 'space: right-anterior-superior': ITK flips the first two axes of origin and directions.
  test::TemporaryFolder dir;
  const std::string path = dir.file("ras.seg.nrrd");
  write_two_layers(path, "right-anterior-superior");
  const Segmentation seg = read_segmentation(path);
  const ImageGeometry& g = seg.geometry();
  EXPECT_TRUE(g.origin.isApprox(Eigen::Vector3d(-10, -20, 30))) << g.origin.transpose();
  EXPECT_TRUE(g.direction.isApprox(Eigen::Vector3d(-1, -1, 1).asDiagonal().toDenseMatrix()))
      << g.direction;
  EXPECT_EQ(seg.layers[0](4, 0, 0), 2);
}

TEST(Segmentation, SingleLayer3DFile) {
  // One layer: a plain 3D NRRD (kinds "domain domain domain"), segments 1 and 3, no Layer keys.
  test::TemporaryFolder dir;
  const std::string path = dir.file("one.seg.nrrd");
  {
    std::ofstream out(path, std::ios::binary);
    out << "NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\n"
        << "sizes: 3 2 2\nspace directions: (0,1,0) (-1,0,0) (0,0,1)\n"
        << "kinds: domain domain domain\nendian: little\nencoding: raw\n"
        << "space origin: (0,0,0)\n"
        << "Segment0_ID:=a\nSegment0_Name:=kidney_left\nSegment0_LabelValue:=3\n"
        << "Segment0_Layer:=0\n"
        << "Segment1_ID:=b\nSegment1_Name:=spleen\nSegment1_LabelValue:=1\nSegment1_Layer:=0\n"
        << "\n";
    const int16_t values[12] = {0, 1, 3, 3, 1, 0, 0, 0, 7, 1, 1, 1};  // 7: no segment declares it
    out.write(reinterpret_cast<const char*>(values), sizeof values);
  }
  const Segmentation seg = read_segmentation(path);
  ASSERT_EQ(seg.layers.size(), 1u);
  ASSERT_EQ(seg.segments.size(), 2u);
  EXPECT_EQ(seg.segments[0].label_value, 3);
  EXPECT_TRUE(seg.geometry().direction.col(0).isApprox(Eigen::Vector3d(0, 1, 0)));
  const std::vector<int32_t> expected = {0, 1, 3, 3, 1, 0, 0, 0, 0, 1, 1, 1};  // 7 dropped
  EXPECT_EQ(seg.layers[0].values(), expected);
}

TEST(Segmentation, SegmentExtentClipsItsVoxels) {
  // Slicer ignores a segment's voxels outside Segment<N>_Extent (file index coordinates).
  test::TemporaryFolder dir;
  const std::string path = dir.file("clipped.seg.nrrd");
  std::string keys = kSegmentKeys;
  keys.replace(keys.find("Segment0_Extent:=0 5"), 20, "Segment0_Extent:=0 1");
  write_two_layers(path, "left-posterior-superior", keys);
  const Segmentation seg = read_segmentation(path);
  EXPECT_EQ(seg.layers[0](1, 0, 0), 1);
  EXPECT_EQ(seg.layers[0](2, 0, 0), 0);  // liver voxel at i = 2, outside the extent 0..1
  EXPECT_EQ(seg.layers[0](4, 0, 0), 2);  // portal vein: no extent given, kept
}

TEST(Segmentation, ObsoleteFourDimensionalLayout) {
  // Slicer's first layout: a 4D image written by ITK (a 4D space, no 'space' field), one binary
  // volume per segment along the 4th axis.
  test::TemporaryFolder dir;
  const std::string path = dir.file("old.seg.nrrd");
  {
    std::ofstream out(path, std::ios::binary);
    out << "NRRD0004\ntype: unsigned char\ndimension: 4\nspace dimension: 4\n"
        << "sizes: 2 2 1 2\n"
        << "space directions: (0,1,0,0) (-1,0,0,0) (0,0,2,0) (0,0,0,1)\n"
        << "kinds: domain domain domain domain\nencoding: raw\nspace origin: (5,6,7,0)\n"
        << "Segmentation_Extent:=0 1 0 1 0 0\n"
        << "Segment0_ID:=s0\nSegment0_Name:=aorta\n"
        << "Segment1_ID:=s1\nSegment1_Name:=liver\n\n";
    const uint8_t values[8] = {1, 0, 1, 0, 1, 1, 0, 0};
    out.write(reinterpret_cast<const char*>(values), sizeof values);
  }
  const Segmentation seg = read_segmentation(path);
  ASSERT_EQ(seg.layers.size(), 2u);
  EXPECT_EQ(seg.segments[1].layer, 1);
  EXPECT_EQ(seg.segments[1].label_value, 1);
  EXPECT_TRUE(seg.geometry().origin.isApprox(Eigen::Vector3d(5, 6, 7)));
  EXPECT_TRUE(seg.geometry().direction.col(1).isApprox(Eigen::Vector3d(-1, 0, 0)));
  EXPECT_NEAR(seg.geometry().spacing.z(), 2.0, 1e-12);
  EXPECT_EQ(seg.layers[0].values(), (std::vector<int32_t>{1, 0, 1, 0}));
  EXPECT_EQ(seg.layers[1].values(), (std::vector<int32_t>{1, 1, 0, 0}));
}

TEST(Segmentation, ErrorsNameTheFileAndTheKey) {
  test::TemporaryFolder dir;
  const auto with_keys = [&](const std::string& name, const std::string& from,
                             const std::string& to) {
    std::string keys = kSegmentKeys;
    keys.replace(keys.find(from), from.size(), to);
    const std::string path = dir.file(name);
    write_two_layers(path, "left-posterior-superior", keys);
    return path;
  };
  const std::string bad_value =
      with_keys("v.seg.nrrd", "Segment1_LabelValue:=2", "Segment1_LabelValue:=two");
  expect_error_containing([&] { read_segmentation(bad_value); },
                          {bad_value, "Segment1_LabelValue", "'two'", "1 to 65535"});
  const std::string bad_layer = with_keys("l.seg.nrrd", "Segment2_Layer:=1", "Segment2_Layer:=2");
  expect_error_containing([&] { read_segmentation(bad_layer); },
                          {bad_layer, "Segment2_Layer", "'2'", "2 layers"});
  const std::string shared =
      with_keys("d.seg.nrrd", "Segment1_LabelValue:=2", "Segment1_LabelValue:=1");
  expect_error_containing([&] { read_segmentation(shared); },
                          {shared, "Segment1_LabelValue", "same layer 0"});
  const std::string bad_extent =
      with_keys("e.seg.nrrd", "Segment0_Extent:=0 5 0 4 0 3", "Segment0_Extent:=0 5 0 4");
  expect_error_containing([&] { read_segmentation(bad_extent); }, {bad_extent, "Segment0_Extent"});

  const std::string plain = dir.file("plain.nrrd");
  write_two_layers(plain, "left-posterior-superior", "");
  expect_error_containing([&] { read_segmentation(plain); }, {plain, "no segments", "Segment0_"});
  expect_error_containing([&] { read_segmentation(dir.file("missing.seg.nrrd")); },
                          {"missing.seg.nrrd", "no such file"});
  const std::string text = dir.file("text.seg.nrrd");
  std::ofstream(text) << "not a NRRD file\n";
  expect_error_containing([&] { read_segmentation(text); }, {text, "NRRD"});
}

TEST(Segmentation, FileNamesAndStructureNames) {
  EXPECT_TRUE(is_segmentation_file("/data/Case 1.seg.nrrd"));
  EXPECT_TRUE(is_segmentation_file("x.SEG.NHDR"));
  EXPECT_FALSE(is_segmentation_file("labels.nrrd"));
  EXPECT_TRUE(structure_names_match("Portal Vein", "portal_vein"));
  EXPECT_TRUE(structure_names_match("  Inferior  vena_cava ", "inferior_vena_cava"));
  EXPECT_FALSE(structure_names_match("liver", "liver_vessels"));
}

// A table on the five-level scale of the presets with the scene's organs.
VulnerabilityTable scene_table() {
  VulnerabilityTable t = VulnerabilityTable::preset("totalsegmentator");
  t.name = "scene";
  t.labels = {{1, "liver", 0}, {2, "portal_vein", 3}, {3, "aorta", 4}};
  return t;
}

TEST(SegmentMatching, NamesMatchCaseInsensitivelyAndUnmatchedAreListed) {
  test::TemporaryFolder dir;
  const std::string path = dir.file("liver.seg.nrrd");
  write_two_layers(path);
  const Segmentation seg = read_segmentation(path);
  const VulnerabilityTable table = scene_table();

  // 'Tumor' is in no table: the error lists it and the table's names.
  expect_error_containing([&] { layer_tables(seg, table); },
                          {path, "1 segment not in vulnerability table 'scene'", "'Tumor'",
                           "'liver', 'portal_vein', 'aorta'"});
  // Excluded (the tumor of the plan): the lowest level.
  const std::vector<VulnerabilityTable> tables = layer_tables(seg, table, {"tumor"});
  ASSERT_EQ(tables.size(), 2u);
  ASSERT_EQ(tables[0].labels.size(), 2u);
  EXPECT_EQ(tables[0].find_label(1)->level, 0);  // Liver -> liver
  EXPECT_EQ(tables[0].find_label(2)->level, 3);  // Portal Vein -> portal_vein
  EXPECT_EQ(tables[0].find_label(2)->name, "Portal Vein");
  EXPECT_EQ(tables[1].find_label(1)->level, 0);  // Tumor, excluded
  EXPECT_EQ(tables[0].levels.size(), table.levels.size());
  expect_error_containing([&] { layer_tables(seg, table, {"lesion"}); },
                          {path, "no segment named 'lesion'", "'Tumor'"});
}

TEST(SegmentMatching, LayersCombineWithTheHigherLevelWinning) {
  // Layer 1's tumor (level 0) overlaps the liver (0) and the portal vein (3) of layer 0: the
  // combined map keeps the portal vein there; the blocking is that of layer 0 alone.
  test::TemporaryFolder dir;
  const std::string path = dir.file("liver.seg.nrrd");
  write_two_layers(path);
  const Segmentation seg = read_segmentation(path);
  const std::vector<VulnerabilityTable> tables = layer_tables(seg, scene_table(), {"Tumor"});
  const CombinedLabels combined = combine_label_maps(segmentation_label_maps(seg, tables));
  const auto level_at = [&](int i, int j, int k) {
    const int32_t v = combined.labels(i, j, k);
    return v == 0 ? -1 : combined.table.levels[size_t(v - 1)].level;
  };
  EXPECT_EQ(level_at(4, 1, 1), 3);   // tumor over portal vein
  EXPECT_EQ(level_at(2, 1, 1), 0);   // tumor over liver
  EXPECT_EQ(level_at(3, 1, 1), 0);   // tumor alone
  EXPECT_EQ(level_at(3, 0, 0), -1);  // nothing
  EXPECT_EQ(level_at(0, 0, 0), 0);   // liver

  MarginOptions margin;
  margin.fwhm_mm = 0.0;
  const Volume<float> b = blocking_from_labels(combined.labels, combined.table, margin, "combined");
  const Volume<float> b0 = blocking_from_labels(seg.layers[0], tables[0], margin, "layer 0");
  EXPECT_EQ(b.values(), b0.values());
}

// --- Writing: path safety classes as a segmentation --------------------------------------------

// The classes' segments as the plan writes them: default palette, unknown grey.
std::vector<SegmentSpec> class_specs() {
  const std::array<Rgb, 3> c = class_colours(Palette::kDefault);
  const auto unit = [](const Rgb& rgb) {
    return std::array<double, 3>{rgb[0] / 255.0, rgb[1] / 255.0, rgb[2] / 255.0};
  };
  return {{"safe", "safe", 1, unit(c[0])},
          {"medium", "medium", 2, unit(c[1])},
          {"dangerous", "dangerous", 3, unit(c[2])},
          {"unknown", "unknown", 4, {0.5, 0.5, 0.5}}};
}

// A grid with nothing aligned: anisotropic spacing, an offset origin, a rotated direction.
ImageGeometry oblique_grid() {
  ImageGeometry g;
  g.dims = {7, 6, 5};
  g.spacing = Eigen::Vector3d(0.8, 1.25, 2.0);
  g.origin = Eigen::Vector3d(-31.5, 12.25, 7.0);
  g.direction = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  return g;
}

// The header text of an attached-data NRRD file: everything before the blank line.
std::string nrrd_header(const std::string& path) {
  std::stringstream all;
  all << std::ifstream(path, std::ios::binary).rdbuf();
  const std::string text = all.str();
  return text.substr(0, text.find("\n\n") + 1);
}

// One value's class thresholds and nine samples on both sides of each threshold, NaN among them.
struct ValueCase {
  const char* name;
  SafetyClasses classes;
  std::array<float, 9> samples;
  float safest;  // a value that would be safe
};

// The definition (docs/ARCHITECTURE.md §4): unknown (4) where the voxel state is unknown, whatever
// the value; no class (0) for NaN; else 1 safe, 2 medium, 3 dangerous by the thresholds.
int expected_label(float value, uint8_t state, const SafetyClasses& c) {
  if (state == kRegionUnknown) return 4;
  if (std::isnan(value)) return 0;
  if (c.higher_is_safer) return value >= c.safe ? 1 : (value < c.dangerous ? 3 : 2);
  return value <= c.safe ? 1 : (value > c.dangerous ? 3 : 2);
}

TEST(SegmentationWriting, PathSafetyClassesReadBackVoxelForVoxel) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const ValueCase cases[] = {{"svv",
                              {true, 90.0, 50.0},
                              {nan, 0.0f, 49.99f, 50.0f, 50.01f, 89.99f, 90.0f, 90.01f, 100.0f},
                              100.0f},
                             {"bvv",
                              {false, 2.5, 7.25},
                              {nan, 0.0f, 2.49f, 2.5f, 2.51f, 7.24f, 7.25f, 7.26f, 1e6f},
                              0.0f}};
  const ImageGeometry g = oblique_grid();
  for (const ValueCase& vc : cases) {
    SCOPED_TRACE(vc.name);
    // Samples cycled over the voxels; the last slice (k = 4) is outside the scan: unknown, NaN but
    // for one voxel that holds the safest value (unknown all the same). NaN elsewhere: outside the
    // region of interest.
    Volume<float> values(g, nan);
    Volume<uint8_t> region(g, kRegionNotComputed);
    for (int k = 0; k < 5; ++k) {
      for (int j = 0; j < 6; ++j) {
        for (int i = 0; i < 7; ++i) {
          if (k == 4) {
            region(i, j, k) = kRegionUnknown;
            values(i, j, k) = i == 0 && j == 0 ? vc.safest : nan;
          } else {
            values(i, j, k) = vc.samples[size_t((i + 2 * j + 3 * k) % 9)];
            region(i, j, k) = std::isnan(values(i, j, k)) ? kRegionNotComputed : kRegionComputed;
          }
        }
      }
    }
    test::TemporaryFolder dir;
    const std::string path = dir.file(std::string("path_safety_") + vc.name + "_classes.seg.nrrd");
    write_segmentation(path, class_labels(values, vc.classes, region), class_specs());

    const Segmentation seg = read_segmentation(path);
    ASSERT_EQ(seg.layers.size(), 1u);
    ASSERT_EQ(seg.segments.size(), 4u);
    const std::vector<SegmentSpec> specs = class_specs();
    for (size_t n = 0; n < 4; ++n) {
      const Segment& s = seg.segments[n];
      EXPECT_EQ(s.id, specs[n].id);
      EXPECT_EQ(s.name, specs[n].name);
      EXPECT_EQ(s.label_value, int(n) + 1);
      EXPECT_EQ(s.layer, 0);
      ASSERT_TRUE(s.colour.has_value()) << s.name;
      for (size_t c = 0; c < 3; ++c) EXPECT_EQ((*s.colour)[c], specs[n].colour[c]) << s.name;
    }
    // Green 200/255, grey 0.5: the colours as Slicer reads them, 0..1.
    EXPECT_NEAR((*seg.segments[0].colour)[1], 200.0 / 255.0, 1e-15);
    EXPECT_EQ(*seg.segments[3].colour, (std::array<double, 3>{0.5, 0.5, 0.5}));

    const ImageGeometry& r = seg.geometry();
    EXPECT_EQ(r.dims, g.dims);
    EXPECT_LT((r.origin - g.origin).cwiseAbs().maxCoeff(), 1e-9) << r.origin.transpose();
    EXPECT_LT((r.spacing - g.spacing).cwiseAbs().maxCoeff(), 1e-9) << r.spacing.transpose();
    EXPECT_LT((r.direction - g.direction).cwiseAbs().maxCoeff(), 1e-9) << r.direction;

    // Each segment holds exactly its class's voxels; every class occurs, unknown on the last
    // slice only (30 voxels, the safest value among them), no class where NaN.
    std::array<int64_t, 5> voxels{};
    for (int64_t v = 0; v < g.voxel_count(); ++v) {
      ++voxels[size_t(expected_label(values[v], region[v], vc.classes))];
    }
    for (size_t n = 0; n < 4; ++n) {
      const Volume<uint8_t> mask = seg.segment_mask(seg.segments[n]);
      int64_t differing = 0, inside = 0;
      for (int64_t v = 0; v < g.voxel_count(); ++v) {
        const bool expected = expected_label(values[v], region[v], vc.classes) == int(n) + 1;
        differing += (mask[v] != 0) != expected ? 1 : 0;
        inside += mask[v];
      }
      EXPECT_EQ(differing, 0) << seg.segments[n].name;
      EXPECT_EQ(inside, voxels[n + 1]) << seg.segments[n].name;
      EXPECT_GT(inside, 0) << seg.segments[n].name;
    }
    EXPECT_EQ(voxels[4], 7 * 6);
    EXPECT_EQ(seg.layers[0](0, 0, 4), 4);  // the safest value outside the scan: unknown
    EXPECT_GT(voxels[0], 0);

    // The header keys 3D Slicer writes, LPS, gzip.
    const std::string header = nrrd_header(path);
    for (const char* line :
         {"type: unsigned char\n", "dimension: 3\n", "space: left-posterior-superior\n",
          "sizes: 7 6 5\n", "kinds: domain domain domain\n", "encoding: gzip\n",
          "Segmentation_MasterRepresentation:=Binary labelmap\n",
          "Segmentation_ContainedRepresentationNames:=Binary labelmap|\n",
          "Segmentation_ReferenceImageExtentOffset:=0 0 0\n", "Segment0_ID:=safe\n",
          "Segment1_Name:=medium\n", "Segment2_LabelValue:=3\n", "Segment3_Layer:=0\n",
          "Segment3_Color:=0.5 0.5 0.5\n", "Segment3_Extent:=0 6 0 5 0 4\n",
          "Segment0_NameAutoGenerated:=0\n", "Segment0_ColorAutoGenerated:=0\n"}) {
      EXPECT_NE(header.find(line), std::string::npos) << line << "in\n" << header;
    }
    EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir.path()),
                            std::filesystem::directory_iterator()),
              1);  // no temporary left beside it
  }
}

TEST(SegmentationWriting, BadSegmentsAndVoxelsAreRefusedNamingTheFile) {
  test::TemporaryFolder dir;
  Volume<uint8_t> labels(oblique_grid(), 0);
  labels(1, 2, 3) = 2;
  const std::string path = dir.file("classes.seg.nrrd");
  expect_error_containing(
      [&] { write_segmentation(dir.file("classes.nrrd"), labels, class_specs()); },
      {"classes.nrrd", "ending in .seg.nrrd"});
  std::vector<SegmentSpec> specs = class_specs();
  specs[3].label_value = 2;
  expect_error_containing([&] { write_segmentation(path, labels, specs); },
                          {path, "segment 3 'unknown'", "label value 2", "as segment 1"});
  specs = class_specs();
  specs[1].id = "safe";
  expect_error_containing([&] { write_segmentation(path, labels, specs); },
                          {path, "segment 1 'medium'", "ID 'safe'"});
  specs = class_specs();
  specs[0].colour[1] = 200.0;  // 0..255 instead of 0..1
  expect_error_containing([&] { write_segmentation(path, labels, specs); },
                          {path, "segment 0 'safe'", "200", "[0, 1]"});
  labels(0, 0, 0) = 9;
  expect_error_containing([&] { write_segmentation(path, labels, class_specs()); },
                          {path, "1 voxels hold the value 9", "no segment declares"});
  EXPECT_FALSE(std::filesystem::exists(path));
  // Voxel states on another grid than the values are refused.
  ImageGeometry other = oblique_grid();
  other.dims[2] = 4;
  expect_error_containing(
      [&] {
        class_labels(Volume<float>(oblique_grid(), 1.0f), SafetyClasses{},
                     Volume<uint8_t>(other, kRegionComputed));
      },
      {"another grid"});
}

}  // namespace
}  // namespace crepuscular::planning
