// Several label maps combined into one (label map, table) pair: per voxel the highest level any map
// gives it, on the first map's grid (or a grid given), maps sampled at nearest voxels.
#include "planning/preprocessing/label_maps.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/log.hpp"

namespace crepuscular::planning {

namespace {

constexpr int kMaxLabelValue = 65535;

struct SharedLevel {
  VulnerabilityLevel level;
  std::string defined_by;  // source and table that defined it first
};

std::string number_text(double x) {
  std::ostringstream s;
  s << x;
  return s.str();
}

// Per label value of one map, the index of its level in `levels` (-1: background). Throws for a
// value present in the map but missing from its table.
std::vector<int> level_index_of_values(const LabelMapInput& in,
                                       const std::vector<SharedLevel>& levels) {
  std::vector<uint8_t> present(size_t(kMaxLabelValue) + 1, 0);
  const int32_t* p = in.labels->data();
  const int64_t n = in.labels->voxel_count();
  for (int64_t v = 0; v < n; ++v) {
    const int32_t x = p[v];
    if (x < 0 || x > kMaxLabelValue) {
      in.table->blocking_of_label(x, in.source);  // throws: not in the table
    } else {
      present[size_t(x)] = 1;
    }
  }
  std::vector<int> index(size_t(kMaxLabelValue) + 1, -1);
  for (int x = 1; x <= kMaxLabelValue; ++x) {
    if (!present[size_t(x)]) continue;
    in.table->blocking_of_label(x, in.source);  // throws for a value missing from the table
    const int level = in.table->find_label(x)->level;
    for (size_t k = 0; k < levels.size(); ++k) {
      if (levels[k].level.level == level) index[size_t(x)] = int(k);
    }
  }
  return index;
}

}  // namespace

CombinedLabels combine_label_maps(const std::vector<LabelMapInput>& inputs,
                                  const std::optional<ImageGeometry>& grid) {
  if (inputs.empty()) throw Error("label maps: none given (expected at least one)");
  for (const LabelMapInput& in : inputs) {
    if (in.labels == nullptr || in.table == nullptr) {
      throw Error("label maps: " + in.source + " has no label map or no table");
    }
    in.labels->geometry().validate(in.source);
    if (in.labels->values().size() != size_t(in.labels->voxel_count())) {
      throw Error(in.source + ": label map holds " + std::to_string(in.labels->values().size()) +
                  " values for " + std::to_string(in.labels->voxel_count()) + " voxels");
    }
  }

  // One scale of levels: the union by level number, coefficients checked.
  std::map<int, SharedLevel> by_number;
  for (const LabelMapInput& in : inputs) {
    for (const VulnerabilityLevel& l : in.table->levels) {
      const std::string here = in.source + " (table '" + in.table->name + "')";
      const auto [it, inserted] = by_number.emplace(l.level, SharedLevel{l, here});
      if (!inserted && it->second.level.blocking_per_mm != l.blocking_per_mm) {
        throw Error("label maps: level " + std::to_string(l.level) + " is '" +
                    it->second.level.name + "' with " +
                    number_text(it->second.level.blocking_per_mm) + " per mm for " +
                    it->second.defined_by + " but '" + l.name + "' with " +
                    number_text(l.blocking_per_mm) + " per mm for " + here +
                    " (expected tables on one scale: the same coefficient for a level number)");
      }
    }
  }
  std::vector<SharedLevel> levels;
  for (const auto& [number, shared] : by_number) levels.push_back(shared);

  CombinedLabels out;
  const ImageGeometry g = grid ? *grid : inputs.front().labels->geometry();
  g.validate("label maps: output grid");
  out.labels = Volume<int32_t>(g, 0);
  out.table.name = inputs.front().table->name;
  for (size_t i = 1; i < inputs.size(); ++i) out.table.name += " + " + inputs[i].table->name;
  for (size_t k = 0; k < levels.size(); ++k) {
    out.table.levels.push_back(levels[k].level);
    out.table.labels.push_back(
        {int(k + 1),
         "level " + std::to_string(levels[k].level.level) + " '" + levels[k].level.name + "'",
         levels[k].level.level});
  }

  int32_t* o = out.labels.data();
  const Index3& d = g.dims;
  for (const LabelMapInput& in : inputs) {
    const std::vector<int> index = level_index_of_values(in, levels);
    const ImageGeometry& m = in.labels->geometry();
    const int32_t* lab = in.labels->data();
    out.coverage.add(m, in.source);
    if (m.same_grid(g)) {
      const int64_t n = g.voxel_count();
#pragma omp parallel for schedule(static)
      for (int64_t v = 0; v < n; ++v) {
        const int k = lab[v] > 0 ? index[size_t(lab[v])] : -1;
        if (k + 1 > o[v]) o[v] = k + 1;
      }
      continue;
    }
    // Voxel centre of g -> continuous index in m: q = a * ijk + b.
    const Eigen::Matrix3d to_m = m.index_to_physical_matrix().inverse();
    const Eigen::Matrix3d a = to_m * g.index_to_physical_matrix();
    const Eigen::Vector3d b = to_m * (g.origin - m.origin);
    int64_t inside = 0;
#pragma omp parallel for schedule(static) reduction(+ : inside)
    for (int64_t k = 0; k < d[2]; ++k) {
      for (int64_t j = 0; j < d[1]; ++j) {
        for (int64_t i = 0; i < d[0]; ++i) {
          const Eigen::Vector3d q = a * Eigen::Vector3d(double(i), double(j), double(k)) + b;
          const int64_t mi = std::llround(q.x()), mj = std::llround(q.y()),
                        mk = std::llround(q.z());
          if (!m.contains(mi, mj, mk)) continue;
          ++inside;
          const int32_t x = lab[m.offset(mi, mj, mk)];
          const int level = x > 0 ? index[size_t(x)] : -1;
          int32_t& target = o[g.offset(i, j, k)];
          if (level + 1 > target) target = level + 1;
        }
      }
    }
    spdlog::debug("label maps: {} resampled (nearest voxel), {} of {} voxels of the grid inside it",
                  in.source, inside, g.voxel_count());
  }

  out.voxels_per_level.assign(levels.size(), 0);
  for (int64_t v = 0; v < g.voxel_count(); ++v) {
    if (o[v] > 0) ++out.voxels_per_level[size_t(o[v] - 1)];
  }
  for (size_t k = 0; k < levels.size(); ++k) {
    spdlog::debug("label maps: level {} '{}': {} voxels", levels[k].level.level,
                  levels[k].level.name, out.voxels_per_level[k]);
  }
  return out;
}

}  // namespace crepuscular::planning
