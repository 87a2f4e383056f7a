// Default safety classes and the comparison of two path safety results.
#include "planning/safety/safety_classes.hpp"

#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

namespace crepuscular::planning {

SafetyClasses default_classes(unsigned value_bit, const Volume<float>& volume) {
  std::vector<float> positive;
  if (value_bit != kernels::kSvv) {
    for (const float x : volume.values()) {
      if (std::isfinite(x) && x > 0.0f) positive.push_back(x);
    }
  }
  return default_classes_of(value_bit, std::move(positive));
}

SafetyClasses default_classes_of(unsigned value_bit, std::vector<float> values) {
  SafetyClasses c;
  if (value_bit == kernels::kSvv) {
    c.higher_is_safer = true;
    c.safe = 90.0;
    c.dangerous = 50.0;
    return c;
  }
  std::vector<float>& v = values;
  v.erase(std::remove_if(v.begin(), v.end(),
                         [](float x) { return !(std::isfinite(x) && x > 0.0f); }),
          v.end());
  const auto percentile = [&](double q) -> double {
    if (v.empty()) return 0.0;
    const size_t i = std::min(v.size() - 1, size_t(q * double(v.size() - 1) + 0.5));
    std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(i), v.end());
    return v[i];
  };
  // Blocking under a thousandth of the largest in the region (the far tails of a safety margin,
  // a path grazing a structure) is no blocking: neither level sits among such values, where it
  // would split voxels that differ by nothing a needle meets.
  const double largest = v.empty() ? 0.0 : double(*std::max_element(v.begin(), v.end()));
  const double insignificant = kInsignificantShare * largest;
  c.safe = std::max(percentile(0.2), insignificant);
  c.dangerous = std::max(percentile(0.6), c.safe);
  return c;
}

ModeDifference compare_volumes(const std::array<Volume<float>, kernels::kValueCount>& reference,
                               const std::array<Volume<float>, kernels::kValueCount>& other,
                               unsigned values) {
  ModeDifference d;
  for (int v = 0; v < kernels::kValueCount; ++v) {
    const unsigned bit = 1u << v;
    if (!(values & bit)) continue;
    const auto& a = reference[size_t(v)].values();
    const auto& b = other[size_t(v)].values();
    const SafetyClasses classes = default_classes(bit, reference[size_t(v)]);
    double diff2 = 0.0, ref2 = 0.0;
    int64_t n = 0, same = 0;
    for (size_t i = 0; i < a.size() && i < b.size(); ++i) {
      if (!std::isfinite(a[i]) || !std::isfinite(b[i])) continue;
      ++n;
      diff2 += double(a[i] - b[i]) * double(a[i] - b[i]);
      ref2 += double(a[i]) * double(a[i]);
      same += classes.classify(a[i]) == classes.classify(b[i]);
    }
    d.relative_l2[size_t(v)] = ref2 > 0.0 ? std::sqrt(diff2 / ref2) : std::sqrt(diff2);
    d.class_agreement[size_t(v)] = n > 0 ? double(same) / double(n) : 1.0;
    d.voxels = n;
  }
  return d;
}

}  // namespace crepuscular::planning
