// Path safety volume: input checks, tumor surface, output grid, CPU backend and device dispatch.
#include "planning/safety/path_safety.hpp"

#include <fmt/format.h>

#include <omp.h>
#include "foundation/log.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <fstream>
#include <future>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <sstream>

#include "foundation/csv.hpp"
#include "foundation/trace.hpp"
#include "kernels/value_set.hpp"
#include "planning/imaging/sampling.hpp"
#include "planning/preprocessing/blocking.hpp"
#include "planning/safety/adaptive_sampling.hpp"
#include "planning/safety/path_safety_scene.hpp"
#include "planning/safety/safety_classes.hpp"
#include <random>

#if defined(CREPUSCULAR_HAVE_CUDA)
#include "kernels/path_safety_cuda.hpp"
#endif

namespace crepuscular::planning {

namespace {

std::string format_bytes(double bytes) {
  std::ostringstream s;
  s.precision(3);
  if (bytes >= 1e9) {
    s << bytes / 1e9 << " GB";
  } else {
    s << bytes / 1e6 << " MB";
  }
  return s.str();
}

// Separable Gaussian (sigma = 1 voxel, truncated at 4 sigma) of a 0/1 mask over a padded box.
std::vector<float> smooth_mask_box(const Volume<uint8_t>& tumor, const int lo[3], const int hi[3],
                                   int pad, int box[3]) {
  for (int a = 0; a < 3; ++a) box[a] = hi[a] - lo[a] + 1 + 2 * pad;
  const int64_t n = int64_t(box[0]) * box[1] * box[2];
  std::vector<float> a(size_t(n), 0.0f), b(size_t(n), 0.0f);
  const auto at = [&](int x, int y, int z) { return (int64_t(z) * box[1] + y) * box[0] + x; };
  const auto& dims = tumor.dims();
  for (int z = 0; z < box[2]; ++z) {
    for (int y = 0; y < box[1]; ++y) {
      for (int x = 0; x < box[0]; ++x) {
        const int64_t i = lo[0] - pad + x, j = lo[1] - pad + y, k = lo[2] - pad + z;
        if (i >= 0 && j >= 0 && k >= 0 && i < dims[0] && j < dims[1] && k < dims[2]) {
          a[size_t(at(x, y, z))] = tumor(i, j, k) ? 1.0f : 0.0f;
        }
      }
    }
  }
  constexpr int kRadius = 4;
  float w[2 * kRadius + 1];
  float sum = 0.0f;
  for (int t = -kRadius; t <= kRadius; ++t) sum += (w[t + kRadius] = std::exp(-0.5f * t * t));
  for (float& v : w) v /= sum;
  const int64_t stride[3] = {1, box[0], int64_t(box[0]) * box[1]};
  for (int axis = 0; axis < 3; ++axis) {
    for (int z = 0; z < box[2]; ++z) {
      for (int y = 0; y < box[1]; ++y) {
        for (int x = 0; x < box[0]; ++x) {
          const int c[3] = {x, y, z};
          float acc = 0.0f;
          for (int t = -kRadius; t <= kRadius; ++t) {
            const int q = c[axis] + t;
            if (q < 0 || q >= box[axis]) continue;
            acc += w[t + kRadius] * a[size_t(at(x, y, z) + t * stride[axis])];
          }
          b[size_t(at(x, y, z))] = acc;
        }
      }
    }
    std::swap(a, b);
  }
  return a;
}

}  // namespace

// ---------------------------------------------------------------------------------------------

unsigned parse_value_set(const std::string& text) {
  unsigned values = 0;
  for (std::string item : split_csv_line(text)) {
    item.erase(std::remove_if(item.begin(), item.end(), ::isspace), item.end());
    std::transform(item.begin(), item.end(), item.begin(), ::tolower);
    if (item == "svv") {
      values |= kernels::kSvv;
    } else if (item == "isbv") {
      values |= kernels::kIsbv;
    } else if (item == "ivbv") {
      values |= kernels::kIvbv;
    } else if (item == "bvv") {
      values |= kernels::kBvv;
    } else if (item == "all") {
      values |= kernels::kAllValues;
    } else if (!item.empty()) {
      throw Error("path safety values: unknown value '" + item +
                  "' (expected svv, isbv, ivbv, bvv or all, comma-separated)");
    }
  }
  if (values == 0) throw Error("path safety values: none given (expected e.g. svv,bvv)");
  return values;
}

const char* value_name(unsigned bit) {
  switch (bit) {
    case kernels::kSvv:
      return "svv";
    case kernels::kIsbv:
      return "isbv";
    case kernels::kIvbv:
      return "ivbv";
    case kernels::kBvv:
      return "bvv";
    default:
      return "?";
  }
}

Device parse_device(const std::string& text) {
  if (text == "auto") return Device::kAuto;
  if (text == "cpu") return Device::kCpu;
  if (text == "cuda") return Device::kCuda;
  throw Error("path safety device: unknown device '" + text + "' (expected auto, cpu or cuda)");
}

Mode parse_mode(const std::string& text) {
  if (text == "exact") return Mode::kExact;
  if (text == "fast") return Mode::kFast;
  throw Error("path safety mode: unknown mode '" + text + "' (expected exact or fast)");
}

const char* mode_name(Mode mode) {
  return mode == Mode::kFast ? "fast" : "exact";
}

const char* device_name(Device device) {
  switch (device) {
    case Device::kAuto:
      return "auto";
    case Device::kCpu:
      return "cpu";
    case Device::kCuda:
      return "cuda";
  }
  return "?";
}

uint64_t available_memory_bytes() {
  std::ifstream in("/proc/meminfo");
  std::string key;
  uint64_t value = 0;
  std::string unit;
  while (in >> key >> value >> unit) {
    if (key == "MemAvailable:") return value * 1024;
  }
  return 0;
}

// ---------------------------------------------------------------------------------------------

TumorSurface extract_tumor_surface(const Volume<uint8_t>& tumor, const std::string& source) {
  tumor.geometry().validate(source);
  const auto& g = tumor.geometry();
  if (g.voxel_count() >= int64_t(std::numeric_limits<int>::max())) {
    throw Error(source + ": tumor mask has " + std::to_string(g.voxel_count()) +
                " voxels; at most 2^31 are supported (crop it around the tumor)");
  }
  TumorSurface s;
  s.lo[0] = s.lo[1] = s.lo[2] = std::numeric_limits<int>::max();
  s.hi[0] = s.hi[1] = s.hi[2] = -1;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  // Only the box of the tumor's voxels is visited (the same voxels in the same order).
  const VoxelBox voxels = nonzero_box(tumor);
  for (int64_t k = voxels.lo[2]; k <= voxels.hi[2]; ++k) {
    for (int64_t j = voxels.lo[1]; j <= voxels.hi[1]; ++j) {
      for (int64_t i = voxels.lo[0]; i <= voxels.hi[0]; ++i) {
        if (!tumor(i, j, k)) continue;
        ++s.tumor_voxels;
        sum += Eigen::Vector3d(double(i), double(j), double(k));
        const int64_t idx[3] = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          s.lo[a] = std::min(s.lo[a], int(idx[a]));
          s.hi[a] = std::max(s.hi[a], int(idx[a]));
        }
      }
    }
  }
  if (s.tumor_voxels == 0) {
    throw Error(source + ": tumor mask is empty (0 voxels > 0); expected a 0/1 mask of the tumor");
  }
  s.centroid = g.index_to_physical(Eigen::Vector3d(sum / double(s.tumor_voxels)));
  s.s2_mm2 = std::pow(g.voxel_volume_mm3(), 2.0 / 3.0);

