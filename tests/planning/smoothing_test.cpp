// The safety margin's separable discrete Gaussian (planning/preprocessing/smoothing.hpp) against
// ITK's DiscreteGaussianImageFilter on the same grid: small structures inside the volume, one
// touching the volume's edges (zero flux there), anisotropic spacing, and an empty input.
#include "planning/preprocessing/smoothing.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <tuple>
#include <vector>

namespace crepuscular::planning {
namespace {

ImageGeometry grid(int nx, int ny, int nz, double sx, double sy, double sz) {
  ImageGeometry g;
  g.dims = {nx, ny, nz};
  g.spacing = {sx, sy, sz};
  g.origin = {-10.0, 4.0, 2.5};
  return g;
}

// Largest absolute difference, and the number of voxels where ITK's result is above 1e-4.
double max_difference(const std::vector<float>& a, const std::vector<float>& b, int64_t& support) {
  double worst = 0.0;
  support = 0;
  for (size_t v = 0; v < a.size(); ++v) {
    worst = std::max(worst, std::abs(double(a[v]) - double(b[v])));
    support += b[v] > 1e-4f ? 1 : 0;
  }
  return worst;
}

std::vector<float> random_blobs(const ImageGeometry& g, int blobs, bool at_edges, unsigned seed) {
  std::vector<float> v(size_t(g.voxel_count()), 0.0f);
  std::mt19937 rng(seed);
  for (int b = 0; b < blobs; ++b) {
    std::uniform_int_distribution<int64_t> x(at_edges ? 0 : 8, g.dims[0] - (at_edges ? 3 : 11));
    std::uniform_int_distribution<int64_t> y(at_edges ? 0 : 8, g.dims[1] - (at_edges ? 3 : 11));
    std::uniform_int_distribution<int64_t> z(at_edges ? 0 : 8, g.dims[2] - (at_edges ? 3 : 11));
    const int64_t i0 = x(rng), j0 = y(rng), k0 = z(rng);
    for (int64_t k = k0; k < k0 + 3; ++k)
      for (int64_t j = j0; j < j0 + 3; ++j)
        for (int64_t i = i0; i < i0 + 3; ++i) v[size_t(g.offset(i, j, k))] = 1.0f;
  }
  return v;
}

TEST(DiscreteGaussian, EqualsItksFilterInsideTheVolume) {
  const ImageGeometry g = grid(48, 40, 36, 1.0, 1.0, 1.0);
  DiscreteGaussian gaussian;
  gaussian.variance_mm2 = 2.12 * 2.12;  // the 5 mm FWHM margin
  const std::vector<float> in = random_blobs(g, 3, false, 7);
  int64_t support = 0;
  const double worst = max_difference(discrete_gaussian(in, g, gaussian),
                                      discrete_gaussian_itk(in, g, gaussian), support);
  EXPECT_LT(worst, 1e-6);
  EXPECT_GT(support, 2000);  // the kernel spread the blobs: the comparison covers them
}

TEST(DiscreteGaussian, EqualsItksFilterAtTheVolumesEdgesWithAnisotropicSpacing) {
  // Thick slices (sigma below a voxel along z) and structures on the faces: zero-flux edges.
  const ImageGeometry g = grid(40, 44, 20, 0.7, 0.8, 3.0);
  DiscreteGaussian gaussian;
  gaussian.variance_mm2 = 2.12 * 2.12;
  gaussian.maximum_kernel_width = 64;
  const std::vector<float> in = random_blobs(g, 12, true, 11);
  int64_t support = 0;
  const std::vector<float> ours = discrete_gaussian(in, g, gaussian);
  const std::vector<float> itk = discrete_gaussian_itk(in, g, gaussian);
  EXPECT_LT(max_difference(ours, itk, support), 1e-6);
  EXPECT_GT(support, 2000);
  // A blob on the edge keeps its mass inside (zero flux): the sums agree too.
  double a = 0.0, b = 0.0;
  for (size_t v = 0; v < in.size(); ++v) {
    a += ours[v];
    b += itk[v];
  }
  EXPECT_NEAR(a, b, 1e-6 * b);
}

TEST(DiscreteGaussian, NothingGivesNothing) {
  const ImageGeometry g = grid(16, 16, 16, 1.0, 1.0, 1.0);
  const std::vector<float> zeros(size_t(g.voxel_count()), 0.0f);
  const std::vector<float> out = discrete_gaussian(zeros, g, DiscreteGaussian{});
  EXPECT_TRUE(std::all_of(out.begin(), out.end(), [](float v) { return v == 0.0f; }));
}

// The box form with buffers reused from a larger input before it (as the blocking levels reuse
// them): inside its box it equals the full smoothing bit for bit, outside the box the full
// smoothing is zero, and an all-zero input after them gives an empty box.
TEST(DiscreteGaussian, BoxWithReusedBuffersEqualsTheFullSmoothing) {
  const ImageGeometry g = grid(40, 36, 30, 0.8, 0.8, 1.5);
  DiscreteGaussian gaussian;
  gaussian.variance_mm2 = 4.0;
  SmoothedBox box;
  std::vector<float> scratch;
  for (const auto& [blobs, edges, seed] :
       {std::make_tuple(12, true, 3u), std::make_tuple(1, false, 4u), std::make_tuple(3, false, 5u)}) {
    const std::vector<float> in = random_blobs(g, blobs, edges, seed);
    const std::vector<float> full = discrete_gaussian(in, g, gaussian);
    discrete_gaussian_box(in, g, gaussian, box, scratch);
    ASSERT_FALSE(box.empty());
    int64_t inside = 0, outside_nonzero = 0, differ = 0;
    for (int64_t k = 0; k < g.dims[2]; ++k)
      for (int64_t j = 0; j < g.dims[1]; ++j)
        for (int64_t i = 0; i < g.dims[0]; ++i) {
          const float f = full[size_t(g.offset(i, j, k))];
          const bool in_box = i >= box.lo[0] && i < box.lo[0] + box.dims[0] && j >= box.lo[1] &&
                              j < box.lo[1] + box.dims[1] && k >= box.lo[2] &&
                              k < box.lo[2] + box.dims[2];
          if (!in_box) {
            outside_nonzero += f != 0.0f;
            continue;
          }
          ++inside;
          differ += box.at(i, j, k) != f;
        }
    EXPECT_EQ(differ, 0) << blobs << " blobs";
    EXPECT_EQ(outside_nonzero, 0) << blobs << " blobs";
    EXPECT_GT(inside, 0);
    if (blobs == 1) {
      EXPECT_LT(inside, g.voxel_count() / 2);  // a small box, not the image
    }
  }
  discrete_gaussian_box(std::vector<float>(size_t(g.voxel_count()), 0.0f), g, gaussian, box,
                        scratch);
  EXPECT_TRUE(box.empty());
}

}  // namespace
}  // namespace crepuscular::planning
