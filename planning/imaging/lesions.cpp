// Lesions: a label's voxels, their connected components (ITK), ranked by size and chosen by rank or
// by a point.
#include "planning/imaging/lesions.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <set>
#include <string>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/text.hpp"
#include "planning/imaging/itk_image.hpp"

// ITK headers after ours (see volume_io.cpp): keep one Eigen (the system one) in this unit.
#ifndef ITK_USE_SYSTEM_EIGEN
#define ITK_USE_SYSTEM_EIGEN
#endif
#include <itkImage.h>

namespace crepuscular::planning {

namespace {

using MaskImage = itk::Image<uint8_t, 3>;

std::string values_text(const std::vector<int32_t>& values) {
  return values.empty() ? "none (all 0)" : format_ranges(values);
}

// Per voxel the ITK component label (1..count, 0 outside), and the count.
std::vector<uint32_t> connected_components(const Volume<uint8_t>& mask, size_t& count) {
  auto image = MaskImage::New();
  set_image_geometry(*image, mask.geometry());
  image->Allocate();
  std::copy(mask.values().begin(), mask.values().end(), image->GetBufferPointer());
  ComponentLabels components;
  try {
    components = label_components(image, true);  // 26-connectivity
  } catch (const itk::ExceptionObject& e) {
    throw Error(std::string("lesions: connected components failed: ") + e.GetDescription());
  }
  count = components.count;
  const uint32_t* p = components.image->GetBufferPointer();
  return std::vector<uint32_t>(p, p + mask.voxel_count());
}

}  // namespace

Volume<uint8_t> label_mask(const Volume<int32_t>& labels, int value, const std::string& source) {
  Volume<uint8_t> mask(labels.geometry(), 0);
  const int64_t n = labels.voxel_count();
  int64_t count = 0;
  for (int64_t v = 0; v < n; ++v) {
    const bool in = labels[v] == value;
    mask[v] = in ? 1 : 0;
    count += in;
  }
  if (count == 0) {
    const std::set<int32_t> present(labels.values().begin(), labels.values().end());
    std::vector<int32_t> nonzero;
    for (const int32_t x : present) {
      if (x != 0) nonzero.push_back(x);
    }
    throw Error(source + ": no voxel has label " + std::to_string(value) +
                " (labels present: " + values_text(nonzero) + ")");
  }
  return mask;
}

namespace {

// The box of a mask's voxels, copied out (a tumor's mask is mostly 0: its components are found
// in the box, the same components, counts and sums in the same order as over the whole grid).
Volume<uint8_t> crop(const Volume<uint8_t>& mask, const VoxelBox& box) {
  const ImageGeometry& g = mask.geometry();
  ImageGeometry b = g;
  b.dims = box.dims();
  b.origin = g.index_to_physical(box.lo[0], box.lo[1], box.lo[2]);
  Volume<uint8_t> out(b, 0);
#pragma omp parallel for schedule(static)
  for (int64_t k = 0; k < b.dims[2]; ++k) {
    for (int64_t j = 0; j < b.dims[1]; ++j) {
      std::copy_n(&mask(box.lo[0], box.lo[1] + j, box.lo[2] + k), b.dims[0], &out(0, j, k));
    }
  }
  return out;
}

// find_lesions over the mask's box: per box voxel the rank of its lesion in `rank_in_box`.
std::vector<Lesion> lesions_in_box(const Volume<uint8_t>& mask, const VoxelBox& box,
                                   Volume<int32_t>& rank_in_box) {
  const ImageGeometry& g = mask.geometry();
  const Volume<uint8_t> part = crop(mask, box);
  const ImageGeometry& pg = part.geometry();
  size_t count = 0;
  const std::vector<uint32_t> comp = connected_components(part, count);

  // Voxel count, first voxel (offset in the whole grid) and centroid (sum of the whole grid's
  // indices) per ITK component, in the whole grid's order.
  std::vector<int64_t> voxels(count + 1, 0);
  std::vector<int64_t> first(count + 1, std::numeric_limits<int64_t>::max());
  std::vector<Eigen::Vector3d> index_sum(count + 1, Eigen::Vector3d::Zero());
  for (int64_t k = 0, v = 0; k < pg.dims[2]; ++k) {
    for (int64_t j = 0; j < pg.dims[1]; ++j) {
      for (int64_t i = 0; i < pg.dims[0]; ++i, ++v) {
        const uint32_t c = comp[size_t(v)];
        if (c == 0 || c > count) continue;
        const Index3 ijk = {i + box.lo[0], j + box.lo[1], k + box.lo[2]};
        ++voxels[c];
        first[c] = std::min(first[c], g.offset(ijk[0], ijk[1], ijk[2]));
        index_sum[c] += Eigen::Vector3d(double(ijk[0]), double(ijk[1]), double(ijk[2]));
      }
    }
  }
  std::vector<uint32_t> order;
  for (uint32_t c = 1; c <= count; ++c) {
    if (voxels[c] > 0) order.push_back(c);
  }
  std::sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) {
    return voxels[a] != voxels[b] ? voxels[a] > voxels[b] : first[a] < first[b];
  });