  constexpr int kPad = 5;
  int box[3];
  const std::vector<float> smooth = smooth_mask_box(tumor, s.lo, s.hi, kPad, box);
  const auto sm = [&](int64_t i, int64_t j, int64_t k) {
    const int64_t x = i - (s.lo[0] - kPad), y = j - (s.lo[1] - kPad), z = k - (s.lo[2] - kPad);
    return smooth[size_t((z * box[1] + y) * box[0] + x)];
  };
  // Gradient in index space -> physical space: grad_phys = D diag(1/s) grad_index.
  const Eigen::Matrix3d to_physical = g.direction * g.spacing.cwiseInverse().asDiagonal();
  const auto inside = [&](int64_t i, int64_t j, int64_t k) {
    return g.contains(i, j, k) && tumor(i, j, k) != 0;
  };
  for (int64_t k = s.lo[2]; k <= s.hi[2]; ++k) {
    for (int64_t j = s.lo[1]; j <= s.hi[1]; ++j) {
      for (int64_t i = s.lo[0]; i <= s.hi[0]; ++i) {
        if (!tumor(i, j, k)) continue;
        const bool surface = !inside(i - 1, j, k) || !inside(i + 1, j, k) ||
                             !inside(i, j - 1, k) || !inside(i, j + 1, k) ||
                             !inside(i, j, k - 1) || !inside(i, j, k + 1);
        if (!surface) continue;
        const Eigen::Vector3d grad_index(0.5 * (sm(i + 1, j, k) - sm(i - 1, j, k)),
                                         0.5 * (sm(i, j + 1, k) - sm(i, j - 1, k)),
                                         0.5 * (sm(i, j, k + 1) - sm(i, j, k - 1)));
        Eigen::Vector3d normal = -(to_physical * grad_index);
        const double norm = normal.norm();
        // A symmetric blob (one voxel) has no gradient at its centre: no preferred direction,
        // encoded as a zero normal (|cos alpha| = 1 in the kernels).
        normal = norm > 1e-9 ? Eigen::Vector3d(normal / norm) : Eigen::Vector3d::Zero();
        const Eigen::Vector3d p = g.index_to_physical(i, j, k);
        kernels::SurfacePoint<double> sp{};
        sp.position = {p.x(), p.y(), p.z()};
        sp.normal = {normal.x(), normal.y(), normal.z()};
        sp.offset = int(g.offset(i, j, k));
        s.points.push_back(sp);
      }
    }
  }
  return s;
}

Eigen::Vector3d tumor_centroid(const Volume<uint8_t>& tumor, const std::string& source) {
  return extract_tumor_surface(tumor, source).centroid;
}

void FastModeOptions::check() const {
  const auto refuse = [](const char* option, const char* expected, int got) {
    throw Error(fmt::format("fast mode {}: expected {} (got {})", option, expected, got));
  };
  if (surface_block < 1 || surface_block > 4) {
    refuse("--fast-surface-block", "1 to 4", surface_block);
  }
  if (ray_stride < 0 || ray_stride > 4) refuse("--fast-ray-stride", "0 (automatic) to 4", ray_stride);
  if (check_voxels < 0 || check_voxels > 1000000) {
    refuse("--fast-check-voxels", "0 to 1000000", check_voxels);
  }
}

double farthest_blocking_mm(const Volume<float>& blocking, const Eigen::Vector3d& centre) {
  const auto& bg = blocking.geometry();
  const auto& d = bg.dims;
  double r2 = 0.0;
  for (int64_t k = 0; k < d[2]; ++k) {
    for (int64_t j = 0; j < d[1]; ++j) {
      for (int64_t i = 0; i < d[0]; ++i) {
        if (blocking(i, j, k) > 0.0f) {
          r2 = std::max(r2, (bg.index_to_physical(i, j, k) - centre).squaredNorm());
        }
      }
    }
  }
  return std::sqrt(r2);
}

namespace {

// A region of interest that holds nothing but tumor (a ball around a centre inside the tumor that
// does not reach its surface) computes no voxel a path could start from: refused with the
// numbers.
void refuse_region_inside_tumor(const Volume<uint8_t>& tumor, const TumorSurface& surface,
                                const Eigen::Vector3d& centre, double radius_mm) {
  const Index3 c = tumor.geometry().nearest_index(centre);
  if (!tumor.geometry().contains(c[0], c[1], c[2]) || !tumor(c[0], c[1], c[2])) return;
  double nearest = std::numeric_limits<double>::infinity(), farthest = 0.0;
  for (const auto& p : surface.points) {
    const double d = (Eigen::Vector3d(p.position.x, p.position.y, p.position.z) - centre).norm();
    nearest = std::min(nearest, d);
    farthest = std::max(farthest, d);
  }
  if (radius_mm < nearest) {
    throw Error(fmt::format(
        "region of interest: a radius of {:.1f} mm lies inside the tumor (its surface is {:.1f} "
        "to {:.1f} mm from the region's centre), so no point around the tumor would be computed; "
        "give a radius larger than {:.0f} mm, which reaches around the whole tumor (the needle's "
        "reach, e.g. 120 mm), or none to reach the farthest vulnerable structure",
        radius_mm, nearest, farthest, std::ceil(farthest)));
  }
}

// Throws Error naming `tumor_source` when the tumor takes more than a quarter of the scan (the
// blocking volume's grid): a label map or an inverted mask given as the tumor, not a lesion.
void refuse_implausible_tumor(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                              const TumorSurface& surface, const std::string& tumor_source) {
  constexpr double kMostOfScan = 0.25;
  const double tumor_ml = double(surface.tumor_voxels) * tumor.geometry().voxel_volume_mm3() / 1e3;
  const double scan_ml = double(blocking.voxel_count()) * blocking.geometry().voxel_volume_mm3() / 1e3;
  if (tumor_ml > kMostOfScan * scan_ml) {
    throw Error(fmt::format(
        "{}: the tumor is {:.0f} mL, {:.0f} % of the scan ({:.0f} mL); a tumor mask marks the "
        "lesion only (at most {:.0f} % of the scan): check that the tumor file or label is the "
        "lesion's, not the label map or an inverted mask",
        tumor_source, tumor_ml, 100.0 * tumor_ml / scan_ml, scan_ml, 100.0 * kMostOfScan));
  }
}

}  // namespace

OutputGrid make_output_grid(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                            const TumorSurface& surface, const PathSafetyOptions& options) {
  const auto& bg = blocking.geometry();
  OutputGrid out;
  out.centre = options.centre_lps_mm ? *options.centre_lps_mm : surface.centroid;
  if (!out.centre.allFinite()) throw Error("output grid centre: not a finite point");
  double h = options.spacing_mm;
  if (h == 0.0) h = std::min(bg.spacing.minCoeff(), tumor.geometry().spacing.minCoeff());
  if (!(h > 0.0) || !std::isfinite(h)) {
    throw Error("output spacing: must be > 0 mm (got " + std::to_string(h) + ")");
  }
  double r = options.radius_mm;
  if (!(r >= 0.0) || !std::isfinite(r)) {
    throw Error("region of interest radius: must be >= 0 mm (got " + std::to_string(r) + ")");
  }
  if (r == 0.0) {
    r = farthest_blocking_mm(blocking, out.centre);
    if (r == 0.0) {
      throw Error(
          "blocking volume has no voxel with b > 0, so the region of interest (the ball "
          "reaching the farthest blocking voxel) is empty; give a region of interest radius");
    }
  }
  out.radius_mm = r;
  refuse_region_inside_tumor(tumor, surface, out.centre, r);
  const int64_t half = int64_t(std::ceil(r / h - 1e-9));
  const int64_t n = 2 * half + 1;
  if (n > 4097) {
    throw Error("region of interest too large: " + std::to_string(n) + " voxels per axis (radius " +
                std::to_string(r) + " mm at spacing " + std::to_string(h) +
                " mm); use a larger output spacing or a smaller region of interest radius");
  }
  out.geometry.dims = {n, n, n};
  out.geometry.spacing = Eigen::Vector3d::Constant(h);
  out.geometry.direction = bg.direction;
  out.geometry.origin = out.centre - bg.direction * Eigen::Vector3d::Constant(double(half) * h);
  // Voxels inside the ball, by the integer test both backends use.
  const double rh = r / h;
  out.half = half;
  out.max_sq = int64_t(std::floor(rh * rh + 1e-9));
  int64_t count = 0;
  for (int64_t k = 0; k < n; ++k) {
    for (int64_t j = 0; j < n; ++j) {
      const int64_t w = std::min<int64_t>(out.roi_half_width(j, k), half);
      if (w >= 0) count += 2 * w + 1;
    }
  }
  out.roi_voxels = count;
  if (count <= 1) {
    throw Error("region of interest: radius " + std::to_string(r) + " mm at output spacing " +
                std::to_string(h) + " mm holds a single voxel, which says nothing about any "
                "path; give a radius of at least one spacing (or a smaller spacing)");
  }
  return out;
}

