// Safety classes of a path safety value (docs/ARCHITECTURE.md §4): safe, medium, dangerous, with
// thresholds per value, and the comparison of two path safety results (fast mode against exact).
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <functional>
#include <utility>
#include <vector>

#include "kernels/path_safety_math.hpp"
#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// kUnknown: no value (NaN): outside the region of interest or outside the scan. Never safe.
enum class SafetyClass { kSafe = 0, kMedium = 1, kDangerous = 2, kUnknown = 3 };

struct SafetyClasses {
  bool higher_is_safer = false;
  double safe = 0.0;       // safe: value <= safe (or >= safe when higher is safer)
  double dangerous = 0.0;  // dangerous: value > dangerous (or < dangerous when higher is safer)

  SafetyClass classify(double value) const {
    if (std::isnan(value)) return SafetyClass::kUnknown;
    if (higher_is_safer) {
      return value >= safe ? SafetyClass::kSafe
                           : value < dangerous ? SafetyClass::kDangerous : SafetyClass::kMedium;
    }
    return value <= safe ? SafetyClass::kSafe
                         : value > dangerous ? SafetyClass::kDangerous : SafetyClass::kMedium;
  }
};

// The classes as a label map, one label value per class: 0 none (outside the region of interest),
// then safe, medium, dangerous, unknown (1 to 4).
constexpr uint8_t kNoClassLabel = 0;
constexpr uint8_t class_label(SafetyClass c) { return uint8_t(int(c) + 1); }

// The class label of every voxel of `values`, on its grid: class_label(kUnknown) where `region`
// (RegionState of planning/safety/unknown.hpp, as roi.nii.gz stores it) holds kRegionUnknown,
// whatever the value; elsewhere class_label(classes.classify(value)) where the value is not NaN,
// and kNoClassLabel where it is. So an unknown voxel is never labelled safe. `region` empty: no
// voxel is unknown by its state. Throws Error when `region` is on another grid.
Volume<uint8_t> class_labels(const Volume<float>& values, const SafetyClasses& classes,
                             const Volume<uint8_t>& region);

// Defaults: SVV is a percentage (safe >= 90 %, dangerous < 50 %). The blocking values have no
// absolute scale, so they are relative to the region of interest: a voxel with no blocking on any
// path (value 0) is safe; among the voxels with some blocking, the lowest 20 % are safe too (the
// paper's "safest 20 % of the paths") and those above the 60th percentile are dangerous. Both
// levels are at least kInsignificantShare of the largest value in the region: values far below
// it are margin tails and grazing paths, not blocking.
constexpr double kInsignificantShare = 1e-3;

// A volume's finite values (NaN: not computed or unknown, left out): count, least, largest, sum.
struct ValueStatistics {
  int64_t voxels = 0;
  double min = INFINITY, max = -INFINITY, sum = 0.0;
};

// Where a volume's finite values may lie, row by row (a row: the voxels of one j and k, numbered
// j + k * ny): the first and last i of the row's run, none where first > last. Every voxel beyond
// the runs must be NaN (a path safety volume outside its region of interest, a ball): the passes
// below then read the runs alone, and give the same bits as reading every voxel.
using RowRun = std::function<std::pair<int64_t, int64_t>(int64_t row)>;

// `runs`: null, every voxel.
ValueStatistics value_statistics(const Volume<float>& volume, const RowRun& runs = {});

// With `statistics`, the volume's statistics too, from the same pass over it (a blocking value's
// classes take one more, for both percentiles; SVV's none but this one).
SafetyClasses default_classes(unsigned value_bit, const Volume<float>& volume,
                              ValueStatistics* statistics = nullptr, const RowRun& runs = {});
// The same rule over a sample of the region's values (NaN and values <= 0 are left out).
SafetyClasses default_classes_of(unsigned value_bit, std::vector<float> values);

// Difference of `other` from `reference` over the voxels both computed, per value slot.
struct ModeDifference {
  std::array<double, kernels::kValueCount> relative_l2{};      // |other - ref|_2 / |ref|_2
  std::array<double, kernels::kValueCount> class_agreement{};  // fraction with the same class
  int64_t voxels = 0;
};
// Classes are taken from the reference (default_classes) for both volumes.
ModeDifference compare_volumes(const std::array<Volume<float>, kernels::kValueCount>& reference,
                               const std::array<Volume<float>, kernels::kValueCount>& other,
                               unsigned values);

}  // namespace crepuscular::planning
