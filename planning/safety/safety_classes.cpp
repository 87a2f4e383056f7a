// Default safety classes and the comparison of two path safety results.
#include "planning/safety/safety_classes.hpp"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <utility>
#include <vector>

namespace crepuscular::planning {

namespace {

// Positive finite floats order as their bit patterns do; the top 16 bits name a bucket.
constexpr int kBucketShift = 16;
constexpr size_t kBuckets = size_t(1) << (32 - kBucketShift - 1);  // sign bit 0

bool counted(float x) { return std::isfinite(x) && x > 0.0f; }
uint32_t bucket_of(float x) {
  uint32_t bits;
  std::memcpy(&bits, &x, 4);
  return bits >> kBucketShift;
}

// The order statistics of a volume's positive finite values that default_classes_of takes by
// nth_element, found without copying the values: a parallel histogram of their top bits names the
// bucket that holds each rank, and only that bucket's values are gathered and ordered.
class PositiveValues {
 public:
  explicit PositiveValues(const std::vector<float>& values) : values_(values), cumulative_(kBuckets + 1, 0) {
    const int64_t n = int64_t(values.size());
    std::vector<uint64_t> histogram(kBuckets, 0);
#pragma omp parallel
    {
      std::vector<uint64_t> mine(kBuckets, 0);
      float most = 0.0f;
#pragma omp for schedule(static) nowait
      for (int64_t i = 0; i < n; ++i) {
        const float x = values[size_t(i)];
        if (!counted(x)) continue;
        ++mine[bucket_of(x)];
        most = std::max(most, x);
      }
#pragma omp critical
      {
        for (size_t b = 0; b < kBuckets; ++b) histogram[b] += mine[b];
        largest_ = std::max(largest_, most);
      }
    }
    for (size_t b = 0; b < kBuckets; ++b) cumulative_[b + 1] = cumulative_[b] + histogram[b];
  }
  uint64_t count() const { return cumulative_[kBuckets]; }
  float largest() const { return largest_; }

  // The value of rank i (0-based) in ascending order.
  float at_rank(uint64_t i) const {
    const size_t b = size_t(std::upper_bound(cumulative_.begin(), cumulative_.end(), i) -
                            cumulative_.begin()) - 1;
    // The bucket's values gathered on every core (a pass over the volume), then joined.
    const size_t threads = size_t(omp_get_max_threads());
    std::vector<std::vector<float>> parts(threads);
    const int64_t n = int64_t(values_.size());
#pragma omp parallel
    {
      std::vector<float>& mine = parts[size_t(omp_get_thread_num())];
#pragma omp for schedule(static) nowait
      for (int64_t v = 0; v < n; ++v) {
        const float x = values_[size_t(v)];
        if (counted(x) && bucket_of(x) == b) mine.push_back(x);
      }
    }
    std::vector<float> bucket;
    bucket.reserve(size_t(cumulative_[b + 1] - cumulative_[b]));
    for (const auto& part : parts) bucket.insert(bucket.end(), part.begin(), part.end());
    const size_t k = size_t(i - cumulative_[b]);
    std::nth_element(bucket.begin(), bucket.begin() + std::ptrdiff_t(k), bucket.end());
    return bucket[k];
  }

 private:
  const std::vector<float>& values_;
  std::vector<uint64_t> cumulative_;
  float largest_ = 0.0f;
};

}  // namespace

// The blocking values' classes from n positive values: the 20th and 60th percentile (the value of
// rank round(q (n - 1)), from at_rank) and the value `largest`. Blocking under a thousandth of the
// largest in the region (the far tails of a safety margin, a path grazing a structure) is no
// blocking: neither level sits among such values, where it would split voxels that differ by
// nothing a needle meets.
template <typename AtRank>
SafetyClasses blocking_classes(uint64_t n, double largest, const AtRank& at_rank) {
  const auto percentile = [&](double q) -> double {
    if (n == 0) return 0.0;
    return at_rank(std::min(n - 1, uint64_t(q * double(n - 1) + 0.5)));
  };
  SafetyClasses c;
  c.safe = std::max(percentile(0.2), kInsignificantShare * largest);
  c.dangerous = std::max(percentile(0.6), c.safe);
  return c;
}

SafetyClasses default_classes(unsigned value_bit, const Volume<float>& volume) {
  if (value_bit == kernels::kSvv) return default_classes_of(value_bit, {});
  const PositiveValues positive(volume.values());
  return blocking_classes(positive.count(), double(positive.largest()),
                          [&](uint64_t i) { return double(positive.at_rank(i)); });
}

SafetyClasses default_classes_of(unsigned value_bit, std::vector<float> values) {
  if (value_bit == kernels::kSvv) {
    SafetyClasses c;
    c.higher_is_safer = true;
    c.safe = 90.0;
    c.dangerous = 50.0;
    return c;
  }
  std::vector<float>& v = values;
  v.erase(std::remove_if(v.begin(), v.end(), [](float x) { return !counted(x); }), v.end());
  const double largest = v.empty() ? 0.0 : double(*std::max_element(v.begin(), v.end()));
  return blocking_classes(uint64_t(v.size()), largest, [&](uint64_t i) {
    std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(i), v.end());
    return double(v[size_t(i)]);
  });
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