namespace {

// Empty-space leaping (kernels::brick_code): every empty brick (code 0) gets -d where d >= 2 is its
// Chebyshev distance, in bricks, to the nearest brick that is not empty, capped at
// kernels::kMaxEmptyRun. The bricks just beyond the grid count as not empty: a sample there reads
// the grid's edge voxels. Separable: the distance along x, then the nearest along y of
// max(|dy|, that), then along z.
void mark_empty_runs(std::vector<float>& bricks, const std::array<int, 3>& n) {
  constexpr int kCap = kernels::kMaxEmptyRun;
  std::vector<uint8_t> dist(bricks.size());
  const auto at = [&](int x, int y, int z) { return size_t((int64_t(z) * n[1] + y) * n[0] + x); };
#pragma omp parallel for collapse(2) schedule(static)
  for (int z = 0; z < n[2]; ++z) {
    for (int y = 0; y < n[1]; ++y) {
      int run = 0;  // distance to the last brick that is not empty (the one before x = 0)
      for (int x = 0; x < n[0]; ++x) {
        run = bricks[at(x, y, z)] == 0.0f ? std::min(run + 1, kCap) : 0;
        dist[at(x, y, z)] = uint8_t(run);
      }
      run = 0;
      for (int x = n[0] - 1; x >= 0; --x) {
        run = bricks[at(x, y, z)] == 0.0f ? std::min(run + 1, kCap) : 0;
        dist[at(x, y, z)] = uint8_t(std::min<int>(dist[at(x, y, z)], run));
      }
    }
  }
  // Along one more axis: the nearest of max(|d|, dist) over the line, the line's ends beyond the
  // grid at distance 0.
  const auto pass = [&](int axis) {
    const int len = n[size_t(axis)];
    const int other = n[0];                     // lines along y or z: one per x
    const int outer = axis == 1 ? n[2] : n[1];  // and one per z or y
#pragma omp parallel
    {
      std::vector<uint8_t> line(static_cast<size_t>(len));
#pragma omp for collapse(2) schedule(static)
      for (int o = 0; o < outer; ++o) {
        for (int a = 0; a < other; ++a) {
          const auto index = [&](int t) { return axis == 1 ? at(a, t, o) : at(a, o, t); };
          for (int t = 0; t < len; ++t) line[size_t(t)] = dist[index(t)];
          for (int t = 0; t < len; ++t) {
            int best = line[size_t(t)];
            for (int d = 1; d < best; ++d) {
              const int lo = t - d, hi = t + d;
              const int below = lo < 0 ? 0 : line[size_t(lo)];
              const int above = hi >= len ? 0 : line[size_t(hi)];
              best = std::min(best, std::max(d, std::min(below, above)));
            }
            dist[index(t)] = uint8_t(best);
          }
        }
      }
    }
  };
  pass(1);
  pass(2);
#pragma omp parallel for schedule(static)
  for (int64_t b = 0; b < int64_t(bricks.size()); ++b) {
    if (dist[size_t(b)] >= 2) bricks[size_t(b)] = -float(dist[size_t(b)]);
  }
}

}  // namespace

int coarsest_stride(double spacing_mm, double radius_mm) {
  const double widest = std::min(8.0, radius_mm / 4.0) + 1e-9;
  int stride = 4;
  while (stride < 64 && 2.0 * stride * spacing_mm <= widest) stride *= 2;
  return stride;
}

int automatic_ray_stride(double spacing_mm, double blocking_spacing_mm) {
  const double gamma = 0.5 * spacing_mm;
  const double longest =
      std::min(kMaxQuadratureStepMm, kMaxQuadratureStepVoxels * blocking_spacing_mm);
  // A spacing stored as float in the file (0.7 as 0.699999988) still counts as its value.
  int stride = 1;
  while (stride < 4 && (stride + 1) * gamma <= longest * (1.0 + 1e-6)) ++stride;
  return stride;
}

std::vector<float> blocking_bricks(const Volume<float>& blocking) {
  const auto& d = blocking.dims();
  const int bx = kernels::bricks_along(int(d[0])), by = kernels::bricks_along(int(d[1])),
            bz = kernels::bricks_along(int(d[2]));
  std::vector<float> bricks(size_t(bx) * by * bz, -1.0f);
  constexpr int64_t kSide = int64_t(1) << kernels::kBrickShift;
  // A brick's samples read the voxels it covers and the next one along each axis (the trilinear
  // support); beyond the grid's last voxel that next one is 0.
#pragma omp parallel for collapse(2) schedule(dynamic, 4)
  for (int z = 0; z < bz; ++z) {
    for (int y = 0; y < by; ++y) {
      for (int x = 0; x < bx; ++x) {
        const int64_t lo[3] = {x * kSide, y * kSide, z * kSide};
        bool beyond = false;
        for (int a = 0; a < 3; ++a) beyond |= lo[a] + kSide > d[a] - 1;
        float value = beyond ? 0.0f : blocking(lo[0], lo[1], lo[2]);
        bool uniform = true;
        for (int64_t k = lo[2]; uniform && k <= std::min<int64_t>(lo[2] + kSide, d[2] - 1); ++k)
          for (int64_t j = lo[1]; uniform && j <= std::min<int64_t>(lo[1] + kSide, d[1] - 1); ++j)
            for (int64_t i = lo[0]; i <= std::min<int64_t>(lo[0] + kSide, d[0] - 1); ++i)
              if (blocking(i, j, k) != value) {
                uniform = false;
                break;
              }
        bricks[size_t((int64_t(z) * by + y) * bx + x)] = uniform ? value : kernels::kMixedBrick;
      }
    }
  }
  mark_empty_runs(bricks, {bx, by, bz});
  return bricks;
}

