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
#include <itkConnectedComponentImageFilter.h>
#include <itkImage.h>

namespace crepuscular::planning {

namespace {

using MaskImage = itk::Image<uint8_t, 3>;
using ComponentImage = itk::Image<uint32_t, 3>;

std::string values_text(const std::vector<int32_t>& values) {
  return values.empty() ? "none (all 0)" : format_ranges(values);
}

// Per voxel the ITK component label (1..count, 0 outside), and the count.
std::vector<uint32_t> connected_components(const Volume<uint8_t>& mask, size_t& count) {
  auto image = MaskImage::New();
  set_image_geometry(*image, mask.geometry());
  image->Allocate();
  std::copy(mask.values().begin(), mask.values().end(), image->GetBufferPointer());
  using Filter = itk::ConnectedComponentImageFilter<MaskImage, ComponentImage>;
  auto cc = Filter::New();
  cc->SetInput(image);
  cc->SetFullyConnected(true);  // 26-connectivity
  try {
    cc->Update();
  } catch (const itk::ExceptionObject& e) {
    throw Error(std::string("lesions: connected components failed: ") + e.GetDescription());
  }
  count = size_t(cc->GetObjectCount());
  const uint32_t* p = cc->GetOutput()->GetBufferPointer();
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

std::vector<Lesion> find_lesions(const Volume<uint8_t>& mask, Volume<int32_t>* component_of) {
  const ImageGeometry& g = mask.geometry();
  size_t count = 0;
  const std::vector<uint32_t> comp = connected_components(mask, count);

  // Voxel count, first voxel and centroid (sum of indices) per ITK component.
  std::vector<int64_t> voxels(count + 1, 0);
  std::vector<int64_t> first(count + 1, std::numeric_limits<int64_t>::max());
  std::vector<Eigen::Vector3d> index_sum(count + 1, Eigen::Vector3d::Zero());
  for (int64_t v = 0; v < g.voxel_count(); ++v) {
    const uint32_t c = comp[size_t(v)];
    if (c == 0 || c > count) continue;
    ++voxels[c];
    first[c] = std::min(first[c], v);
    const Index3 ijk = g.index_of_offset(v);
    index_sum[c] += Eigen::Vector3d(double(ijk[0]), double(ijk[1]), double(ijk[2]));
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
  if (component_of != nullptr) {
    *component_of = Volume<int32_t>(g, 0);
    for (int64_t v = 0; v < g.voxel_count(); ++v) {
      const uint32_t c = comp[size_t(v)];
      (*component_of)[v] = c <= count ? rank_of[c] : 0;
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
  Volume<int32_t> rank_of;
  const std::vector<Lesion> lesions = find_lesions(mask, &rank_of);
  if (lesions.empty()) throw Error(what + ": the mask is empty (no voxel > 0)");
  const int count = int(lesions.size());
  const ImageGeometry& g = mask.geometry();

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
      if (g.contains(n[0], n[1], n[2]) && rank_of(n[0], n[1], n[2]) > 0) {
        chosen = rank_of(n[0], n[1], n[2]);
        break;
      }
      double best = std::numeric_limits<double>::infinity();
      for (int64_t v = 0; v < g.voxel_count(); ++v) {
        const int32_t r = rank_of[v];
        if (r == 0) continue;
        const Index3 ijk = g.index_of_offset(v);
        const double d = (g.index_to_physical(ijk[0], ijk[1], ijk[2]) - selection.point).norm();
        if (d < best || (d == best && r < chosen)) {
          best = d;
          chosen = r;
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
  for (int64_t v = 0; v < g.voxel_count(); ++v) out.mask[v] = rank_of[v] == chosen ? 1 : 0;
  return out;
}

}  // namespace crepuscular::planning
