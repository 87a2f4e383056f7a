// The safety margin's Gaussian passes on the GPU against a host reference written from their
// definition, and the planner's smoothing on the GPU against its own on the cores: the same bits.
#include "kernels/gaussian_cuda.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <random>
#include <vector>

#include "kernels/path_safety_cuda.hpp"
#include "planning/preprocessing/blocking.hpp"
#include "planning/preprocessing/smoothing.hpp"
#include "planning/preprocessing/vulnerability.hpp"

namespace crepuscular::planning {
namespace {

// One pass of the definition: out(x) = sum over q in order of taps[q] in(clamp(x + q - r)), the
// input 0 outside the box, on a box of dims m at image voxel lo of an image of dims n.
std::vector<float> reference_pass(const std::vector<float>& in, const int64_t lo[3],
                                  const int64_t m[3], const int64_t n[3], int axis,
                                  const std::vector<double>& taps) {
  std::vector<float> out(in.size());
  const int64_t r = int64_t(taps.size() / 2);
  for (int64_t k = 0; k < m[2]; ++k)
    for (int64_t j = 0; j < m[1]; ++j)
      for (int64_t i = 0; i < m[0]; ++i) {
        int64_t c[3] = {i, j, k};
        double acc = 0.0;
        for (size_t q = 0; q < taps.size(); ++q) {
          int64_t x = c[axis] + lo[axis] + int64_t(q) - r;
          x = std::clamp<int64_t>(x, 0, n[axis] - 1) - lo[axis];
          if (x < 0 || x >= m[axis]) continue;
          int64_t d[3] = {i, j, k};
          d[axis] = x;
          acc += taps[q] * double(in[size_t((d[2] * m[1] + d[1]) * m[0] + d[0])]);
        }
        out[size_t((k * m[1] + j) * m[0] + i)] = float(acc);
      }
  return out;
}

TEST(GaussianCuda, PassesGiveTheDefinitionsBitsAtTheImagesEdge) {
  if (kernels::cuda_device_count() == 0) GTEST_SKIP() << "no CUDA device";
  // A box touching the image's low x and high z edges (zero flux there), inside it elsewhere.
  const int64_t n[3] = {40, 35, 30}, lo[3] = {0, 6, 11}, m[3] = {23, 17, 19};
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::vector<float> in(size_t(m[0] * m[1] * m[2]));
  for (float& v : in) v = u(rng) < 0.3f ? 0.0f : u(rng);
  std::vector<double> taps[3];
  for (int a = 0; a < 3; ++a) {
    const int r = 3 + 2 * a;  // different widths per axis catch swapped axes
    for (int q = -r; q <= r; ++q) taps[a].push_back(std::exp(-0.5 * q * q / (1.3 + a)) / 3.1);
  }
  std::vector<float> gpu(in.size(), -1.0f);
  ASSERT_TRUE(kernels::gaussian_box_cuda(in.data(), lo, m, n, taps, gpu.data()));
  const std::vector<float> host =
      reference_pass(reference_pass(reference_pass(in, lo, m, n, 2, taps[2]), lo, m, n, 1, taps[1]),
                     lo, m, n, 0, taps[0]);
  int64_t differ = 0;
  for (size_t v = 0; v < in.size(); ++v) differ += std::memcmp(&gpu[v], &host[v], 4) != 0;
  EXPECT_EQ(differ, 0);
  // Not a trivial smoothing: the edge voxels took values from the clamped taps.
  EXPECT_GT(host[0], 0.0f);
}

TEST(GaussianCuda, MarginSmoothedOnTheGpuIsTheCoresBits) {
  if (kernels::cuda_device_count() == 0) GTEST_SKIP() << "no CUDA device";
  ImageGeometry g;
  g.dims = {64, 52, 37};
  g.spacing = Eigen::Vector3d(0.7, 0.8, 2.5);  // thick slices: a kernel below a voxel along z
  std::vector<float> mask(size_t(g.voxel_count()), 0.0f);
  for (int64_t k = 0; k < 37; ++k)
    for (int64_t j = 0; j < 52; ++j)
      for (int64_t i = 0; i < 64; ++i) {
        const double x = (i - 20) * 0.7, y = (j - 30) * 0.8, z = (k - 30) * 2.5;
        if (x * x + y * y + z * z < 300.0 || (i > 55 && j < 5)) mask[size_t((k * 52 + j) * 64 + i)] = 1.0f;
      }
  DiscreteGaussian gaussian;
  gaussian.variance_mm2 = 4.5;
  SmoothedBox cores, gpu;
  std::vector<float> scratch;
  discrete_gaussian_box(mask, g, gaussian, cores, scratch, false);
  discrete_gaussian_box(mask, g, gaussian, gpu, scratch, true);
  ASSERT_FALSE(cores.empty());
  EXPECT_EQ(gpu.lo, cores.lo);
  EXPECT_EQ(gpu.dims, cores.dims);
  ASSERT_EQ(gpu.values.size(), cores.values.size());
  int64_t differ = 0;
  for (size_t v = 0; v < gpu.values.size(); ++v) {
    differ += std::memcmp(&gpu.values[v], &cores.values[v], 4) != 0;
  }
  EXPECT_EQ(differ, 0);
}

// The whole blocking volume made on the GPU (blocking_levels_cuda) against the cores' level by
// level: every label of the phantom's table, structures cut by the image's edges, thick slices,
// labels of a free level (coefficient 0); with and without a margin.
TEST(GaussianCuda, BlockingVolumeOnTheGpuIsTheCoresBits) {
  if (kernels::cuda_device_count() == 0) GTEST_SKIP() << "no CUDA device";
  const VulnerabilityTable table = VulnerabilityTable::preset("phantom");
  ImageGeometry g;
  g.dims = {71, 58, 33};
  g.spacing = Eigen::Vector3d(0.8, 0.7, 2.0);
  g.origin = Eigen::Vector3d(-20.0, 13.0, 4.0);
  Volume<int32_t> labels(g, 0);
  std::mt19937 rng(11);
  std::uniform_int_distribution<int> label(1, 12);
  // Balls of random labels, some reaching past the image's faces.
  std::uniform_real_distribution<double> x(-5.0, 75.0), y(-5.0, 62.0), z(-3.0, 36.0), r(2.0, 9.0);
  for (int ball = 0; ball < 40; ++ball) {
    const double cx = x(rng), cy = y(rng), cz = z(rng), rr = r(rng);
    const int value = label(rng);
    for (int64_t k = 0; k < g.dims[2]; ++k)
      for (int64_t j = 0; j < g.dims[1]; ++j)
        for (int64_t i = 0; i < g.dims[0]; ++i) {
          const double dx = (i - cx) * 0.8, dy = (j - cy) * 0.7, dz = (k - cz) * 2.0;
          if (dx * dx + dy * dy + dz * dz < rr * rr) labels(i, j, k) = value;
        }
  }
  for (const double fwhm : {5.0, 0.0}) {
    MarginOptions cores, gpu;
    cores.fwhm_mm = gpu.fwhm_mm = fwhm;
    gpu.on_gpu = true;
    const Volume<float> on_cores = blocking_from_labels(labels, table, cores, "labels");
    const Volume<float> on_gpu = blocking_from_labels(labels, table, gpu, "labels");
    ASSERT_EQ(on_gpu.values().size(), on_cores.values().size());
    int64_t differ = 0, blocked = 0, between = 0;
    for (size_t v = 0; v < on_gpu.values().size(); ++v) {
      differ += std::memcmp(&on_gpu.values()[v], &on_cores.values()[v], 4) != 0;
      blocked += on_cores.values()[v] > 0.0f;
      between += on_cores.values()[v] > 0.0f && on_cores.values()[v] < 0.02f;
    }
    EXPECT_EQ(differ, 0) << "FWHM " << fwhm << " mm";
    // Not a trivial volume: a tenth of it blocks, and with a margin the edges fade.
    EXPECT_GT(blocked, int64_t(on_cores.values().size() / 10)) << "FWHM " << fwhm << " mm";
    if (fwhm > 0.0) {
      EXPECT_GT(between, 100);
    }
  }
}

}  // namespace
}  // namespace crepuscular::planning