std::vector<uint8_t> tumor_leaps(const Volume<uint8_t>& tumor, const int lo[3], const int hi[3]) {
  const int64_t mx = hi[0] - lo[0] + 1, my = hi[1] - lo[1] + 1, mz = hi[2] - lo[2] + 1;
  if (mx <= 0 || my <= 0 || mz <= 0) return {};
  const auto at = [&](int64_t i, int64_t j, int64_t k) { return size_t((k * my + j) * mx + i); };
  std::vector<uint8_t> distance(size_t(mx * my * mz), 0), kind(distance.size(), 0);
  for (int64_t k = 0; k < mz; ++k)
    for (int64_t j = 0; j < my; ++j)
      for (int64_t i = 0; i < mx; ++i) {
        kind[at(i, j, k)] = tumor(lo[0] + i, lo[1] + j, lo[2] + k) != 0 ? 1 : 0;
      }
  const auto inside = [&](int64_t i, int64_t j, int64_t k) {
    return i >= 0 && j >= 0 && k >= 0 && i < mx && j < my && k < mz && kind[at(i, j, k)] != 0;
  };
  // Chebyshev distance to the other kind: 1 where one of the 26 neighbours (voxels beyond the box
  // included: not tumor) differs, then breadth first through voxels of one kind.
  std::vector<int64_t> front, next;
  for (int64_t k = 0; k < mz; ++k)
    for (int64_t j = 0; j < my; ++j)
      for (int64_t i = 0; i < mx; ++i) {
        const bool in = kind[at(i, j, k)] != 0;
        bool edge = false;
        for (int dz = -1; dz <= 1 && !edge; ++dz)
          for (int dy = -1; dy <= 1 && !edge; ++dy)
            for (int dx = -1; dx <= 1 && !edge; ++dx)
              edge = inside(i + dx, j + dy, k + dz) != in;
        if (edge) {
          distance[at(i, j, k)] = 1;
          front.push_back(int64_t(at(i, j, k)));
        }
      }
  for (int d = 2; !front.empty(); ++d) {
    next.clear();
    for (const int64_t v : front) {
      const int64_t i = v % mx, j = (v / mx) % my, k = v / (mx * my);
      for (int dz = -1; dz <= 1; ++dz)
        for (int dy = -1; dy <= 1; ++dy)
          for (int dx = -1; dx <= 1; ++dx) {
            const int64_t a = i + dx, b = j + dy, c = k + dz;
            if (a < 0 || b < 0 || c < 0 || a >= mx || b >= my || c >= mz) continue;
            const size_t w = at(a, b, c);
            if (distance[w] != 0 || kind[w] != kind[size_t(v)]) continue;
            distance[w] = uint8_t(std::min(d, kernels::kMaxTumorLeap));
            next.push_back(int64_t(w));
          }
    }
    front.swap(next);
  }
  for (size_t v = 0; v < distance.size(); ++v) {
    // A box of one kind throughout (no voxel of the other kind in it): only the voxels beyond it.
    const uint8_t d = distance[v] == 0 ? uint8_t(1) : distance[v];
    distance[v] = uint8_t(d | (kind[v] ? kernels::kTumorLeapInside : 0));
  }
  return distance;
}

kernels::PathSafetyScene<double> make_scene(const Volume<float>& blocking,
                                            const Volume<uint8_t>& tumor,
                                            const TumorSurface& surface, double gamma_mm,
                                            double eps, const std::vector<float>& bricks,
                                            const std::vector<uint8_t>& leaps) {
  kernels::PathSafetyScene<double> s{};
  s.blocking = blocking_grid(blocking);
  if (!bricks.empty()) {
    const auto& bd = blocking.dims();
    s.blocking.bricks = bricks.data();
    s.blocking.bx = kernels::bricks_along(int(bd[0]));
    s.blocking.by = kernels::bricks_along(int(bd[1]));
    s.blocking.bz = kernels::bricks_along(int(bd[2]));
  }
  const auto& td = tumor.dims();
  s.tumor.mask = tumor.data();
  s.tumor.nx = int(td[0]);
  s.tumor.ny = int(td[1]);
  s.tumor.nz = int(td[2]);
  s.tumor.physical_to_index = physical_to_index_affine(tumor.geometry());
  for (int a = 0; a < 3; ++a) {
    s.tumor.lo[a] = surface.lo[a];
    s.tumor.hi[a] = surface.hi[a];
  }
  if (!leaps.empty()) s.tumor.leap = leaps.data();
  s.surface = surface.points.data();
  s.surface_count = int(surface.points.size());
  s.gamma = gamma_mm;
  s.eps = eps;
  s.s2 = surface.s2_mm2;
  return s;
}

Volume<uint8_t> resample_tumor(const Volume<uint8_t>& tumor, const TumorSurface& surface,
                               const OutputGrid& grid, double spacing) {
  const ImageGeometry& tg = tumor.geometry();
  const Eigen::Matrix3d& axes = grid.geometry.direction;
  // The mask's tumor box (voxel edges) in the output axes, in units of the new spacing from the
  // output grid's centre.
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  for (int corner = 0; corner < 8; ++corner) {
    const Eigen::Vector3d index((corner & 1) ? surface.hi[0] + 0.5 : surface.lo[0] - 0.5,
                                (corner & 2) ? surface.hi[1] + 0.5 : surface.lo[1] - 0.5,
                                (corner & 4) ? surface.hi[2] + 0.5 : surface.lo[2] - 0.5);
    const Eigen::Vector3d q =
        axes.transpose() * (tg.index_to_physical(index) - grid.centre) / spacing;
    lo = lo.cwiseMin(q);
    hi = hi.cwiseMax(q);
  }
  ImageGeometry g;
  g.spacing = Eigen::Vector3d::Constant(spacing);
  g.direction = axes;
  Eigen::Vector3d first;
  for (int a = 0; a < 3; ++a) {
    first[a] = std::floor(lo[a]) - 1.0;
    g.dims[a] = int64_t(std::ceil(hi[a]) + 1.0 - first[a]) + 1;
  }
  g.origin = grid.centre + axes * (first * spacing);
  if (g.voxel_count() >= int64_t(std::numeric_limits<int>::max())) {
    throw Error("tumor spacing " + std::to_string(spacing) + " mm: the resampled tumor grid would have " +
                std::to_string(g.voxel_count()) + " voxels; give a larger tumor spacing");
  }
  Volume<uint8_t> out(g, uint8_t(0));
  const auto& d = g.dims;
#pragma omp parallel for schedule(static)
  for (int64_t k = 0; k < d[2]; ++k) {
    for (int64_t j = 0; j < d[1]; ++j) {
      for (int64_t i = 0; i < d[0]; ++i) {
        out(i, j, k) = nearest_voxel_or(tumor, g.index_to_physical(i, j, k), uint8_t(0)) ? 1 : 0;
      }
    }
  }
  return out;
}

// ---------------------------------------------------------------------------------------------

