// Preprocessing (§3.1, docs/ARCHITECTURE.md §5): the blocking volume b (risk per mm) from a
// label map and a vulnerability table, or from CT thresholds, with the Gaussian safety margin.
#include "planning/preprocessing/blocking.hpp"
#include "planning/imaging/itk_image.hpp"
#include "planning/preprocessing/smoothing.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <set>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/large_buffers.hpp"
#include "foundation/log.hpp"

#if defined(CREPUSCULAR_HAVE_CUDA)
#include "kernels/gaussian_cuda.hpp"
#include "kernels/path_safety_cuda.hpp"
#endif

// ITK headers after ours (see volume_io.cpp): keep one Eigen (the system one) in this unit.
#ifndef ITK_USE_SYSTEM_EIGEN
#define ITK_USE_SYSTEM_EIGEN
#endif
#include <itkImage.h>

namespace crepuscular::planning {

namespace {

using FloatImage = itk::Image<float, 3>;
using MaskImage = itk::Image<uint8_t, 3>;

constexpr int kMaxLabelValue = 65535;  // vulnerability tables hold values 1..65535

// sigma = FWHM / (2 sqrt(2 ln 2)).
double sigma_of_fwhm(double fwhm_mm) { return fwhm_mm / (2.0 * std::sqrt(2.0 * std::log(2.0))); }

void check_margin(const MarginOptions& margin) {
  if (!std::isfinite(margin.fwhm_mm) || margin.fwhm_mm < 0.0) {
    std::ostringstream m;
    m << "safety margin: FWHM is " << margin.fwhm_mm << " mm (expected a finite value >= 0)";
    throw Error(m.str());
  }
}

// An empty ITK image with the grid of `g` (same origin, spacing, direction; LPS as ITK).
template <typename Image>
typename Image::Pointer make_image(const ImageGeometry& g) {
  auto image = Image::New();
  set_image_geometry(*image, g);
  image->Allocate();
  return image;
}

// The safety margin's Gaussian of full width at half maximum `fwhm_mm` on the grid `g`. ITK's
// discrete Gaussian (Lindeberg's Bessel kernel) rather than a recursive one: it never goes
// negative nor overshoots 1, keeps the exact variance when sigma is below a voxel (thick slices),
// and has no minimum image size. MaximumError, not MaximumKernelWidth, sets the kernel size.
// Applied by separable passes over the structure's box (smoothing.hpp): ITK's values.
DiscreteGaussian margin_gaussian(const ImageGeometry& g, double fwhm_mm) {
  const double sigma_mm = sigma_of_fwhm(fwhm_mm);
  double max_sigma_voxels = 0.0;
  for (int a = 0; a < 3; ++a)
    max_sigma_voxels = std::max(max_sigma_voxels, sigma_mm / g.spacing[a]);
  const unsigned max_width = unsigned(2.0 * std::ceil(6.0 * max_sigma_voxels) + 3.0);
  DiscreteGaussian gaussian;
  gaussian.variance_mm2 = sigma_mm * sigma_mm;
  gaussian.maximum_error = 1e-3;
  gaussian.maximum_kernel_width = std::max(32u, max_width);
  return gaussian;
}

// b = max(b, coeff * max(mask, G_sigma * mask)) with mask(v) = in_mask(v) (0 or 1) on the grid `g`
// (§3.1: the safety margin never lowers a structure). G is in physical units (mm), so anisotropic
// spacing gets the same profile in mm. The volume is extended by its border values (zero flux), so
// a structure cut by the field of view is smoothed as if it went on.
// Buffers of add_level kept from one level to the next (a level's mask and smoothing are a
// volume each: fresh memory for every level would have the system clear gigabytes).
struct LevelBuffers {
  std::vector<float> mask, scratch;
  SmoothedBox smoothed;
};

template <typename InMask>
void add_level(std::vector<float>& b, const ImageGeometry& g, double coeff,
               const MarginOptions& margin, InMask in_mask, LevelBuffers& buffers) {
  const double fwhm_mm = margin.fwhm_mm;
  const int64_t n = g.voxel_count();
  std::vector<float>& mask = buffers.mask;
  mask.resize(static_cast<size_t>(n));
  float* m = mask.data();
#pragma omp parallel for schedule(static)
  for (int64_t v = 0; v < n; ++v) m[v] = in_mask(v) ? 1.0f : 0.0f;

  const float c = float(coeff);
  if (fwhm_mm <= 0.0) {
#pragma omp parallel for schedule(static)
    for (int64_t v = 0; v < n; ++v) b[size_t(v)] = std::max(b[size_t(v)], c * m[v]);
    return;
  }

  SmoothedBox& smoothed = buffers.smoothed;
  discrete_gaussian_box(mask, g, margin_gaussian(g, fwhm_mm), smoothed, buffers.scratch,
                        margin.on_gpu);
  // Outside the smoothed box the smoothing is 0 (and so is the mask).
  if (smoothed.empty()) return;
  const int64_t nx = g.dims[0], ny = g.dims[1];
#pragma omp parallel for collapse(2) schedule(static)
  for (int64_t k = smoothed.lo[2]; k < smoothed.lo[2] + smoothed.dims[2]; ++k) {
    for (int64_t j = smoothed.lo[1]; j < smoothed.lo[1] + smoothed.dims[1]; ++j) {
      for (int64_t i = smoothed.lo[0]; i < smoothed.lo[0] + smoothed.dims[0]; ++i) {
        const int64_t v = (k * ny + j) * nx + i;
        b[size_t(v)] = std::max(b[size_t(v)], c * std::max(m[v], smoothed.at(i, j, k)));
      }
    }
  }
}

// Distinct label values present in the map, sorted (one fast pass).
std::vector<int32_t> distinct_labels(const Volume<int32_t>& labels) {
  std::vector<uint8_t> seen(size_t(kMaxLabelValue) + 1, 0);
  std::set<int32_t> others;  // outside 0..65535: never in a table, reported as unknown
  const int32_t* p = labels.data();
  const int64_t n = labels.voxel_count();
#pragma omp parallel
  {
    std::vector<uint8_t> mine(seen.size(), 0);
    std::set<int32_t> mine_others;
#pragma omp for schedule(static) nowait
    for (int64_t v = 0; v < n; ++v) {
      const int32_t x = p[v];
      if (x >= 0 && x <= kMaxLabelValue) {
        mine[size_t(x)] = 1;
      } else {
        mine_others.insert(x);
      }
    }
#pragma omp critical
    {
      for (size_t x = 0; x < seen.size(); ++x) seen[x] |= mine[x];
      others.insert(mine_others.begin(), mine_others.end());
    }
  }
  std::vector<int32_t> out(others.begin(), others.end());
  for (int32_t x = 0; x <= kMaxLabelValue; ++x) {
    if (seen[size_t(x)]) out.push_back(x);
  }
  std::sort(out.begin(), out.end());
  return out;
}

// Throws Error unless the CT thresholds are finite, air below bone, and the risk positive.
void check_ct_thresholds(const CtThresholds& thresholds) {
  if (!std::isfinite(thresholds.bone_hu) || !std::isfinite(thresholds.air_hu) ||
      thresholds.air_hu >= thresholds.bone_hu) {
    std::ostringstream m;
    m << "CT thresholds: air " << thresholds.air_hu << " HU, bone " << thresholds.bone_hu
      << " HU (expected finite, air below bone)";
    throw Error(m.str());
  }
  if (!std::isfinite(thresholds.impassable_per_mm) || thresholds.impassable_per_mm <= 0.0) {
    std::ostringstream m;
    m << "CT thresholds: impassable_per_mm is " << thresholds.impassable_per_mm
      << " (expected a finite value > 0)";
    throw Error(m.str());
  }
}

struct AirMask {
  MaskImage::Pointer image;  // 1 where HU <= the air threshold
  int64_t voxels = 0;
};

// The air mask of the CT; a NaN is bad input, not tissue: Error naming the voxel.
AirMask air_mask(const Volume<float>& ct_hu, double air_hu, const std::string& source) {
  const ImageGeometry& g = ct_hu.geometry();
  const int64_t n = ct_hu.voxel_count();
  const float* hu = ct_hu.data();
  AirMask air;
  air.image = make_image<MaskImage>(g);
  uint8_t* air_p = air.image->GetBufferPointer();
  for (int64_t v = 0; v < n; ++v) {
    if (std::isnan(hu[v])) {
      const Index3 ijk = g.index_of_offset(v);
      std::ostringstream m;
      m << source << ": voxel (" << ijk[0] << ", " << ijk[1] << ", " << ijk[2]
        << ") is NaN (expected Hounsfield units)";
      throw Error(m.str());
    }
    air_p[v] = hu[v] <= air_hu ? 1 : 0;
    air.voxels += air_p[v];
  }
  return air;
}

// Which of the `count` components (labels 1..count in `comp`) touch a side face of the grid: the
// faces parallel to the table (cranio-caudal) axis, the index axis closest to LPS S.
std::vector<uint8_t> components_on_side_faces(const uint32_t* comp, size_t count,
                                              const ImageGeometry& g) {
  int table_axis = 0;
  for (int a = 1; a < 3; ++a) {
    if (std::abs(g.direction(2, a)) > std::abs(g.direction(2, table_axis))) table_axis = a;
  }
  std::vector<uint8_t> outside(count + 1, 0);
  const Index3& d = g.dims;
  for (int64_t k = 0; k < d[2]; ++k) {
    for (int64_t j = 0; j < d[1]; ++j) {
      const bool whole_row = (table_axis != 1 && (j == 0 || j == d[1] - 1)) ||
                             (table_axis != 2 && (k == 0 || k == d[2] - 1));
      if (!whole_row && table_axis == 0) continue;
      const int64_t step = whole_row ? 1 : std::max<int64_t>(d[0] - 1, 1);
      for (int64_t i = 0; i < d[0]; i += step) {
        const uint32_t c = comp[g.offset(i, j, k)];
        if (c != 0 && c <= count) outside[c] = 1;
      }
    }
  }
  return outside;
}

// Air components (6-connected) touching the volume's side faces are outside the body; the others
// (lungs, bowel gas, pockets) are inside it and impassable. The side faces are those parallel to
// the table (cranio-caudal) axis: the two faces across that axis usually cut through the body
// (lungs and trachea reach the first slice of an abdominal CT), and air touching only them is
// still inside. Outside air always reaches a side face. Sets inside_air (one flag per voxel) and
// returns the number of inside air voxels.
int64_t mark_inside_air(const AirMask& air, const ImageGeometry& g, const std::string& source,
                        std::vector<uint8_t>& inside_air) {
  ComponentLabels components;
  try {
    components = label_components(air.image, false);
  } catch (const itk::ExceptionObject& e) {
    throw Error(source + ": connected components of air failed: " + e.GetDescription());
  }
  const uint32_t* comp = components.image->GetBufferPointer();
  const size_t count = components.count;
  const std::vector<uint8_t> outside = components_on_side_faces(comp, count, g);
  const int64_t n = g.voxel_count();
  int64_t inside = 0;
  for (int64_t v = 0; v < n; ++v) {
    const uint32_t c = comp[v];
    inside_air[size_t(v)] = (c != 0 && c <= count && !outside[c]) ? 1 : 0;
    inside += inside_air[size_t(v)];
  }
  return inside;
}

}  // namespace

Volume<float> blocking_from_labels(const Volume<int32_t>& labels, const VulnerabilityTable& table,
                                   const MarginOptions& margin, const std::string& labels_source) {
  labels.geometry().validate(labels_source);
  if (labels.values().size() != size_t(labels.voxel_count())) {
    throw Error(labels_source + ": label map holds " + std::to_string(labels.values().size()) +
                " values for " + std::to_string(labels.voxel_count()) + " voxels");
  }
  check_margin(margin);

  // Fast pass first: an unknown label fails before any smoothing.
  const std::vector<int32_t> present = distinct_labels(labels);
  std::vector<int> level_of_value(size_t(kMaxLabelValue) + 1, -1);  // index into table.levels
  std::vector<int64_t> voxels_per_level(table.levels.size(), 0);
  for (const int32_t value : present) {
    table.blocking_of_label(value, labels_source);  // throws for a value missing from the table
    if (value == 0) continue;
    const LabelClass* label = table.find_label(value);
    for (size_t l = 0; l < table.levels.size(); ++l) {
      if (table.levels[l].level == label->level) level_of_value[size_t(value)] = int(l);
    }
  }
  // One pass: each level's voxel count, and for the GPU each voxel's level (its code, index + 1;
  // 0 none) and each level's box.
  const ImageGeometry& g = labels.geometry();
  const int64_t n = labels.voxel_count();
  const int32_t* lab = labels.data();
  const size_t level_count = table.levels.size();
  if (level_count > 254) {
    throw Error(labels_source + ": the vulnerability table has " + std::to_string(level_count) +
                " levels (expected at most 254)");
  }
#if defined(CREPUSCULAR_HAVE_CUDA)
  const bool on_gpu = margin.on_gpu && kernels::cuda_device_count() > 0;
#else
  const bool on_gpu = false;
#endif
  std::vector<uint8_t> codes;
  if (on_gpu) assign_large(codes, size_t(n), uint8_t(0));
  std::vector<std::array<int64_t, 3>> box_lo(level_count, {g.dims[0], g.dims[1], g.dims[2]});
  std::vector<std::array<int64_t, 3>> box_hi(level_count, {-1, -1, -1});
#pragma omp parallel
  {
    std::vector<int64_t> mine(level_count, 0);
    std::vector<std::array<int64_t, 3>> lo = box_lo, hi = box_hi;
#pragma omp for schedule(static) nowait
    for (int64_t k = 0; k < g.dims[2]; ++k) {
      for (int64_t j = 0; j < g.dims[1]; ++j) {
        const int64_t row = (k * g.dims[1] + j) * g.dims[0];
        for (int64_t i = 0; i < g.dims[0]; ++i) {
          const int32_t x = lab[row + i];
          const int l = x > 0 ? level_of_value[size_t(x)] : -1;
          if (l >= 0) ++mine[size_t(l)];
          if (!on_gpu) continue;  // the cores find each level's box as they smooth it
          codes[size_t(row + i)] = uint8_t(l + 1);
          if (l < 0) continue;
          std::array<int64_t, 3>& a = lo[size_t(l)];
          std::array<int64_t, 3>& b = hi[size_t(l)];
          a = {std::min(a[0], i), std::min(a[1], j), std::min(a[2], k)};
          b = {std::max(b[0], i), std::max(b[1], j), std::max(b[2], k)};
        }
      }
    }
#pragma omp critical
    for (size_t l = 0; l < level_count; ++l) {
      voxels_per_level[l] += mine[l];
      for (size_t a = 0; a < 3; ++a) {
        box_lo[l][a] = std::min(box_lo[l][a], lo[l][a]);
        box_hi[l][a] = std::max(box_hi[l][a], hi[l][a]);
      }
    }
  }

  std::vector<uint8_t> blocks(level_count, 0);
  for (size_t l = 0; l < level_count; ++l) {
    const VulnerabilityLevel& level = table.levels[l];
    if (level.blocking_per_mm <= 0.0 || voxels_per_level[l] == 0) {
      spdlog::debug("blocking: level {} '{}' skipped ({} voxels, {} per mm)", level.level,
                    level.name, voxels_per_level[l], level.blocking_per_mm);
      continue;
    }
    spdlog::info("blocking: level {} '{}' ({} per mm), {} voxels, margin FWHM {} mm", level.level,
                 level.name, level.blocking_per_mm, voxels_per_level[l], margin.fwhm_mm);
    blocks[l] = 1;
  }

  Volume<float> b(g, 0.0f);
#if defined(CREPUSCULAR_HAVE_CUDA)
  if (on_gpu) {
    // The whole volume on the GPU: each level's box grown by its kernel's radius, as
    // discrete_gaussian_box grows the box of its mask, so the same bits as the cores.
    std::vector<kernels::MarginLevel> gpu_levels;
    std::array<std::vector<double>, 3> taps;
    if (margin.fwhm_mm > 0.0) taps = discrete_gaussian_taps(g, margin_gaussian(g, margin.fwhm_mm));
    for (size_t l = 0; l < level_count; ++l) {
      if (!blocks[l]) continue;
      kernels::MarginLevel level;
      level.code = uint8_t(l + 1);
      level.coeff = float(table.levels[l].blocking_per_mm);
      for (size_t a = 0; a < 3; ++a) {
        const int64_t r = int64_t(taps[a].size() / 2);
        level.lo[a] = std::max<int64_t>(0, box_lo[l][a] - r);
        level.dims[a] = std::min<int64_t>(g.dims[a] - 1, box_hi[l][a] + r) - level.lo[a] + 1;
        level.taps[a] = taps[a];
      }
      gpu_levels.push_back(std::move(level));
    }
    if (kernels::blocking_levels_cuda(codes.data(), g.dims.data(), gpu_levels, b.data())) {
      return b;
    }
    spdlog::info("blocking: not enough GPU memory for the volume; smoothing on the cores");
  }
#endif
  MarginOptions on_cores = margin;
  on_cores.on_gpu = false;
  LevelBuffers buffers;
  for (size_t l = 0; l < level_count; ++l) {
    if (!blocks[l]) continue;
    const VulnerabilityLevel& level = table.levels[l];
    add_level(b.values(), labels.geometry(), level.blocking_per_mm, on_cores,
              [&](int64_t v) { return lab[v] > 0 && level_of_value[size_t(lab[v])] == int(l); },
              buffers);
  }
  return b;
}

Volume<float> blocking_from_ct(const Volume<float>& ct_hu, const CtThresholds& thresholds,
                               const MarginOptions& margin) {
  const std::string source = "CT";
  ct_hu.geometry().validate(source);
  if (ct_hu.values().size() != size_t(ct_hu.voxel_count())) {
    throw Error(source + ": volume holds " + std::to_string(ct_hu.values().size()) +
                " values for " + std::to_string(ct_hu.voxel_count()) + " voxels");
  }
  check_margin(margin);
  check_ct_thresholds(thresholds);

  const ImageGeometry& g = ct_hu.geometry();
  const int64_t n = ct_hu.voxel_count();
  const float* hu = ct_hu.data();
  const AirMask air = air_mask(ct_hu, thresholds.air_hu, source);
  std::vector<uint8_t> inside_air(static_cast<size_t>(n), 0);
  if (air.voxels > 0) {
    const int64_t inside = mark_inside_air(air, g, source, inside_air);
    spdlog::info("blocking from CT: {} air voxels (<= {} HU), {} of them inside the body",
                 air.voxels, thresholds.air_hu, inside);
  }

  const auto blocked = [&](int64_t v) {
    return hu[v] >= thresholds.bone_hu || inside_air[size_t(v)] != 0;
  };
  int64_t impassable = 0;
  for (int64_t v = 0; v < n; ++v) impassable += blocked(v) ? 1 : 0;
  spdlog::info(
      "blocking from CT: {} impassable voxels (bone >= {} HU or inside air), {} per mm, "
      "margin FWHM {} mm",
      impassable, thresholds.bone_hu, thresholds.impassable_per_mm, margin.fwhm_mm);

  Volume<float> b(g, 0.0f);
  if (impassable > 0) {
    LevelBuffers buffers;
    add_level(b.values(), g, thresholds.impassable_per_mm, margin, blocked, buffers);
  }
  return b;
}

void validate_blocking(const Volume<float>& blocking, const std::string& source) {
  blocking.geometry().validate(source);
  if (blocking.values().size() != size_t(blocking.voxel_count())) {
    throw Error(source + ": blocking volume holds " + std::to_string(blocking.values().size()) +
                " values for " + std::to_string(blocking.voxel_count()) + " voxels");
  }
  const float* p = blocking.data();
  const int64_t n = blocking.voxel_count();
  // On every core first; only a bad volume is searched again, in order, for its first bad voxel.
  // (NaN fails both comparisons.)
  int bad = 0;
#pragma omp parallel for schedule(static) reduction(| : bad)
  for (int64_t v = 0; v < n; ++v) {
    bad |= !(p[v] >= 0.0f && p[v] <= std::numeric_limits<float>::max());
  }
  if (!bad) return;
  for (int64_t v = 0; v < n; ++v) {
    if (!std::isfinite(p[v]) || p[v] < 0.0f) {
      const Index3 ijk = blocking.geometry().index_of_offset(v);
      std::ostringstream m;
      m << source << ": blocking value at voxel (" << ijk[0] << ", " << ijk[1] << ", " << ijk[2]
        << ") is " << p[v] << " (expected a finite risk per mm >= 0)";
      throw Error(m.str());
    }
  }
}

}  // namespace crepuscular::planning
