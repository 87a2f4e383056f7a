// The host/device sampling helpers of the path safety math, against analytic values.
#include "kernels/path_safety_math.hpp"

#include "kernels/launch_order.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

namespace crepuscular::kernels {
namespace {

Affine<double> identity_affine() {
  Affine<double> a{};
  a.m[0][0] = a.m[1][1] = a.m[2][2] = 1.0;
  return a;
}

TEST(Sampling, TrilinearReproducesLinearFunctionsInside) {
  // Trilinear interpolation is exact for f = a + b x + c y + d z + e x y z-free linear fields.
  const int n = 6;
  std::vector<float> v(n * n * n);
  const auto f = [](double x, double y, double z) { return 1.0 + 0.5 * x - 0.25 * y + 2.0 * z; };
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) v[size_t((k * n + j) * n + i)] = float(f(i, j, k));
  BlockingGrid<double> g{v.data(), n, n, n, identity_affine(), nullptr, 0, 0, 0};
  for (double x : {0.0, 0.3, 2.71, 4.99})
    for (double y : {0.0, 1.5, 4.2})
      for (double z : {0.1, 3.3, 4.999})
        EXPECT_NEAR(sample_blocking(g, Vec3<double>{x, y, z}), f(x, y, z), 1e-5);
}

TEST(Sampling, OutsideTheGridBlendsToZero) {
  // Zero padding: at index -0.5 the value is half of voxel 0; at -1 and beyond it is 0.
  const int n = 4;
  std::vector<float> v(n * n * n, 3.0f);
  BlockingGrid<double> g{v.data(), n, n, n, identity_affine(), nullptr, 0, 0, 0};
  EXPECT_NEAR(sample_blocking(g, Vec3<double>{-0.5, 1.0, 1.0}), 1.5, 1e-6);
  EXPECT_NEAR(sample_blocking(g, Vec3<double>{1.0, 3.25, 1.0}), 2.25, 1e-6);
  EXPECT_EQ(sample_blocking(g, Vec3<double>{-1.0, 1.0, 1.0}), 0.0);
  EXPECT_EQ(sample_blocking(g, Vec3<double>{1.0, 1.0, 7.0}), 0.0);
  EXPECT_EQ(sample_blocking(g, Vec3<double>{-100.0, 1.0, 1.0}), 0.0);
}

TEST(Sampling, TumorLookupRoundsToNearestVoxel) {
  const int n = 5;
  std::vector<uint8_t> m(n * n * n, 0);
  m[size_t((2 * n + 2) * n + 3)] = 1;  // voxel (3, 2, 2)
  TumorGrid<double> g{m.data(), n, n, n, identity_affine(), {3, 2, 2}, {3, 2, 2}};
  EXPECT_EQ(tumor_offset_at(g, Vec3<double>{3.4, 2.0, 1.6}), (2 * n + 2) * n + 3);
  EXPECT_EQ(tumor_offset_at(g, Vec3<double>{3.6, 2.0, 2.0}), -1);
  EXPECT_EQ(tumor_offset_at(g, Vec3<double>{2.6, 2.4, 2.4}), (2 * n + 2) * n + 3);
  EXPECT_EQ(tumor_offset_at(g, Vec3<double>{-3.0, 2.0, 2.0}), -1);
}

TEST(Sampling, BoxRangeCoversTheBoxWithOneVoxelMargin) {
  const int lo[3] = {2, 2, 2}, hi[3] = {4, 4, 4};
  double k_in, k_out;
  box_range(Vec3<double>{3, 3, -10}, Vec3<double>{0, 0, 0.5}, lo, hi, k_in, k_out);
  EXPECT_NEAR(k_in, (1.0 + 10.0) / 0.5, 1e-12);   // enters at z = lo - 1 = 1
  EXPECT_NEAR(k_out, (5.0 + 10.0) / 0.5, 1e-12);  // leaves at z = hi + 1 = 5
  box_range(Vec3<double>{10, 3, -10}, Vec3<double>{0, 0, 0.5}, lo, hi, k_in, k_out);
  EXPECT_GT(k_in, k_out);  // misses the box
}

// The launch order of fast mode's point blocks (launch_order.hpp) against work summed point by
// point here: every block once, in the order of decreasing work, ties in their own order.
TEST(LaunchOrder, BlocksStartLongestFirstEachOnce) {
  const double origin[3] = {-10.0, 5.0, 2.0};
  const double axes[3][3] = {{0.7, 0.0, 0.0}, {0.0, 0.0, -0.7}, {0.0, 0.7, 0.0}};  // permuted
  const double centre[3] = {-3.0, 1.0, 9.0};
  const double reach = 10.0;
  std::mt19937 rng(7);
  std::uniform_int_distribution<int> index(-20, 200);
  const int block = 4;
  const int64_t count = 4 * 50 + 3;  // a short last block
  std::vector<int32_t> ijk(size_t(3 * count));
  for (int32_t& v : ijk) v = index(rng);
  // Two blocks of the same points: a tie, kept in order.
  std::copy(ijk.begin(), ijk.begin() + 3 * block, ijk.begin() + 3 * 7 * block);
  const std::vector<int32_t> order =
      blocks_longest_first(ijk.data(), count, block, origin, axes, centre, reach);
  ASSERT_EQ(order.size(), 51u);
  std::vector<double> work(51, 0.0);
  for (int64_t p = 0; p < count; ++p) {
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a) {
      double x = origin[a] - centre[a];
      for (int e = 0; e < 3; ++e) x += ijk[size_t(3 * p + e)] * axes[e][a];
      d2 += x * x;
    }
    work[size_t(p / block)] += std::sqrt(d2) + reach;
  }
  std::vector<int32_t> sorted = order;
  std::sort(sorted.begin(), sorted.end());
  for (int b = 0; b < 51; ++b) EXPECT_EQ(sorted[size_t(b)], b);
  for (size_t at = 1; at < order.size(); ++at) {
    EXPECT_GE(work[size_t(order[at - 1])], work[size_t(order[at])] - 1e-9) << at;
  }
  // The short last block (3 points) has less work than full blocks near it, and the tie stays in
  // order: block 0 before block 7.
  const auto pos = [&order](int b) { return std::find(order.begin(), order.end(), b) - order.begin(); };
  EXPECT_LT(pos(0), pos(7));
  EXPECT_NEAR(work[0], work[7], 1e-9);
  // A far block starts before a near one.
  // Block 0 at the grid's origin (10.7 mm from the centre), block 1 at (-3, 0.8, 9) mm (0.2 mm).
  std::vector<int32_t> two = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
  std::vector<int32_t> near = {10, -10, -6, 10, -10, -6, 10, -10, -6, 10, -10, -6};
  two.insert(two.end(), near.begin(), near.end());
  const std::vector<int32_t> o2 =
      blocks_longest_first(two.data(), 8, block, origin, axes, centre, reach);
  ASSERT_EQ(o2.size(), 2u);
  EXPECT_EQ(o2[0], 0);
  EXPECT_EQ(o2[1], 1);
  std::swap_ranges(two.begin(), two.begin() + 12, two.begin() + 12);  // now block 0 is the near one
  EXPECT_EQ(blocks_longest_first(two.data(), 8, block, origin, axes, centre, reach),
            (std::vector<int32_t>{1, 0}));
}

}  // namespace
}  // namespace crepuscular::kernels