namespace {

void check_tumor_inside_blocking(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                                 const TumorSurface& surface, const std::string& blocking_source,
                                 const std::string& tumor_source) {
  const auto& bg = blocking.geometry();
  const auto& tg = tumor.geometry();
  int64_t outside = 0;
  for (int64_t k = surface.lo[2]; k <= surface.hi[2]; ++k) {
    for (int64_t j = surface.lo[1]; j <= surface.hi[1]; ++j) {
      for (int64_t i = surface.lo[0]; i <= surface.hi[0]; ++i) {
        if (!tumor(i, j, k)) continue;
        if (!within_extent(bg, bg.physical_to_index(tg.index_to_physical(i, j, k)))) ++outside;
      }
    }
  }
  if (outside > 0) {
    std::ostringstream m;
    m << tumor_source << ": " << outside << " of " << surface.tumor_voxels
      << " tumor voxels lie outside the blocking volume (" << blocking_source
      << "); the tumor must lie inside the segmented region";
    throw Error(m.str());
  }
}

// Output voxel centres through kernels::grid_point, the definition the CUDA kernels use, so that
// both backends cast their rays from the same double-precision points.
struct VoxelCentres {
  double origin[3];
  double axes[3][3];
  explicit VoxelCentres(const ImageGeometry& g) {
    const Eigen::Matrix3d m = g.index_to_physical_matrix();
    for (int a = 0; a < 3; ++a) {
      origin[a] = g.origin[a];
      for (int b = 0; b < 3; ++b) axes[a][b] = m(b, a);
    }
  }
  kernels::Vec3<double> operator()(int64_t i, int64_t j, int64_t k) const {
    return kernels::grid_point(origin, axes, int(i), int(j), int(k));
  }
};

// The result's arrays of the requested values (null for the others), in slot order.
void value_outputs(PathSafetyResult& result, unsigned values,
                   float* out[kernels::kValueCount]) {
  for (int v = 0; v < kernels::kValueCount; ++v) {
    out[v] = (values & (1u << v)) ? result.volumes[size_t(v)].data() : nullptr;
  }
}

void run_cpu(const kernels::PathSafetyScene<double>& scene, const OutputGrid& grid,
             const uint8_t* known, unsigned values, int threads, PathSafetyResult& result,
             const std::function<void(double)>& progress) {
  const auto& g = grid.geometry;
  const VoxelCentres centre(g);
  const int64_t n = g.dims[0];
  float* out[kernels::kValueCount] = {};
  value_outputs(result, values, out);
  std::atomic<int64_t> done{0};
  const int64_t total = std::max<int64_t>(grid.roi_voxels, 1);
  double next_report = 0.02;
  kernels::with_value_set(values, [&](auto tag) {
    constexpr unsigned kValues = decltype(tag)::value;
#pragma omp parallel for collapse(2) schedule(dynamic, 1) num_threads(threads)
    for (int64_t k = 0; k < n; ++k) {
      for (int64_t j = 0; j < n; ++j) {
        int64_t row_done = 0;
        for (int64_t i = 0; i < n; ++i) {
          if (!grid.in_roi(i, j, k)) continue;
          if (known && !known[g.offset(i, j, k)]) continue;  // unknown: stays NaN
          float res[kernels::kValueCount] = {0.0f, 0.0f, 0.0f, 0.0f};
          kernels::path_safety_at<double, kValues>(scene, centre(i, j, k), res);
          const int64_t off = g.offset(i, j, k);
          for (int v = 0; v < kernels::kValueCount; ++v) {
            if (out[v]) out[v][off] = res[v];
          }
          ++row_done;
        }
        const int64_t now = done.fetch_add(row_done) + row_done;
        if (progress && omp_get_thread_num() == 0) {
          const double f = double(now) / double(total);
          if (f >= next_report) {
            progress(std::min(f, 1.0));
            next_report = f + 0.02;
          }
        }
      }
    }
  });
  if (progress) progress(1.0);
}

// Fast mode: the output grid sampled coarse to fine (adaptive_sampling.hpp), each point's values
// computed by `evaluate` (exact rays on the CPU or the GPU).
void run_adaptive(const OutputGrid& grid, const uint8_t* known, const PathSafetyOptions& options,
                  const PointEvaluator& evaluate, PathSafetyResult& result,
                  bool evaluator_on_device = false) {
  AdaptiveOptions adaptive;
  adaptive.values = options.values;
  adaptive.stride = coarsest_stride(grid.geometry.spacing[0], grid.radius_mm);
  adaptive.combination = options.combination;
  adaptive.progress = options.progress;
  adaptive.overlap_host_steps = evaluator_on_device;
  if (known) {
    const ImageGeometry& g = grid.geometry;
    adaptive.known = [known, &g, coverage = options.coverage](int64_t i, int64_t j, int64_t k) {
      if (i >= 0 && j >= 0 && k >= 0 && i < g.dims[0] && j < g.dims[1] && k < g.dims[2]) {
        return known[g.offset(i, j, k)] != 0;
      }
      return coverage->contains(g.index_to_physical(Eigen::Vector3d(double(i), double(j), double(k))));
    };
  }
  adaptive.known_mask = known;
  result.fast.coarsest_stride = adaptive.stride;
  float* out[kernels::kValueCount] = {};
  value_outputs(result, options.values, out);
  if (options.before_sampling) {
    trace::event("turn_wait_begin");
    options.before_sampling();
  }
  trace::event("sampling_begin");
  const AdaptiveReport report = sample_adaptively(grid, adaptive, evaluate, out);
  trace::event("sampling_end");
  result.fast.evaluated_points = report.evaluated;
  result.fast.interpolated_voxels = report.interpolated;
  result.fast.levels = report.levels;
  result.fast.cells_left_to_combination = report.cells_left_to_combination;
  result.fast.points_left_to_combination = report.points_left_to_combination;
  if (adaptive.combination) {
    spdlog::info("fast mode: {} cells and {} finest points left to the phases before (they "
                 "decide the combination's class there; this phase's own values there, and so "
                 "its own check, are approximate)",
                 report.cells_left_to_combination, report.points_left_to_combination);
  }
  result.phases.insert(result.phases.end(), report.seconds.begin(), report.seconds.end());
  std::string levels;
  for (const auto& [stride, count] : report.levels) {
    levels += (levels.empty() ? "" : ", ") + std::to_string(count) + " at stride " +
              std::to_string(stride);
  }
  spdlog::info("fast mode: {} points computed exactly ({}), {} of {} ROI voxels interpolated",
               report.evaluated, levels, report.interpolated, grid.roi_voxels);
}

// The exact values at listed points, on the CPU.
PointEvaluator cpu_point_evaluator(const kernels::PathSafetyScene<double>& scene,
                                   const OutputGrid& grid, unsigned values, int threads) {
  return [&scene, &grid, values, threads](const std::vector<GridPoint>& points,
                                          std::vector<float>& out) {
    const VoxelCentres centre(grid.geometry);
    kernels::with_value_set(values, [&](auto tag) {
      constexpr unsigned kValues = decltype(tag)::value;
#pragma omp parallel for schedule(dynamic, 8) num_threads(threads)
      for (int64_t p = 0; p < int64_t(points.size()); ++p) {
        const GridPoint& g = points[size_t(p)];
        kernels::path_safety_at<double, kValues>(scene, centre(g.i, g.j, g.k),
                                                 &out[size_t(p) * kernels::kValueCount]);
      }
    });
  };
}

// The self-check's voxels (up to `count` of the region inside the scan, drawn at random with a
// fixed seed) and their exact values. Independent of fast mode's result, so it may be computed
// while fast mode samples.
CheckSample exact_check_sample(const OutputGrid& grid, const uint8_t* known, int count,
                               const PointEvaluator& evaluate) {
  std::mt19937_64 rng(20111);
  const int64_t n = grid.geometry.dims[0];
  std::uniform_int_distribution<int64_t> u(0, n - 1);
  CheckSample sample;
  std::vector<GridPoint> points;
  // Voxels of the region inside the scan (the others have no value), a bounded number of draws.
  for (int64_t draw = 0;
       int64_t(sample.offsets.size()) < std::min<int64_t>(count, grid.roi_voxels) &&
       draw < 1000 * int64_t(count);
       ++draw) {
    const int64_t i = u(rng), j = u(rng), k = u(rng);
    if (!grid.in_roi(i, j, k)) continue;
    if (known && !known[grid.geometry.offset(i, j, k)]) continue;
    sample.offsets.push_back(grid.geometry.offset(i, j, k));
    points.push_back({int32_t(i), int32_t(j), int32_t(k)});
  }
  sample.exact.assign(points.size() * kernels::kValueCount, 0.0f);
  if (!points.empty()) evaluate(points, sample.exact);
  return sample;
}

}  // namespace

void compare_with_check_sample(const CheckSample& sample, unsigned values,
                               PathSafetyResult& result) {
  const std::vector<int64_t>& offsets = sample.offsets;
  FastModeReport& fast = result.fast;
  fast.check_voxels = int64_t(offsets.size());
  for (int v = 0; v < kernels::kValueCount; ++v) {
    const unsigned bit = 1u << v;
    if (!(values & bit)) continue;
    const SafetyClasses& classes = classes_of(result, bit);
    double diff2 = 0.0, ref2 = 0.0;
    int64_t same = 0;
    for (size_t s = 0; s < offsets.size(); ++s) {
      const double a = sample.exact[s * kernels::kValueCount + size_t(v)];
      const double b = result.volumes[size_t(v)][offsets[s]];
      diff2 += (a - b) * (a - b);
      ref2 += a * a;
      same += classes.classify(a) == classes.classify(b);
    }
    fast.check_relative_l2[size_t(v)] = ref2 > 0.0 ? std::sqrt(diff2 / ref2) : std::sqrt(diff2);
    fast.check_class_agreement[size_t(v)] =
        offsets.empty() ? 1.0 : double(same) / double(offsets.size());
  }
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (values & (1u << v)) {
      spdlog::info("fast mode vs exact at {} voxels: {} relative L2 {:.2e}, same class {:.2f} %",
                   fast.check_voxels, value_name(1u << v), fast.check_relative_l2[size_t(v)],
                   100.0 * fast.check_class_agreement[size_t(v)]);
    }
  }
}

