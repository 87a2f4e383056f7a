#include "planning/preprocessing/smoothing.hpp"
#include "planning/imaging/itk_image.hpp"

#include <algorithm>
#include <array>
#include <cstdint>
#include <string>

#include "foundation/error.hpp"

#if defined(CREPUSCULAR_HAVE_CUDA)
#include "kernels/gaussian_cuda.hpp"
#endif

// ITK headers after ours (see volume_io.cpp): keep one Eigen (the system one) in this unit.
#ifndef ITK_USE_SYSTEM_EIGEN
#define ITK_USE_SYSTEM_EIGEN
#endif
#include <itkDiscreteGaussianImageFilter.h>
#include <itkGaussianOperator.h>
#include <itkImage.h>

namespace crepuscular::planning {
namespace {

using FloatImage = itk::Image<float, 3>;

// The taps along axis a, offsets -r..r: the operator DiscreteGaussianImageFilter builds.
std::vector<double> taps_along(int a, const ImageGeometry& g, const DiscreteGaussian& gaussian) {
  itk::GaussianOperator<double, 3> op;
  op.SetDirection(unsigned(a));
  op.SetVariance(gaussian.variance_mm2 / (g.spacing[a] * g.spacing[a]));
  op.SetMaximumKernelWidth(gaussian.maximum_kernel_width);
  op.SetMaximumError(gaussian.maximum_error);
  op.CreateDirectional();
  std::vector<double> taps(op.Size());
  for (size_t i = 0; i < taps.size(); ++i) taps[i] = op.GetElement(i);
  return taps;
}

}  // namespace

std::array<std::vector<double>, 3> discrete_gaussian_taps(const ImageGeometry& g,
                                                          const DiscreteGaussian& gaussian) {
  std::array<std::vector<double>, 3> taps;
  for (int a = 0; a < 3; ++a) taps[size_t(a)] = taps_along(a, g, gaussian);
  return taps;
}

std::vector<float> discrete_gaussian(const std::vector<float>& values, const ImageGeometry& g,
                                     const DiscreteGaussian& gaussian) {
  SmoothedBox box;
  std::vector<float> scratch;
  discrete_gaussian_box(values, g, gaussian, box, scratch);
  std::vector<float> out(values.size(), 0.0f);
  if (box.empty()) return out;
  const int64_t nx = g.dims[0], ny = g.dims[1];
  for (int64_t k = box.lo[2]; k < box.lo[2] + box.dims[2]; ++k)
    for (int64_t j = box.lo[1]; j < box.lo[1] + box.dims[1]; ++j)
      std::copy_n(&box.values[size_t(((k - box.lo[2]) * box.dims[1] + (j - box.lo[1])) *
                                     box.dims[0])],
                  box.dims[0], out.data() + (k * ny + j) * nx + box.lo[0]);
  return out;
}

void discrete_gaussian_box(const std::vector<float>& values, const ImageGeometry& g,
                           const DiscreteGaussian& gaussian, SmoothedBox& result,
                           std::vector<float>& scratch, bool on_gpu) {
  const std::array<int64_t, 3> n = {g.dims[0], g.dims[1], g.dims[2]};
  result.lo = {0, 0, 0};
  result.dims = {0, 0, 0};
  // The box of non-zero input.
  std::array<int64_t, 3> lo = n, hi = {-1, -1, -1};
#pragma omp parallel
  {
    std::array<int64_t, 3> l = n, h = {-1, -1, -1};
#pragma omp for schedule(static) nowait
    for (int64_t k = 0; k < n[2]; ++k)
      for (int64_t j = 0; j < n[1]; ++j) {
        const float* row = values.data() + (k * n[1] + j) * n[0];
        for (int64_t i = 0; i < n[0]; ++i) {
          if (row[i] == 0.0f) continue;
          l = {std::min(l[0], i), std::min(l[1], j), std::min(l[2], k)};
          h = {std::max(h[0], i), std::max(h[1], j), std::max(h[2], k)};
        }
      }
#pragma omp critical
    for (int a = 0; a < 3; ++a) {
      lo[size_t(a)] = std::min(lo[size_t(a)], l[size_t(a)]);
      hi[size_t(a)] = std::max(hi[size_t(a)], h[size_t(a)]);
    }
  }
  if (hi[0] < 0) return;  // all zero: so is its smoothing

  // Grown by each axis' kernel radius: outside this box every pass's values are exactly zero.
  const std::array<std::vector<double>, 3> taps = discrete_gaussian_taps(g, gaussian);
  std::array<int64_t, 3> b0{}, b1{}, m{};
  for (int a = 0; a < 3; ++a) {
    const int64_t r = int64_t(taps[size_t(a)].size() / 2);
    b0[size_t(a)] = std::max<int64_t>(0, lo[size_t(a)] - r);
    b1[size_t(a)] = std::min<int64_t>(n[size_t(a)] - 1, hi[size_t(a)] + r);
    m[size_t(a)] = b1[size_t(a)] - b0[size_t(a)] + 1;
  }
  const auto box = [&](int64_t i, int64_t j, int64_t k) {
    return size_t(((k - b0[2]) * m[1] + (j - b0[1])) * m[0] + (i - b0[0]));
  };
  // Reused buffers: resize() keeps their memory (no fresh pages) and never shrinks it.
  std::vector<float>& a = scratch;
  std::vector<float>& b = result.values;
  a.resize(size_t(m[0] * m[1] * m[2]));
  b.resize(a.size());
#pragma omp parallel for collapse(2) schedule(static)
  for (int64_t k = b0[2]; k <= b1[2]; ++k)
    for (int64_t j = b0[1]; j <= b1[1]; ++j)
      std::copy_n(values.data() + (k * n[1] + j) * n[0] + b0[0], m[0], &a[box(b0[0], j, k)]);
#if defined(CREPUSCULAR_HAVE_CUDA)
  if (on_gpu && kernels::gaussian_box_cuda(a.data(), b0.data(), m.data(), n.data(), taps.data(),
                                           b.data())) {
    result.lo = b0;
    result.dims = m;
    return;
  }
#else
  (void)on_gpu;
#endif

  // One pass along `axis`: out(x) = sum_t taps[t] in(clamp(x + t - r)), in() zero outside the
  // box (and clamped to the image's edge: zero flux), accumulated in double over t in order.
  const auto pass = [&](int axis, const std::vector<float>& in, std::vector<float>& to) {
    const std::vector<double>& t = taps[size_t(axis)];
    const int64_t r = int64_t(t.size() / 2);
#pragma omp parallel
    {
      std::vector<double> acc(static_cast<size_t>(m[0]));
      std::vector<float> padded(static_cast<size_t>(m[0] + 2 * r));
      // Rows in the order that keeps a pass's window of input rows in cache: along z, each
      // thread walks k for one j after another, so that the next output row reads one new input
      // row (k walking within a j would read 2r + 1 rows from other planes for every output row:
      // the pass read the volume 2r + 1 times from memory). Same values, same bits.
      const int64_t rows = m[1] * m[2];
#pragma omp for schedule(static)
      for (int64_t line = 0; line < rows; ++line) {
        const int64_t j = axis == 2 ? b0[1] + line / m[2] : b0[1] + line % m[1];
        const int64_t k = axis == 2 ? b0[2] + line % m[2] : b0[2] + line / m[1];
        {
          std::fill(acc.begin(), acc.end(), 0.0);
          if (axis == 0) {
            // The row padded by r on each side with what the taps read there.
            for (int64_t p = 0; p < m[0] + 2 * r; ++p) {
              const int64_t x = std::clamp<int64_t>(b0[0] - r + p, 0, n[0] - 1);
              padded[size_t(p)] = x >= b0[0] && x <= b1[0] ? in[box(x, j, k)] : 0.0f;
            }
            // Tap by tap across the row (each output still sums its taps in order, so the
            // values are the same bits): the loop over i vectorizes, where a dot product per
            // output waited on each addition.
            for (size_t q = 0; q < t.size(); ++q) {
              const double w = t[q];
              const float* src = padded.data() + q;
              for (int64_t i = 0; i < m[0]; ++i) acc[size_t(i)] += w * double(src[i]);
            }
          } else {
            const int64_t c = axis == 1 ? j : k;
            for (size_t q = 0; q < t.size(); ++q) {
              const int64_t x = std::clamp<int64_t>(c + int64_t(q) - r, 0, n[size_t(axis)] - 1);
              if (x < b0[size_t(axis)] || x > b1[size_t(axis)]) continue;  // zero there
              const double w = t[q];
              const float* row = axis == 1 ? &in[box(b0[0], x, k)] : &in[box(b0[0], j, x)];
              for (int64_t i = 0; i < m[0]; ++i) acc[size_t(i)] += w * double(row[i]);
            }
          }
          float* dst = &to[box(b0[0], j, k)];
          for (int64_t i = 0; i < m[0]; ++i) dst[i] = float(acc[size_t(i)]);
        }
      }
    }
  };
  // ITK's order: z, then y, then x.
  pass(2, a, b);
  pass(1, b, a);
  pass(0, a, b);
  result.lo = b0;
  result.dims = m;
}

std::vector<float> discrete_gaussian_itk(const std::vector<float>& values, const ImageGeometry& g,
                                         const DiscreteGaussian& gaussian) {
  auto image = FloatImage::New();
  set_image_geometry(*image, g);
  image->Allocate();
  std::copy(values.begin(), values.end(), image->GetBufferPointer());
  using Gaussian = itk::DiscreteGaussianImageFilter<FloatImage, FloatImage>;
  auto filter = Gaussian::New();
  filter->SetInput(image);
  filter->SetUseImageSpacing(true);
  filter->SetVariance(gaussian.variance_mm2);
  filter->SetMaximumError(gaussian.maximum_error);
  filter->SetMaximumKernelWidth(gaussian.maximum_kernel_width);
  try {
    filter->Update();
  } catch (const itk::ExceptionObject& e) {
    throw Error(std::string("Gaussian smoothing failed: ") + e.GetDescription());
  }
  const float* p = filter->GetOutput()->GetBufferPointer();
  return std::vector<float>(p, p + values.size());
}

}  // namespace crepuscular::planning
