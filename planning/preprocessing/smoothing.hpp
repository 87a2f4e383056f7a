// The safety margin's Gaussian (docs/ARCHITECTURE.md §5): ITK's discrete Gaussian (Lindeberg's
// kernel, the DiscreteGaussianImageFilter's own operators, variance in mm^2, zero-flux edges),
// applied as separable passes over the box where the input is non-zero, grown by the kernel. ITK's
// filter spends most of a plan's preprocessing in its neighbourhood iterators; this gives its
// values in a fraction of the time.
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

struct DiscreteGaussian {
  double variance_mm2 = 1.0;
  double maximum_error = 1e-3;
  unsigned maximum_kernel_width = 32;
};

// The smoothed volume on the grid `g` (x fastest). Passes along z, y, then x, each summing its taps
// in double in ITK's order with float results between passes, as ITK does.
std::vector<float> discrete_gaussian(const std::vector<float>& values, const ImageGeometry& g,
                                     const DiscreteGaussian& gaussian);

// The same smoothing kept to the box where it is not zero (the input's non-zero voxels grown by
// the kernel's radius; empty when the input is all zero): values x fastest, `lo` its first voxel
// in the image, `dims` its size. `box` and `scratch` are reused from call to call, so smoothing
// several masks of one image allocates (and has the system clear) its memory once. on_gpu: the
// passes run on a CUDA device where this build has one and one is found (the same values, bit for
// bit: kernels/gaussian_cuda.hpp), else on the cores.
struct SmoothedBox {
  std::array<int64_t, 3> lo{}, dims{};
  std::vector<float> values;
  bool empty() const { return dims[0] == 0; }
  float at(int64_t i, int64_t j, int64_t k) const {  // image indices inside the box
    return values[size_t(((k - lo[2]) * dims[1] + (j - lo[1])) * dims[0] + (i - lo[0]))];
  }
};
void discrete_gaussian_box(const std::vector<float>& values, const ImageGeometry& g,
                           const DiscreteGaussian& gaussian, SmoothedBox& box,
                           std::vector<float>& scratch, bool on_gpu = false);

// The taps the passes use along each index axis of `g` (offsets -r..r, r = size / 2): the
// operators ITK's DiscreteGaussianImageFilter builds.
std::array<std::vector<double>, 3> discrete_gaussian_taps(const ImageGeometry& g,
                                                          const DiscreteGaussian& gaussian);

// ITK's DiscreteGaussianImageFilter itself: the reference the separable passes are tested against.
std::vector<float> discrete_gaussian_itk(const std::vector<float>& values, const ImageGeometry& g,
                                         const DiscreteGaussian& gaussian);

}  // namespace crepuscular::planning