namespace {

// Fast mode's self-check (options.fast.check_voxels voxels recomputed exactly), logged.
void check_fast_mode(const OutputGrid& grid, const uint8_t* known,
                     const PathSafetyOptions& options, const PointEvaluator& evaluate,
                     PathSafetyResult& result) {
  result.check_sample = std::make_shared<const CheckSample>(
      exact_check_sample(grid, known, options.fast.check_voxels, evaluate));
  compare_with_check_sample(*result.check_sample, options.values, result);
}

// Fast mode's rays: the surface points grouped by blocks of block^3 voxels of the tumor grid; each
// block's point nearest the mean of its points stands for all of them (weight = their count), so
// that every sum and count keeps its size while a block^2-th of the rays are cast.
TumorSurface surface_representatives(const TumorSurface& surface, const ImageGeometry& tumor,
                                     int block) {
  std::map<std::array<int64_t, 3>, std::vector<size_t>> blocks;
  for (size_t n = 0; n < surface.points.size(); ++n) {
    const Index3 v = tumor.index_of_offset(surface.points[n].offset);
    blocks[{v[0] / block, v[1] / block, v[2] / block}].push_back(n);
  }
  TumorSurface out = surface;
  out.points.clear();
  for (const auto& [key, members] : blocks) {
    kernels::Vec3<double> mean{0.0, 0.0, 0.0};
    for (size_t n : members) {
      const auto& q = surface.points[n].position;
      mean = {mean.x + q.x, mean.y + q.y, mean.z + q.z};
    }
    const double w = 1.0 / double(members.size());
    mean = {mean.x * w, mean.y * w, mean.z * w};
    size_t best = members.front();
    double best_d2 = std::numeric_limits<double>::infinity();
    for (size_t n : members) {
      const kernels::Vec3<double> d = surface.points[n].position - mean;
      const double d2 = kernels::dot(d, d);
      if (d2 < best_d2) best_d2 = d2, best = n;
    }
    kernels::SurfacePoint<double> rep = surface.points[best];
    rep.weight = int(members.size());
    out.points.push_back(rep);
  }
  return out;
}

// Throws Error when an input's geometry or an option is unusable.
void check_inputs(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                  const PathSafetyOptions& options, const std::string& blocking_source,
                  const std::string& tumor_source) {
  blocking.geometry().validate(blocking_source);
  tumor.geometry().validate(tumor_source);
  if (options.values == 0 || (options.values & ~kernels::kAllValues) != 0) {
    throw Error("path safety: no valid value requested (expected svv, isbv, ivbv, bvv)");
  }
  options.fast.check();
  if (!(options.eps >= 0.0) || !std::isfinite(options.eps)) {
    throw Error("insignificant blocking eps: must be a finite number >= 0 (got " +
                std::to_string(options.eps) + ")");
  }
  if (options.spacing_mm < 0.0 || !std::isfinite(options.spacing_mm)) {
    throw Error("output spacing: must be > 0 mm (got " + std::to_string(options.spacing_mm) + ")");
  }
  if (options.threads < 0 || options.threads > 1024) {
    throw Error("CPU threads: expected 1 to 1024, or 0 for all cores (got " +
                std::to_string(options.threads) + ")");
  }
  if (!std::isfinite(options.tumor_spacing_mm) ||
      (options.tumor_spacing_mm < 0.0 &&
       options.tumor_spacing_mm != PathSafetyOptions::kTumorSpacingAuto)) {
    throw Error("tumor spacing: must be > 0 mm, or 0 for the mask's own voxels (got " +
                std::to_string(options.tumor_spacing_mm) + ")");
  }
}

// Throws Error when the output volumes would not fit the memory limit (options, else 80 % of the
// memory available).
void check_memory(const OutputGrid& grid, const PathSafetyOptions& options) {
  int value_count = 0;
  for (int v = 0; v < kernels::kValueCount; ++v) value_count += (options.values >> v) & 1u;
  const double need = double(grid.geometry.voxel_count()) * 4.0 * value_count;
  const double limit = options.memory_limit_bytes > 0
                           ? double(options.memory_limit_bytes)
                           : 0.8 * double(available_memory_bytes());
  if (limit > 0.0 && need > limit) {
    const auto& d = grid.geometry.dims;
    std::ostringstream m;
    m << "region of interest too large for memory: output grid " << d[0] << "x" << d[1] << "x"
      << d[2] << " voxels (radius " << grid.radius_mm << " mm, spacing " << grid.geometry.spacing[0]
      << " mm) x " << value_count << " values needs " << format_bytes(need) << ", "
      << format_bytes(limit)
      << " may be used; give a larger output spacing, a smaller region of interest radius or "
         "fewer path safety values";
    throw Error(m.str());
  }
}

// Durations of the host's phases of a run, each from the end of the previous one.
class PhaseClock {
 public:
  void done(const char* name) {
    const auto now = std::chrono::steady_clock::now();
    phases.emplace_back(name, std::chrono::duration<double>(now - last_).count());
    last_ = now;
  }
  std::vector<std::pair<std::string, double>> phases;

 private:
  std::chrono::steady_clock::time_point last_ = std::chrono::steady_clock::now();
};

// The output volumes (NaN = not computed), allocated one thread each: touching a few GB of fresh
// memory takes a good fraction of a second, which overlaps the GPU's work where there is one.
class PendingVolumes {
 public:
  PendingVolumes(const ImageGeometry& geometry, unsigned values) {
    for (int v = 0; v < kernels::kValueCount; ++v) {
      if (values & (1u << v)) {
        pending_[size_t(v)] = std::async(std::launch::async, [&geometry] {
          return Volume<float>(geometry, std::numeric_limits<float>::quiet_NaN());
        });
      }
    }
  }
  // Waits for the volumes and moves them into result.volumes; later calls do nothing.
  void collect(PathSafetyResult& result) {
    for (int v = 0; v < kernels::kValueCount; ++v) {
      if (pending_[size_t(v)].valid()) result.volumes[size_t(v)] = pending_[size_t(v)].get();
    }
  }

 private:
  std::array<std::future<Volume<float>>, kernels::kValueCount> pending_;
};

// The run's path safety table and sizes, before any value is computed.
PathSafetyResult start_result(const OutputGrid& grid, const TumorSurface& surface,
                              const PathSafetyOptions& options) {
  PathSafetyResult result;
  result.grid = grid;
  result.values = options.values;
  result.mode = options.mode;
  result.tumor_voxels = surface.tumor_voxels;
  result.surface_points = int64_t(surface.points.size());
  result.s2_mm2 = surface.s2_mm2;
  result.gamma_mm = 0.5 * grid.geometry.spacing[0];
  result.eps = options.eps;
  result.rays = uint64_t(grid.roi_voxels) * uint64_t(surface.points.size());
  return result;
}

// The CUDA backend, the one place that knows whether this build has one: it starts CUDA early,
// counts the devices and runs a pass. Without CUDA it has no devices and never runs.
#if defined(CREPUSCULAR_HAVE_CUDA)
// Starting CUDA takes a good part of a second: once per process, on its own thread, from the
// first call on (the devices found).
std::shared_future<int> cuda_warm_up_once() {
  static std::mutex mutex;
  static std::shared_future<int> started;
  const std::lock_guard<std::mutex> lock(mutex);
  if (!started.valid()) {
    started = std::async(std::launch::async, [] { return kernels::cuda_warm_up(); }).share();
  }
  return started;
}

class CudaBackend {
 public:
  static constexpr const char* kNoDevice =
      "path safety device cuda: no CUDA device found (choose device cpu or auto)";

