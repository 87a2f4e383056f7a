// Tests of the tumor as a label of a label map (planning/imaging/lesions.hpp): connected components
// of three balls of known size and centre, chosen by rank or by a point; and of the FILE[:LABEL]
// specs (planning/imaging/file_spec.hpp).
#include "planning/imaging/lesions.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <set>
#include <string>
#include <vector>

#include "planning/imaging/file_spec.hpp"
#include "tests/support/errors.hpp"

namespace crepuscular::planning {
namespace {

using test::expect_error_containing;

struct Ball {
  Eigen::Vector3d centre;  // LPS mm, on a voxel centre so that the centroid is exact
  double radius_mm;
};

// 40 x 36 x 30 voxels of 1 x 1 x 1.5 mm, origin (-20, -10, 5): label 2 in three balls of radii 6,
// 4 and 2.5 mm, label 1 (another structure) in a slab away from them.
struct Scene {
  ImageGeometry g;
  std::vector<Ball> balls;
  Volume<int32_t> labels;
  std::vector<int64_t> voxels;  // per ball, counted when drawing it
};

Scene three_balls() {
  Scene s;
  s.g.dims = {40, 36, 30};
  s.g.spacing = Eigen::Vector3d(1.0, 1.0, 1.5);
  s.g.origin = Eigen::Vector3d(-20, -10, 5);
  s.balls = {{s.g.index_to_physical(10, 10, 10), 6.0},
             {s.g.index_to_physical(28, 24, 12), 4.0},
             {s.g.index_to_physical(30, 8, 22), 2.5}};
  s.labels = Volume<int32_t>(s.g, 0);
  s.voxels.assign(s.balls.size(), 0);
  for (int64_t k = 0; k < s.g.dims[2]; ++k) {
    for (int64_t j = 0; j < s.g.dims[1]; ++j) {
      for (int64_t i = 0; i < s.g.dims[0]; ++i) {
        const Eigen::Vector3d p = s.g.index_to_physical(i, j, k);
        if (k >= 27) s.labels(i, j, k) = 1;
        for (size_t b = 0; b < s.balls.size(); ++b) {
          if ((p - s.balls[b].centre).norm() <= s.balls[b].radius_mm) {
            s.labels(i, j, k) = 2;
            ++s.voxels[b];
          }
        }
      }
    }
  }
  return s;
}

TEST(Lesions, ThreeBallsRankedBySizeWithTheirCentroids) {
  const Scene s = three_balls();
  const Volume<uint8_t> mask = label_mask(s.labels, 2, "labels.nii.gz");
  Volume<int32_t> rank_of;
  const std::vector<Lesion> lesions = find_lesions(mask, &rank_of);
  ASSERT_EQ(lesions.size(), 3u);
  const double voxel_ml = s.g.voxel_volume_mm3() / 1000.0;
  for (size_t b = 0; b < 3; ++b) {
    EXPECT_EQ(lesions[b].rank, int(b + 1));
    EXPECT_EQ(lesions[b].voxels, s.voxels[b]);
    EXPECT_NEAR(lesions[b].volume_ml, double(s.voxels[b]) * voxel_ml, 1e-12);
    // Voxel count of a ball of radius r: 4/3 pi r^3 within 25 % for r >= 2.5 voxels.
    const double r = s.balls[b].radius_mm;
    EXPECT_NEAR(lesions[b].volume_ml, 4.0 / 3.0 * M_PI * r * r * r / 1000.0,
                0.25 * 4.0 / 3.0 * M_PI * r * r * r / 1000.0);
    // A ball centred on a voxel centre is symmetric about it.
    EXPECT_TRUE(lesions[b].centroid.isApprox(s.balls[b].centre, 1e-12))
        << lesions[b].centroid.transpose() << " vs " << s.balls[b].centre.transpose();
    const Index3 c = s.g.nearest_index(s.balls[b].centre);
    EXPECT_EQ(rank_of(c[0], c[1], c[2]), int(b + 1));
  }
  EXPECT_EQ(rank_of(0, 0, 0), 0);
}

TEST(Lesions, SeveralLesionsWithoutSelectionAreListed) {
  const Scene s = three_balls();
  const Volume<uint8_t> mask = label_mask(s.labels, 2, "labels.nii.gz");
  const std::vector<Lesion> lesions = find_lesions(mask);
  const auto centroid_text = [](const Eigen::Vector3d& c) {
    char buffer[80];
    std::snprintf(buffer, sizeof buffer, "(%.1f, %.1f, %.1f) mm LPS", c.x(), c.y(), c.z());
    return std::string(buffer);
  };
  expect_error_containing(
      [&] { select_lesion(mask, LesionSelection::only(), "labels.nii.gz label 2"); },
      {"labels.nii.gz label 2", "3 separate lesions",
       "#1: " + std::to_string(s.voxels[0]) + " voxels",
       "#3: " + std::to_string(s.voxels[2]) + " voxels", " mL", centroid_text(lesions[0].centroid),
       centroid_text(lesions[2].centroid)});
  expect_error_containing(
      [&] { select_lesion(mask, LesionSelection::by_rank(4), "labels.nii.gz label 2"); },
      {"lesion 4 requested", "are 3 lesions", "#2: "});
  expect_error_containing(
      [&] { select_lesion(mask, LesionSelection::by_rank(0), "labels.nii.gz label 2"); },
      "expected 1 to 3");
}

TEST(Lesions, SelectionByRankAndByPoint) {
  const Scene s = three_balls();
  const Volume<uint8_t> mask = label_mask(s.labels, 2, "labels.nii.gz");
  const auto count = [](const Volume<uint8_t>& m) {
    int64_t n = 0;
    for (const uint8_t x : m.values()) n += x;
    return n;
  };

  const SelectedLesion largest = select_lesion(mask, LesionSelection::by_rank(1), "tumor");
  EXPECT_EQ(largest.lesion.rank, 1);
  EXPECT_EQ(largest.lesion_count, 3);
  EXPECT_EQ(count(largest.mask), s.voxels[0]);
  const SelectedLesion third = select_lesion(mask, LesionSelection::by_rank(3), "tumor");
  EXPECT_EQ(count(third.mask), s.voxels[2]);
  const Index3 c3 = s.g.nearest_index(s.balls[2].centre);
  EXPECT_EQ(third.mask(c3[0], c3[1], c3[2]), 1);

  // A point inside ball 2 (1 mm off its centre).
  const SelectedLesion inside =
      select_lesion(mask, LesionSelection::at(s.balls[1].centre + Eigen::Vector3d(1, 0, 0)), "t");
  EXPECT_EQ(inside.lesion.rank, 2);
  EXPECT_EQ(inside.distance_mm, 0.0);
  // A point 5 mm beyond ball 3's surface along +L (voxel centres at integer mm in L): the nearest
  // voxel of ball 3 is at its centre + 2 mm (radius 2.5), 5.5 mm away.
  const Eigen::Vector3d outside = s.balls[2].centre + Eigen::Vector3d(7.5, 0, 0);
  const SelectedLesion near = select_lesion(mask, LesionSelection::at(outside), "t");
  EXPECT_EQ(near.lesion.rank, 3);
  EXPECT_NEAR(near.distance_mm, 5.5, 1e-9);
}

TEST(Lesions, OneLesionNeedsNoSelectionAndCornersConnect) {
  // Two voxels touching at a corner are one lesion (26-connectivity).
  ImageGeometry g;
  g.dims = {4, 4, 4};
  Volume<uint8_t> mask(g, 0);
  mask(1, 1, 1) = 1;
  mask(2, 2, 2) = 1;
  const SelectedLesion only = select_lesion(mask, LesionSelection::only(), "tumor.nii.gz");
  EXPECT_EQ(only.lesion_count, 1);
  EXPECT_EQ(only.lesion.voxels, 2);
  EXPECT_TRUE(only.lesion.centroid.isApprox(Eigen::Vector3d(1.5, 1.5, 1.5)));
  EXPECT_EQ(only.mask.values(), mask.values());

  const Volume<uint8_t> empty(g, 0);
  expect_error_containing([&] { select_lesion(empty, LesionSelection::only(), "tumor.nii.gz"); },
                          {"tumor.nii.gz", "empty"});
}

TEST(Lesions, MissingLabelListsThosePresent) {
  const Scene s = three_balls();
  expect_error_containing([&] { label_mask(s.labels, 5, "labels.nii.gz"); },
                          {"labels.nii.gz", "no voxel has label 5", "labels present: 1-2"});
}

TEST(FileSpec, SeparatorRules) {
  const auto split = [](const std::string& spec) { return split_file_spec(spec, "tumor"); };
  EXPECT_EQ(split("labels.nii.gz").path, "labels.nii.gz");
  EXPECT_FALSE(split("labels.nii.gz").qualifier);
  EXPECT_EQ(split("labels.nii.gz:2").path, "labels.nii.gz");
  EXPECT_EQ(*split("labels.nii.gz:2").qualifier, "2");
  // The table may be a path with '/': the volume's extension marks the end of the file.
  EXPECT_EQ(split("/data/labels.nii.gz:/tables/mine.json").path, "/data/labels.nii.gz");
  EXPECT_EQ(*split("/data/labels.nii.gz:/tables/mine.json").qualifier, "/tables/mine.json");
  EXPECT_EQ(split("C:/scans/Labels.NRRD:totalsegmentator").path, "C:/scans/Labels.NRRD");
  EXPECT_EQ(*split("case.seg.nrrd:Tumor 2").qualifier, "Tumor 2");
  // No volume extension: the last ':' whose tail holds no path separator.
  EXPECT_EQ(split("/data/scan:3/labels").path, "/data/scan:3/labels");
  EXPECT_FALSE(split("/data/scan:3/labels").qualifier);
  EXPECT_EQ(split("/data/a:b/labels:7").path, "/data/a:b/labels");
  EXPECT_EQ(*split("/data/a:b/labels:7").qualifier, "7");
  EXPECT_EQ(split("C:\\scans\\labels").path, "C:\\scans\\labels");
  // A file that exists whole wins; a head that is a file is split after.
  const std::set<std::string> files = {"odd:name.nii.gz", "/data/labels"};
  const auto is_file = [&](const std::string& p) { return files.count(p) > 0; };
  EXPECT_FALSE(split_file_spec("odd:name.nii.gz", "labels", is_file).qualifier);
  EXPECT_EQ(split_file_spec("/data/labels:my/table.json", "labels", is_file).path, "/data/labels");
  expect_error_containing([&] { split("labels.nii.gz:"); }, {"tumor", "nothing after ':'"});
  expect_error_containing([&] { split(""); }, {"tumor", "empty"});
}

TEST(FileSpec, LabelValues) {
  EXPECT_EQ(parse_label_value("5"), 5);
  EXPECT_EQ(parse_label_value("65535"), 65535);
  EXPECT_FALSE(parse_label_value("0"));
  EXPECT_FALSE(parse_label_value("65536"));
  EXPECT_FALSE(parse_label_value("-1"));
  EXPECT_FALSE(parse_label_value("Tumor"));
  EXPECT_FALSE(parse_label_value("2.0"));
}

}  // namespace
}  // namespace crepuscular::planning