  std::vector<Lesion> lesions;
  std::vector<int32_t> rank_of(count + 1, 0);
  for (size_t r = 0; r < order.size(); ++r) {
    const uint32_t c = order[r];
    Lesion l;
    l.rank = int(r + 1);
    l.voxels = voxels[c];
    l.volume_ml = double(voxels[c]) * g.voxel_volume_mm3() / 1000.0;
    l.centroid = g.index_to_physical(index_sum[c] / double(voxels[c]));
    lesions.push_back(l);
    rank_of[c] = l.rank;
  }
  rank_in_box = Volume<int32_t>(pg, 0);
  for (int64_t v = 0; v < pg.voxel_count(); ++v) {
    const uint32_t c = comp[size_t(v)];
    rank_in_box[v] = c <= count ? rank_of[c] : 0;
  }
  return lesions;
}

}  // namespace

std::vector<Lesion> find_lesions(const Volume<uint8_t>& mask, Volume<int32_t>* component_of) {
  const ImageGeometry& g = mask.geometry();
  const VoxelBox box = nonzero_box(mask);
  std::vector<Lesion> lesions;
  Volume<int32_t> rank_in_box;
  if (!box.empty()) lesions = lesions_in_box(mask, box, rank_in_box);
  if (component_of != nullptr) {
    *component_of = Volume<int32_t>(g, 0);
    const Index3 d = box.empty() ? Index3{0, 0, 0} : box.dims();
    for (int64_t k = 0; k < d[2]; ++k) {
      for (int64_t j = 0; j < d[1]; ++j) {
        std::copy_n(&rank_in_box(0, j, k), d[0],
                    &(*component_of)(box.lo[0], box.lo[1] + j, box.lo[2] + k));
      }
    }
  }
  return lesions;
}

std::string describe_lesions(const std::vector<Lesion>& lesions) {
  std::string s;
  for (const Lesion& l : lesions) {
    s += fmt::format("  #{}: {} voxels, {:.2f} mL, centroid ({:.1f}, {:.1f}, {:.1f}) mm LPS\n",
                     l.rank, l.voxels, l.volume_ml, l.centroid.x(), l.centroid.y(), l.centroid.z());
  }
  return s;
}

SelectedLesion select_lesion(const Volume<uint8_t>& mask, const LesionSelection& selection,
                             const std::string& what) {
  const VoxelBox box = nonzero_box(mask);
  if (box.empty()) throw Error(what + ": the mask is empty (no voxel > 0)");
  Volume<int32_t> rank_of;  // over the box
  const std::vector<Lesion> lesions = lesions_in_box(mask, box, rank_of);
  const int count = int(lesions.size());
  const ImageGeometry& g = mask.geometry();
  const Index3 d = box.dims();

  int chosen = 1;
  double distance = 0.0;
  switch (selection.kind) {
    case LesionSelection::Kind::kOnly:
      if (count > 1) {
        throw Error(what + ": " + std::to_string(count) +
                    " separate lesions (connected components); choose one by rank (1 = "
                    "largest) or by a point in it:\n" +
                    describe_lesions(lesions));
      }
      break;
    case LesionSelection::Kind::kRank:
      if (selection.rank < 1 || selection.rank > count) {
        throw Error(what + ": lesion " + std::to_string(selection.rank) + " requested, but there " +
                    (count == 1 ? "is 1 lesion" : "are " + std::to_string(count) + " lesions") +
                    " (expected 1 to " + std::to_string(count) + "):\n" +
                    describe_lesions(lesions));
      }
      chosen = selection.rank;
      break;
    case LesionSelection::Kind::kPoint: {
      if (!selection.point.allFinite()) throw Error(what + ": lesion point is not finite");
      const Index3 n = g.nearest_index(selection.point);
      const Index3 b = {n[0] - box.lo[0], n[1] - box.lo[1], n[2] - box.lo[2]};
      if (rank_of.geometry().contains(b[0], b[1], b[2]) && rank_of(b[0], b[1], b[2]) > 0) {
        chosen = rank_of(b[0], b[1], b[2]);
        break;
      }
      double best = std::numeric_limits<double>::infinity();
      for (int64_t k = 0, v = 0; k < d[2]; ++k) {
        for (int64_t j = 0; j < d[1]; ++j) {
          for (int64_t i = 0; i < d[0]; ++i, ++v) {
            const int32_t r = rank_of[v];
            if (r == 0) continue;
            const double dist = (g.index_to_physical(i + box.lo[0], j + box.lo[1], k + box.lo[2]) -
                                 selection.point)
                                    .norm();
            if (dist < best || (dist == best && r < chosen)) {
              best = dist;
              chosen = r;
            }
          }
        }
      }
      distance = best;
      break;
    }
  }

  SelectedLesion out;
  out.lesion = lesions[size_t(chosen - 1)];
  out.lesion_count = count;
  out.distance_mm = distance;
  out.mask = Volume<uint8_t>(g, 0);
  for (int64_t k = 0, v = 0; k < d[2]; ++k) {
    for (int64_t j = 0; j < d[1]; ++j) {
      uint8_t* row = &out.mask(box.lo[0], box.lo[1] + j, box.lo[2] + k);
      for (int64_t i = 0; i < d[0]; ++i, ++v) row[i] = rank_of[v] == chosen ? 1 : 0;
    }
  }
  return out;
}

}  // namespace crepuscular::planning