  // The warm-up overlaps the preparation on the host, or started earlier (start_device_warm_up);
  // never when the CPU is asked for.
  explicit CudaBackend(Device device) : device_(device) {
    if (device != Device::kCpu) warm_up_ = cuda_warm_up_once();
  }

  int device_count() {
    if (device_ == Device::kCpu) return 0;
    if (!count_) count_ = warm_up_.get();
    return *count_;
  }

  void run(const kernels::PathSafetyScene<double>& scene,
           const kernels::PathSafetyScene<double>& fast_scene, const OutputGrid& grid,
           const uint8_t* known, const PathSafetyOptions& options, PhaseClock& clock,
           PendingVolumes& volumes, PathSafetyResult& result) {
    kernels::OutputGridDesc desc{};
    const Eigen::Matrix3d axes = grid.geometry.index_to_physical_matrix();
    for (int a = 0; a < 3; ++a) {
      desc.origin[a] = grid.geometry.origin[a];
      for (int b = 0; b < 3; ++b) desc.axes[a][b] = axes(b, a);
    }
    desc.n = int(grid.geometry.dims[0]);
    desc.half = int(grid.half);
    desc.max_sq = grid.max_sq;
    if (options.mode == Mode::kFast) {
      run_fast(scene, fast_scene, grid, known, desc, options, clock, volumes, result);
      return;
    }
    desc.known = known;
    float* out[kernels::kValueCount] = {};
    kernels::CudaRunOptions cuda;
    cuda.wait_for_outputs = [&] {
      const auto t = std::chrono::steady_clock::now();
      volumes.collect(result);
      value_outputs(result, options.values, out);
      clock.phases.emplace_back(
          "allocate_wait",
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count());
    };
    cuda.storage = kernels::BlockingStorage::kGlobal;
    cuda.max_devices = options.max_gpus;
    cuda.progress = options.progress;
    const kernels::CudaRunReport report =
        kernels::run_path_safety_cuda(scene, desc, options.values, out, cuda);
    volumes.collect(result);  // when the backend failed before asking for them
    result.device = report.devices;
    result.phases = clock.phases;
    result.phases.insert(result.phases.end(), report.phases.begin(), report.phases.end());
  }

 private:
  // Fast mode: the scene uploaded once to every device, the grid sampled coarse to fine.
  // `scene` is exact mode's (the self-check's reference), `fast_scene` the one fast mode samples.
  void run_fast(const kernels::PathSafetyScene<double>& scene,
                const kernels::PathSafetyScene<double>& fast_scene, const OutputGrid& grid,
                const uint8_t* known, const kernels::OutputGridDesc& desc,
                const PathSafetyOptions& options, PhaseClock& clock, PendingVolumes& volumes,
                PathSafetyResult& result) {
    // Fast mode samples through a texture of halves (hardware filtering, relative L2 below 2e-3
    // against float filtering; bench/RESULTS.md, 2026-11-28); its self-check recomputes in global
    // memory, the exact definition, so that it measures the texture's difference too.
    // Both scenes go with the result (PathSafetyResult::device_memory): freed here, they would
    // wait for the kernels of a phase computed beside this one.
    struct Scenes {
      std::unique_ptr<kernels::CudaPointEvaluator> fast, reference;
    };
    const auto scenes = std::make_shared<Scenes>();
    scenes->fast = std::make_unique<kernels::CudaPointEvaluator>(
        fast_scene, desc, options.values, kernels::BlockingStorage::kTextureHalf,
        options.max_gpus);
    kernels::CudaPointEvaluator& evaluator = *scenes->fast;
    result.device_memory = scenes;
    clock.done("upload");
    volumes.collect(result);
    clock.done("allocate_wait");
    const auto evaluator_of = [](kernels::CudaPointEvaluator& e) -> PointEvaluator {
      return [&e](const std::vector<GridPoint>& points, std::vector<float>& out) {
        e.evaluate(&points.front().i, int64_t(points.size()), out.data());
      };
    };
    // The self-check's scene uploads, and its exact values are computed, on another thread while
    // the grid is sampled, rather than after it behind the rays of a phase computed beside this
    // one.
    std::future<CheckSample> exact;
    if (options.fast.check_voxels > 0) {
      exact = std::async(std::launch::async, [&] {
        scenes->reference = std::make_unique<kernels::CudaPointEvaluator>(
            scene, desc, options.values, kernels::BlockingStorage::kGlobal, options.max_gpus);
        return exact_check_sample(grid, known, options.fast.check_voxels,
                                  evaluator_of(*scenes->reference));
      });
    }
    run_adaptive(grid, known, options, evaluator_of(evaluator), result,
                 /*evaluator_on_device=*/true);
    clock.done("adaptive_sampling");
    double kernel_s = evaluator.kernel_seconds();
    if (exact.valid()) {
      auto sample = std::make_shared<const CheckSample>(exact.get());
      const unsigned values = options.values;
      result.check_sample = sample;
      result.pending_check = [sample, values](PathSafetyResult& r) {
        compare_with_check_sample(*sample, values, r);
      };
      if (!options.compare_check_later) finish_fast_check(result);
      clock.done("self_check");  // the wait for the exact values (and the comparison)
    }
    result.device = evaluator.devices() + " (texture)";
    result.phases.insert(result.phases.begin(), clock.phases.begin(), clock.phases.end());
    result.phases.emplace_back("gpu_kernels", kernel_s);
  }

  Device device_;
  std::shared_future<int> warm_up_;
  std::optional<int> count_;
};

void start_cuda_warm_up() { cuda_warm_up_once(); }
#else
void start_cuda_warm_up() {}

class CudaBackend {
 public:
  static constexpr const char* kNoDevice =
      "path safety device cuda: this build has no CUDA backend (rebuild with nvcc available)";
  explicit CudaBackend(Device) {}
  int device_count() { return 0; }
  void run(const kernels::PathSafetyScene<double>&, const kernels::PathSafetyScene<double>&,
           const OutputGrid&, const uint8_t*, const PathSafetyOptions&, PhaseClock&,
           PendingVolumes&, PathSafetyResult&) {
    throw Error("path safety: this build has no CUDA backend");
  }
};
#endif

// The device of a run: options.device, auto resolved to CUDA where a GPU is found.
Device choose_device(Device requested, CudaBackend& cuda) {
  const int gpus = requested == Device::kCpu ? 0 : cuda.device_count();
  if (requested == Device::kCuda && gpus == 0) throw Error(CudaBackend::kNoDevice);
  if (requested == Device::kAuto) return gpus > 0 ? Device::kCuda : Device::kCpu;
  return requested;
}

int thread_count(const PathSafetyOptions& options) {
  return options.threads > 0 ? options.threads : omp_get_max_threads();
}

void run_on_cpu(const kernels::PathSafetyScene<double>& scene, const OutputGrid& grid,
                const uint8_t* known, const PathSafetyOptions& options,
                PathSafetyResult& result) {
  result.threads = thread_count(options);
  result.device = "cpu";
  if (options.mode == Mode::kFast) {
    run_adaptive(grid, known, options,
                 cpu_point_evaluator(scene, grid, options.values, result.threads), result);
  } else {
    run_cpu(scene, grid, known, options.values, result.threads, result, options.progress);
  }
}

}  // namespace

void finish_fast_check(PathSafetyResult& result) {
  if (!result.pending_check) return;
  const auto check = std::move(result.pending_check);
  result.pending_check = nullptr;
  check(result);
}

RowRun roi_runs(const OutputGrid& grid, const Volume<float>& volume) {
  const Index3& d = grid.geometry.dims;
  if (grid.roi_voxels <= 0 || volume.geometry().dims != d) return {};
  return [&grid, ny = d[1]](int64_t row) { return grid.roi_run(row % ny, row / ny); };
}

