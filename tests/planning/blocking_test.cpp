// Tests of preprocessing (planning/blocking.hpp): blocking from labels with and without the
// Gaussian safety margin (checked against the analytic edge response), level combination by
// maximum, anisotropic spacing, CT thresholding, and validation of ready blocking volumes.
#include "planning/preprocessing/blocking.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <initializer_list>
#include <limits>
#include <string>

#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"

namespace crepuscular::planning {
namespace {

using test::expect_error_containing;

// Labels 1..4 at levels 1..4 (0.02, 0.1, 1, 100 per mm); label 5 at level 0 (no blocking).
VulnerabilityTable test_table() {
  const nlohmann::json j = {{"name", "test"},
                            {"levels",
                             {{{"level", 0}, {"name", "none"}, {"blocking_per_mm", 0.0}},
                              {{"level", 1}, {"name", "low"}, {"blocking_per_mm", 0.02}},
                              {{"level", 2}, {"name", "medium"}, {"blocking_per_mm", 0.1}},
                              {{"level", 3}, {"name", "high"}, {"blocking_per_mm", 1.0}},
                              {{"level", 4}, {"name", "impassable"}, {"blocking_per_mm", 100.0}}}},
                            {"labels",
                             {{{"value", 1}, {"name", "muscle"}, {"level", 1}},
                              {{"value", 2}, {"name", "organ"}, {"level", 2}},
                              {{"value", 3}, {"name", "vessel"}, {"level", 3}},
                              {{"value", 4}, {"name", "bone"}, {"level", 4}},
                              {{"value", 5}, {"name", "liver"}, {"level", 0}}}}};
  return VulnerabilityTable::from_json(j, "test table");
}

ImageGeometry grid(Index3 dims, Eigen::Vector3d spacing) {
  ImageGeometry g;
  g.dims = dims;
  g.spacing = spacing;
  g.origin = Eigen::Vector3d(-10.0, 20.0, 5.0);
  return g;
}

double sigma_of_fwhm(double fwhm) { return fwhm / (2.0 * std::sqrt(2.0 * std::log(2.0))); }

// Blurring the indicator of a half space with a Gaussian of sigma gives, at signed distance d
// outside its face, 0.5 * erfc(d / (sigma sqrt(2))).
double edge_response(double d_mm, double sigma_mm) {
  return 0.5 * std::erfc(d_mm / (sigma_mm * std::sqrt(2.0)));
}

// Slab of `label` across the whole grid, `first`..`last` (inclusive) along `axis`.
Volume<int32_t> slab(const ImageGeometry& g, int axis, int64_t first, int64_t last, int32_t label) {
  Volume<int32_t> v(g, 0);
  for (int64_t k = 0; k < g.dims[2]; ++k) {
    for (int64_t j = 0; j < g.dims[1]; ++j) {
      for (int64_t i = 0; i < g.dims[0]; ++i) {
        const int64_t x = axis == 0 ? i : axis == 1 ? j : k;
        if (x >= first && x <= last) v(i, j, k) = label;
      }
    }
  }
  return v;
}

// Checks b along `axis` (through the grid's first row) against the analytic profile of a slab
// first..last of coefficient coeff; returns the largest deviation, in units of coeff.
double max_profile_error(const Volume<float>& b, int axis, int64_t first, int64_t last,
                         double coeff, double fwhm) {
  const ImageGeometry& g = b.geometry();
  const double h = g.spacing[axis];
  const double sigma = sigma_of_fwhm(fwhm);
  double worst = 0.0;
  for (int64_t x = 0; x < g.dims[axis]; ++x) {
    Index3 ijk{0, 0, 0};
    ijk[size_t(axis)] = x;
    const double value = b(ijk[0], ijk[1], ijk[2]);
    if (x >= first && x <= last) {
      // Inside the structure the margin never lowers the coefficient.
      EXPECT_GE(value, coeff * (1.0 - 1e-6)) << "x " << x;
      EXPECT_LE(value, coeff * (1.0 + 1e-5)) << "x " << x;
      continue;
    }
    // Distance to the nearer face of the slab (faces half a voxel outside the end voxels); the far
    // face adds its own (tiny, slab >> sigma) tail.
    const double d_low = (double(first) - 0.5 - double(x)) * h;
    const double d_high = (double(x) - double(last) - 0.5) * h;
    const double expected =
        coeff * (x < first ? edge_response(d_low, sigma) -
                                 edge_response(d_low + (last - first + 1) * h, sigma)
                           : edge_response(d_high, sigma) -
                                 edge_response(d_high + (last - first + 1) * h, sigma));
    worst = std::max(worst, std::abs(value - expected) / coeff);
  }
  return worst;
}

TEST(BlockingFromLabels, WithoutMarginIsTheCoefficientInsideAndZeroOutside) {
  // A one-voxel-thick slab of "vessel" (1 per mm) at k = 4: exactly 1 there, 0 elsewhere.
  const ImageGeometry g = grid({9, 7, 9}, Eigen::Vector3d(1.0, 1.0, 1.0));
  const Volume<int32_t> labels = slab(g, 2, 4, 4, 3);
  const Volume<float> b = blocking_from_labels(labels, test_table(), MarginOptions{0.0}, "labels");
  ASSERT_TRUE(b.geometry().same_grid(g));
  for (int64_t v = 0; v < b.voxel_count(); ++v) {
    const Index3 ijk = g.index_of_offset(v);
    EXPECT_EQ(b[v], ijk[2] == 4 ? 1.0f : 0.0f) << ijk[0] << " " << ijk[1] << " " << ijk[2];
  }
}

TEST(BlockingFromLabels, LevelZeroAndBackgroundNeverBlock) {
  // Liver (level 0, coefficient 0) everywhere but one background voxel; margin on: all zero.
  const ImageGeometry g = grid({12, 12, 12}, Eigen::Vector3d(1.0, 1.0, 1.0));
  Volume<int32_t> labels(g, 5);
  labels(0, 0, 0) = 0;
  const Volume<float> b = blocking_from_labels(labels, test_table(), MarginOptions{5.0}, "labels");
  for (int64_t v = 0; v < b.voxel_count(); ++v) EXPECT_EQ(b[v], 0.0f);
}

TEST(BlockingFromLabels, MarginFollowsTheGaussianEdgeResponse) {
  // A 30 mm slab of bone (100 per mm), thickness >> FWHM, 1 mm voxels: the margin outside each face
  // is 100 * 0.5 erfc(d / (sigma sqrt 2)), d = distance to the face, sigma = FWHM / 2.355; the
  // discrete Gaussian matches it within 2 % of the coefficient.
  for (const double fwhm : {5.0, 8.0}) {
    const ImageGeometry g = grid({3, 2, 100}, Eigen::Vector3d(1.0, 1.0, 1.0));
    const Volume<int32_t> labels = slab(g, 2, 35, 64, 4);
    const Volume<float> b =
        blocking_from_labels(labels, test_table(), MarginOptions{fwhm}, "labels");
    EXPECT_LT(max_profile_error(b, 2, 35, 64, 100.0, fwhm), 0.02) << "FWHM " << fwhm;
    // Half the coefficient half-way between the face voxels, so ~ 0.5 erfc(0.5/(sigma sqrt2)) at
    // the first voxel outside: well above zero, below the coefficient.
    EXPECT_GT(b(0, 0, 65), 30.0f);
    EXPECT_LT(b(0, 0, 65), 50.0f);
    // Far from the slab (> 4 sigma + 1 mm) the margin has died out.
    EXPECT_LT(b(0, 0, 99), 1e-3f);
    // The same across the slab's other dimensions (it fills them).
    EXPECT_FLOAT_EQ(b(2, 1, 66), b(0, 0, 66));
  }
}

TEST(BlockingFromLabels, OverlappingLevelsCombineByMaximum) {
  // A vessel slab (1 per mm) and a bone slab (100 per mm) 4 mm apart: their margins overlap in the
  // gap. The result is the voxel-wise maximum of the two levels computed alone, not their sum.
  const ImageGeometry g = grid({2, 2, 60}, Eigen::Vector3d(1.0, 1.0, 1.0));
  Volume<int32_t> both = slab(g, 2, 10, 24, 3);
  const Volume<int32_t> bone_only = slab(g, 2, 29, 45, 4);
  for (int64_t v = 0; v < g.voxel_count(); ++v) {
    if (bone_only[v] != 0) both[v] = bone_only[v];
  }
  const Volume<int32_t> vessel_only = slab(g, 2, 10, 24, 3);
  const MarginOptions m{5.0};
  const auto table = test_table();
  const Volume<float> b = blocking_from_labels(both, table, m, "labels");
  const Volume<float> b_vessel = blocking_from_labels(vessel_only, table, m, "labels");
  const Volume<float> b_bone = blocking_from_labels(bone_only, table, m, "labels");
  bool some_overlap = false;
  for (int64_t v = 0; v < g.voxel_count(); ++v) {
    EXPECT_FLOAT_EQ(b[v], std::max(b_vessel[v], b_bone[v])) << "offset " << v;
    some_overlap = some_overlap || (b_vessel[v] > 1e-3f && b_bone[v] > 1e-3f);
  }
  EXPECT_TRUE(some_overlap);  // the test does exercise overlapping margins
  // Inside the vessel slab far from the bone: the vessel coefficient.
  EXPECT_NEAR(b(0, 0, 14), 1.0f, 1e-5f);
  // In the vessel slab next to the gap, the bone's margin (100 * ~0.0x) wins over 1.
  EXPECT_GT(b(0, 0, 24), 1.0f);
}

TEST(BlockingFromLabels, AnisotropicSpacingGivesTheSameProfileInMm) {
  // Spacing 0.5, 1.0 and 1.5 mm: a 30 mm slab normal to each axis in turn gives the analytic
  // profile in mm (the Gaussian is defined in physical units, not voxels).
  const Eigen::Vector3d spacing(0.5, 1.0, 1.5);
  const double fwhm = 6.0;
  for (int axis = 0; axis < 3; ++axis) {
    const double h = spacing[axis];
    Index3 dims{2, 2, 2};
    dims[size_t(axis)] = int64_t(std::lround(90.0 / h));  // 90 mm along the slab normal
    const ImageGeometry g = grid(dims, spacing);
    const int64_t first = std::lround(30.0 / h);
    const int64_t last = first + std::lround(30.0 / h) - 1;
    const Volume<int32_t> labels = slab(g, axis, first, last, 3);
    const Volume<float> b = blocking_from_labels(labels, test_table(), MarginOptions{fwhm}, "l");
    EXPECT_LT(max_profile_error(b, axis, first, last, 1.0, fwhm), 0.02) << "axis " << axis;
    // About 3 mm outside the face (the voxel centre nearest to it), on every axis.
    Index3 ijk{0, 0, 0};
    ijk[size_t(axis)] = last + std::lround(3.0 / h);
    const double d = (double(ijk[size_t(axis)] - last) - 0.5) * h;
    EXPECT_NEAR(b(ijk[0], ijk[1], ijk[2]), edge_response(d, sigma_of_fwhm(fwhm)), 0.02)
        << "axis " << axis;
  }
}

TEST(BlockingFromLabels, UnknownLabelThrowsBeforeSmoothing) {
  const ImageGeometry g = grid({6, 6, 6}, Eigen::Vector3d(1.0, 1.0, 1.0));
  Volume<int32_t> labels(g, 1);
  labels(3, 2, 1) = 17;
  expect_error_containing(
      [&] { blocking_from_labels(labels, test_table(), MarginOptions{5.0}, "labels.nii.gz"); },
      {"labels.nii.gz", "label 17", "'test'", "known: 1-5"});
  labels(3, 2, 1) = -2;  // negative values are not labels either
  expect_error_containing(
      [&] { blocking_from_labels(labels, test_table(), MarginOptions{5.0}, "labels.nii.gz"); },
      {"labels.nii.gz", "label -2"});
}

TEST(BlockingFromLabels, BadGeometryAndMarginAreRejected) {
  ImageGeometry g = grid({4, 4, 4}, Eigen::Vector3d(1.0, 0.0, 1.0));
  const Volume<int32_t> labels(g, 1);
  expect_error_containing(
      [&] { blocking_from_labels(labels, test_table(), MarginOptions{5.0}, "labels.nii.gz"); },
      {"labels.nii.gz", "spacing"});
  const Volume<int32_t> good(grid({4, 4, 4}, Eigen::Vector3d(1.0, 1.0, 1.0)), 1);
  expect_error_containing(
      [&] { blocking_from_labels(good, test_table(), MarginOptions{-1.0}, "labels.nii.gz"); },
      {"FWHM", "-1"});
}

// Synthetic CT, 1 mm voxels: air (-1000 HU) around a body cylinder of fat (-100 HU, radius 15 mm,
// along k, closed by air above and below), a 4 mm bone cube (700 HU) and a 3 mm air pocket
// (-900 HU) inside the fat.
Volume<float> synthetic_ct() {
  const ImageGeometry g = grid({40, 40, 26}, Eigen::Vector3d(1.0, 1.0, 1.0));
  Volume<float> ct(g, -1000.0f);
  for (int64_t k = 3; k <= 22; ++k) {
    for (int64_t j = 0; j < 40; ++j) {
      for (int64_t i = 0; i < 40; ++i) {
        const double x = double(i) - 19.5;
        const double y = double(j) - 19.5;
        if (x * x + y * y <= 15.0 * 15.0) ct(i, j, k) = -100.0f;
      }
    }
  }
  for (int64_t k = 10; k <= 13; ++k)
    for (int64_t j = 18; j <= 21; ++j)
      for (int64_t i = 8; i <= 11; ++i) ct(i, j, k) = 700.0f;
  for (int64_t k = 11; k <= 13; ++k)
    for (int64_t j = 18; j <= 20; ++j)
      for (int64_t i = 26; i <= 28; ++i) ct(i, j, k) = -900.0f;
  return ct;
}

bool in_bone(int64_t i, int64_t j, int64_t k) {
  return i >= 8 && i <= 11 && j >= 18 && j <= 21 && k >= 10 && k <= 13;
}
bool in_pocket(int64_t i, int64_t j, int64_t k) {
  return i >= 26 && i <= 28 && j >= 18 && j <= 20 && k >= 11 && k <= 13;
}

TEST(BlockingFromCt, BoneAndInternalAirAreImpassableOutsideAirAndFatAreFree) {
  const Volume<float> ct = synthetic_ct();
  const CtThresholds th;  // bone >= 250 HU, air <= -400 HU, 100 per mm
  const Volume<float> b = blocking_from_ct(ct, th, MarginOptions{0.0});
  const ImageGeometry& g = b.geometry();
  ASSERT_TRUE(g.same_grid(ct.geometry()));
  int64_t impassable = 0;
  for (int64_t v = 0; v < b.voxel_count(); ++v) {
    const Index3 x = g.index_of_offset(v);
    const bool expected = in_bone(x[0], x[1], x[2]) || in_pocket(x[0], x[1], x[2]);
    EXPECT_EQ(b[v], expected ? 100.0f : 0.0f) << x[0] << " " << x[1] << " " << x[2];
    impassable += b[v] > 0.0f ? 1 : 0;
  }
  EXPECT_EQ(impassable, 64 + 27);  // the bone cube and the pocket, nothing else
}

TEST(BlockingFromCt, MarginSpreadsIntoTheFatNearby) {
  const Volume<float> ct = synthetic_ct();
  const Volume<float> b = blocking_from_ct(ct, CtThresholds{}, MarginOptions{5.0});
  EXPECT_GE(b(9, 19, 11), 100.0f * (1.0f - 1e-6f));   // inside the bone: never lowered
  EXPECT_GE(b(27, 19, 12), 100.0f * (1.0f - 1e-6f));  // inside the pocket
  EXPECT_GT(b(12, 19, 11), 1.0f);                     // fat right beside the bone
  EXPECT_LT(b(12, 19, 11), 100.0f);
  EXPECT_LT(b(19, 8, 11), 1e-3f);  // fat > 10 mm (~ 5 sigma) from both: free
  EXPECT_LT(b(0, 0, 0), 1e-3f);    // outside air: free
}

// A body (fat) cylinder along index axis `axis`, cut by the field of view at both ends, with an air
// column (a lung or the trachea) inside it running through the whole volume, 1 mm voxels. The
// direction maps index axis `table_axis` to LPS S (the scanner's table axis).
Volume<float> cut_body_ct(int axis, int table_axis) {
  ImageGeometry g = grid({24, 24, 24}, Eigen::Vector3d(1.0, 1.0, 1.0));
  g.direction.setZero();
  for (int a = 0; a < 3; ++a) g.direction((a + 2 - table_axis + 3) % 3, a) = 1.0;  // cyclic: det +1
  Volume<float> ct(g, -1000.0f);
  for (int64_t v = 0; v < g.voxel_count(); ++v) {
    const Index3 x = g.index_of_offset(v);
    const double u = double(x[size_t((axis + 1) % 3)]) - 11.5;
    const double w = double(x[size_t((axis + 2) % 3)]) - 11.5;
    if (u * u + w * w <= 10.0 * 10.0) ct[v] = -100.0f;
    if (std::abs(u - 3.0) <= 2.0 && std::abs(w) <= 2.0) ct[v] = -850.0f;  // the air column
  }
  return ct;
}

TEST(BlockingFromCt, AirCutOnlyByTheTableAxisFacesIsInsideTheBody) {
  // The body and the column run along the table axis: the column touches only the two faces
  // across it (the field of view cuts the patient there), so it is inside the body: impassable.
  // Outside air touches the side faces and stays free.
  for (int axis = 0; axis < 3; ++axis) {
    const Volume<float> ct = cut_body_ct(axis, axis);
    const Volume<float> b = blocking_from_ct(ct, CtThresholds{}, MarginOptions{0.0});
    int64_t column = 0;
    for (int64_t v = 0; v < b.voxel_count(); ++v) {
      const float expected = ct[v] == -850.0f ? 100.0f : 0.0f;
      EXPECT_EQ(b[v], expected) << "axis " << axis << " offset " << v;
      column += ct[v] == -850.0f ? 1 : 0;
    }
    EXPECT_EQ(column,
              4 * 4 * 24);  // |u - 3| <= 2 and |w| <= 2 hold for 4 half-integer offsets each
  }
  // Across the table axis the same column touches side faces: it is outside air (free).
  const Volume<float> ct = cut_body_ct(0, 2);
  const Volume<float> b = blocking_from_ct(ct, CtThresholds{}, MarginOptions{0.0});
  for (int64_t v = 0; v < b.voxel_count(); ++v) EXPECT_EQ(b[v], 0.0f) << "offset " << v;
}

TEST(BlockingFromCt, NaNInTheCtIsAnError) {
  Volume<float> ct = synthetic_ct();
  ct(5, 6, 7) = std::numeric_limits<float>::quiet_NaN();
  expect_error_containing([&] { blocking_from_ct(ct, CtThresholds{}, MarginOptions{0.0}); },
                          {"(5, 6, 7)", "NaN"});
}

TEST(ValidateBlocking, RejectsNaNAndNegativeValuesNamingTheVoxel) {
  const ImageGeometry g = grid({4, 5, 6}, Eigen::Vector3d(1.0, 1.0, 1.0));
  Volume<float> b(g, 0.5f);
  EXPECT_NO_THROW(validate_blocking(b, "blocking.nii.gz"));

  b(1, 2, 3) = std::numeric_limits<float>::quiet_NaN();
  expect_error_containing([&] { validate_blocking(b, "blocking.nii.gz"); },
                          {"blocking.nii.gz", "(1, 2, 3)", "nan"});
  b(1, 2, 3) = 0.0f;
  b(3, 0, 5) = -0.25f;
  expect_error_containing([&] { validate_blocking(b, "blocking.nii.gz"); },
                          {"blocking.nii.gz", "(3, 0, 5)", "-0.25"});
  b(3, 0, 5) = std::numeric_limits<float>::infinity();
  expect_error_containing([&] { validate_blocking(b, "blocking.nii.gz"); },
                          {"blocking.nii.gz", "(3, 0, 5)", "inf"});
}

}  // namespace
}  // namespace crepuscular::planning
