// Tests of 3D Slicer segmentations (planning/imaging/segmentation.hpp) and of matching their
// segment names to vulnerability tables (planning/preprocessing/segment_matching.hpp). The
// .seg.nrrd files are written here by hand, header text + raw voxels, in the layout 3D Slicer
// writes (a 'list' axis first for several layers).
#include "planning/imaging/segmentation.hpp"

#include <gtest/gtest.h>

#include <cstdint>
#include <fstream>
#include <functional>
#include <string>
#include <vector>

#include "planning/preprocessing/blocking.hpp"
#include "planning/preprocessing/label_maps.hpp"
#include "planning/preprocessing/segment_matching.hpp"
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

}  // namespace
}  // namespace crepuscular::planning