const SafetyClasses& classes_of(PathSafetyResult& result, unsigned value_bit) {
  const size_t slot = size_t(kernels::value_slot(value_bit));
  std::optional<SafetyClasses>& c = result.classes[slot];
  if (!c) {
    const Volume<float>& volume = result.volumes[slot];
    ValueStatistics statistics;
    c = default_classes(value_bit, volume, &statistics, roi_runs(result.grid, volume));
    result.statistics[slot] = statistics;
  }
  return *c;
}

const ValueStatistics& statistics_of(PathSafetyResult& result, unsigned value_bit) {
  const size_t slot = size_t(kernels::value_slot(value_bit));
  if (!result.statistics[slot]) {
    const Volume<float>& volume = result.volumes[slot];
    result.statistics[slot] = value_statistics(volume, roi_runs(result.grid, volume));
  }
  return *result.statistics[slot];
}

int gpus_for(Device device) { return CudaBackend(device).device_count(); }

void start_device_warm_up(Device device) {
  if (device != Device::kCpu) start_cuda_warm_up();
}

PathSafetyResult compute_path_safety(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                                     const PathSafetyOptions& options,
                                     const std::string& blocking_source,
                                     const std::string& tumor_source) {
  const auto t0 = std::chrono::steady_clock::now();
  check_inputs(blocking, tumor, options, blocking_source, tumor_source);
  CudaBackend cuda(options.device);
  PhaseClock clock;
  validate_blocking(blocking, blocking_source);
  const TumorSurface mask_surface = extract_tumor_surface(tumor, tumor_source);
  refuse_implausible_tumor(blocking, tumor, mask_surface, tumor_source);
  check_tumor_inside_blocking(blocking, tumor, mask_surface, blocking_source, tumor_source);
  const OutputGrid grid = make_output_grid(blocking, tumor, mask_surface, options);
  check_memory(grid, options);

  // Rays as dense as the output grid: a mask finer than the tumor spacing is resampled to it.
  const double h = grid.geometry.spacing[0];
  const double tumor_spacing = options.tumor_spacing_mm > 0.0 ? options.tumor_spacing_mm : h;
  const bool resample =
      options.tumor_spacing_mm > 0.0 ||
      (options.tumor_spacing_mm < 0.0 &&
       tumor.geometry().spacing.minCoeff() < tumor_spacing * (1.0 - 1e-6));
  Volume<uint8_t> resampled;
  TumorSurface surface;
  if (resample) {
    resampled = resample_tumor(tumor, mask_surface, grid, tumor_spacing);
    if (std::any_of(resampled.data(), resampled.data() + resampled.geometry().voxel_count(),
                    [](uint8_t v) { return v != 0; })) {
      surface = extract_tumor_surface(resampled, tumor_source + " (resampled)");
    } else {
      spdlog::warn("{}: the tumor is smaller than one voxel of {:.2f} mm; its rays end on the "
                   "mask's own {} surface voxels",
                   tumor_source, tumor_spacing, mask_surface.points.size());
      resampled = Volume<uint8_t>();
    }
  }
  const bool resampled_used = resampled.geometry().voxel_count() > 0;
  const Volume<uint8_t>& ray_tumor = resampled_used ? resampled : tumor;
  if (!resampled_used) surface = mask_surface;
  if (resampled_used) {
    spdlog::info("tumor resampled from {:.2f} mm to {:.2f} mm: {} surface points instead of {}",
                 tumor.geometry().spacing.minCoeff(), tumor_spacing, surface.points.size(),
                 mask_surface.points.size());
  }
  clock.done("prepare");

  PathSafetyResult result = start_result(grid, surface, options);
  result.tumor_resampled = resampled_used;
  result.tumor_spacing_mm =
      resampled_used ? tumor_spacing : ray_tumor.geometry().spacing.minCoeff();
  result.mask_surface_points = int64_t(mask_surface.points.size());
  PendingVolumes volumes(grid.geometry, options.values);
  const Device device = choose_device(options.device, cuda);
  spdlog::info("path safety ({}): {} ROI voxels x {} surface points = {:.3g} rays (R = {:.1f} "
               "mm, h = {:.2f} mm) on {}",
               mode_name(options.mode), grid.roi_voxels, surface.points.size(),
               double(result.rays), grid.radius_mm, grid.geometry.spacing[0],
               device == Device::kCuda ? "cuda" : "cpu");
  // The scan's mask on the output grid, made on another thread while the bricks are.
  std::future<Volume<uint8_t>> scan_mask;
  if (options.coverage && !options.coverage->empty()) {
    scan_mask = std::async(std::launch::async,
                           [&] { return options.coverage->mask(grid.geometry); });
  }
  const std::vector<float> bricks = blocking_bricks(blocking);
  // The GPU's walks leap over the tumor's box; the cores' do not, where the extra work per
  // sample costs more than the samples it saves (bench/RESULTS.md, 2026-11-26).
  const std::vector<uint8_t> leaps = device == Device::kCuda
                                         ? tumor_leaps(ray_tumor, surface.lo, surface.hi)
                                         : std::vector<uint8_t>{};
  const auto scene =
      make_scene(blocking, ray_tumor, surface, result.gamma_mm, options.eps, bricks, leaps);
  // Fast mode casts one ray per block of the surface; exact mode's scene stays the self-check's
  // reference.
  TumorSurface fast_surface;
  kernels::PathSafetyScene<double> fast_scene = scene;
  if (options.mode == Mode::kFast) {
    result.fast.ray_stride = options.fast.ray_stride > 0
                                 ? options.fast.ray_stride
                                 : automatic_ray_stride(grid.geometry.spacing[0],
                                                        blocking.geometry().spacing.minCoeff());
    fast_scene.blocking_stride = result.fast.ray_stride;
    if (result.fast.ray_stride > 1) {
      spdlog::info("fast mode: the blocking volume sampled in runs of {} samples ({:.2f} mm), "
                   "each at its midpoint",
                   result.fast.ray_stride, result.fast.ray_stride * result.gamma_mm);
    }
  }
  if (options.mode == Mode::kFast && options.fast.surface_block > 1) {
    fast_surface = surface_representatives(surface, ray_tumor.geometry(),
                                           options.fast.surface_block);
    fast_scene = make_scene(blocking, ray_tumor, fast_surface, result.gamma_mm, options.eps,
                            bricks, leaps);
    fast_scene.blocking_stride = result.fast.ray_stride;
    result.fast.surface_points = int64_t(fast_surface.points.size());
    spdlog::info("fast mode: {} rays per voxel stand for the {} surface points (blocks of {}^3 "
                 "tumor voxels)",
                 fast_surface.points.size(), surface.points.size(), options.fast.surface_block);
  }
  clock.done("bricks");
  // Unknown is never computed: voxels outside the scan stay NaN (the plan marks them unknown).
  Volume<uint8_t> known_mask;
  if (scan_mask.valid()) {
    known_mask = scan_mask.get();
    clock.done("scan_mask");  // the wait for it beyond the bricks
  }
  const uint8_t* known = known_mask.geometry().voxel_count() > 0 ? known_mask.data() : nullptr;
  if (device == Device::kCuda) {
    cuda.run(scene, fast_scene, grid, known, options, clock, volumes, result);
  } else {
    volumes.collect(result);
    run_on_cpu(options.mode == Mode::kFast ? fast_scene : scene, grid, known, options, result);
  }
  result.scan_mask = std::move(known_mask);
  result.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  // Fast mode on the GPU checked itself there; otherwise the CPU recomputes the sample.
  if (options.mode == Mode::kFast && options.fast.check_voxels > 0 &&
      result.fast.check_voxels == 0 &&
      !result.pending_check) {
    const auto t = std::chrono::steady_clock::now();
    check_fast_mode(grid, known, options,
                    cpu_point_evaluator(scene, grid, options.values, thread_count(options)),
                    result);
    result.phases.emplace_back(
        "self_check", std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count());
  }
  return result;
}

}  // namespace crepuscular::planning
