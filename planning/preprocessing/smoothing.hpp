// The safety margin's Gaussian (DESIGN.md §5): ITK's discrete Gaussian (Lindeberg's kernel, the
// DiscreteGaussianImageFilter's own operators, variance in mm^2, zero-flux edges), applied as
// separable passes over the box where the input is non-zero, grown by the kernel. ITK's filter
// spends most of a plan's preprocessing in its neighbourhood iterators; this gives its values in a
// fraction of the time.
#pragma once

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

// ITK's DiscreteGaussianImageFilter itself: the reference the separable passes are tested against.
std::vector<float> discrete_gaussian_itk(const std::vector<float>& values, const ImageGeometry& g,
                                         const DiscreteGaussian& gaussian);

}  // namespace crepuscular::planning
