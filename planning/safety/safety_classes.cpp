// Default safety classes, the classes as a label map and the comparison of two path safety
// results.
#include "planning/safety/safety_classes.hpp"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <utility>
#include <vector>

#include "foundation/error.hpp"
#include "planning/safety/unknown.hpp"

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

// The part [lo, hi) of the offsets [i, end) that lies in the run of i's row (all of it up to the
// row's end without runs), and where the next part starts (`next`: the row's end or `end`); rows
// are `row_length` voxels long. Walked part by part, [begin, end) in increasing order.
struct RunPart {
  int64_t lo, hi, next;
};
RunPart run_part(const RowRun& runs, int64_t row_length, int64_t i, int64_t end) {
  if (!runs) return {i, end, end};
  const int64_t row = i / row_length, start = row * row_length;
  const int64_t row_end = std::min(end, start + row_length);
  const auto [first, last] = runs(row);
  const int64_t lo = std::max(i, start + first), hi = std::min(row_end, start + last + 1);
  return {lo, std::max(lo, hi), row_end};
}

// The statistics of the finite values, on every core: thread(chunks) runs on each thread, and
// chunks(f) goes through the thread's share of the values calling f(x) for every finite one and
// returns its statistics without their sum. The sum is taken in chunks of fixed size added in
// order: the same mean, bit for bit, whatever the number of threads, and with or without `runs`
// (the values beyond them are NaN, which the sum leaves out either way).
template <typename Thread>
ValueStatistics scan_finite(const std::vector<float>& values, int64_t row_length,
                            const RowRun& runs, const Thread& thread) {
  constexpr int64_t kChunk = int64_t(1) << 18;
  const int64_t n = int64_t(values.size());
  const int64_t count = (n + kChunk - 1) / kChunk;
  std::vector<double> sums(size_t(count), 0.0);
  ValueStatistics all;
#pragma omp parallel
  {
    const auto chunks = [&](const auto& f) {
      ValueStatistics own;
#pragma omp for schedule(static) nowait
      for (int64_t c = 0; c < count; ++c) {
        double sum = 0.0;
        const int64_t end = std::min(n, (c + 1) * kChunk);
        for (int64_t at = c * kChunk; at < end;) {
          const RunPart part = run_part(runs, row_length, at, end);
          for (int64_t i = part.lo; i < part.hi; ++i) {
            const float x = values[size_t(i)];
            if (!std::isfinite(x)) continue;
            ++own.voxels;
            own.min = std::min(own.min, double(x));
            own.max = std::max(own.max, double(x));
            sum += x;
            f(x);
          }
          at = part.next;
        }
        sums[size_t(c)] = sum;
      }
      return own;
    };
    const ValueStatistics own = thread(chunks);
#pragma omp critical
    {
      all.voxels += own.voxels;
      all.min = std::min(all.min, own.min);
      all.max = std::max(all.max, own.max);
    }
  }
  for (const double s : sums) all.sum += s;
  return all;
}

// The order statistics of a volume's positive finite values that default_classes_of takes by
// nth_element, found without copying the values: a parallel histogram of their top bits names the
// bucket that holds each rank, and only that bucket's values are gathered and ordered.
class PositiveValues {
 public:
  // One pass: the histogram of the positive values, and the statistics of every finite one.
  PositiveValues(const std::vector<float>& values, int64_t row_length, const RowRun& runs)
      : values_(values), row_length_(row_length), runs_(runs), cumulative_(kBuckets + 1, 0) {
    std::vector<uint64_t> histogram(kBuckets, 0);
    statistics_ = scan_finite(values, row_length, runs, [&](const auto& chunks) {
      std::vector<uint64_t> mine(kBuckets, 0);
      ValueStatistics own = chunks([&](float x) {
        if (x > 0.0f) ++mine[bucket_of(x)];
      });
#pragma omp critical
      for (size_t b = 0; b < kBuckets; ++b) histogram[b] += mine[b];
      return own;
    });
    for (size_t b = 0; b < kBuckets; ++b) cumulative_[b + 1] = cumulative_[b] + histogram[b];
  }
  uint64_t count() const { return cumulative_[kBuckets]; }
  float largest() const { return count() > 0 ? float(statistics_.max) : 0.0f; }
  const ValueStatistics& statistics() const { return statistics_; }

  // The values of ranks i (0-based, ascending order), in one more pass over the volume: the
  // buckets that hold them gathered on every core, then each ordered.
  std::vector<float> at_ranks(const std::vector<uint64_t>& ranks) const {
    std::vector<size_t> buckets;
    for (const uint64_t i : ranks) buckets.push_back(bucket_of_rank(i));
    std::vector<size_t> wanted = buckets;
    std::sort(wanted.begin(), wanted.end());
    wanted.erase(std::unique(wanted.begin(), wanted.end()), wanted.end());
    const size_t threads = size_t(omp_get_max_threads());
    std::vector<std::vector<std::vector<float>>> parts(
        threads, std::vector<std::vector<float>>(wanted.size()));
    const int64_t n = int64_t(values_.size());
    constexpr int64_t kChunk = int64_t(1) << 16;
#pragma omp parallel
    {
      std::vector<std::vector<float>>& mine = parts[size_t(omp_get_thread_num())];
#pragma omp for schedule(static) nowait
      for (int64_t c = 0; c < n; c += kChunk) {
        const int64_t end = std::min(n, c + kChunk);
        for (int64_t at = c; at < end;) {
          const RunPart part = run_part(runs_, row_length_, at, end);
          for (int64_t v = part.lo; v < part.hi; ++v) {
            const float x = values_[size_t(v)];
            if (!counted(x)) continue;
            const size_t b = bucket_of(x);
            for (size_t w = 0; w < wanted.size(); ++w) {
              if (wanted[w] == b) mine[w].push_back(x);
            }
          }
          at = part.next;
        }
      }
    }
    std::vector<float> out;
    for (size_t r = 0; r < ranks.size(); ++r) {
      const size_t w = size_t(std::lower_bound(wanted.begin(), wanted.end(), buckets[r]) -
                              wanted.begin());
      std::vector<float> bucket;
      bucket.reserve(size_t(cumulative_[buckets[r] + 1] - cumulative_[buckets[r]]));
      for (const auto& part : parts) bucket.insert(bucket.end(), part[w].begin(), part[w].end());
      const size_t k = size_t(ranks[r] - cumulative_[buckets[r]]);
      std::nth_element(bucket.begin(), bucket.begin() + std::ptrdiff_t(k), bucket.end());
      out.push_back(bucket[k]);
    }
    return out;
  }

 private:
  size_t bucket_of_rank(uint64_t i) const {
    return size_t(std::upper_bound(cumulative_.begin(), cumulative_.end(), i) -
                  cumulative_.begin()) - 1;
  }

  const std::vector<float>& values_;
  int64_t row_length_;
  const RowRun& runs_;
  std::vector<uint64_t> cumulative_;
  ValueStatistics statistics_;
};

}  // namespace

// The blocking values' classes from n positive values: the 20th and 60th percentile (the value of
// rank round(q (n - 1)), from at_rank) and the value `largest`. Blocking under a thousandth of the
// largest in the region (the far tails of a safety margin, a path grazing a structure) is no
// blocking: neither level sits among such values, where it would split voxels that differ by
// nothing a needle meets.
template <typename AtRanks>
SafetyClasses blocking_classes(uint64_t n, double largest, const AtRanks& at_ranks) {
  SafetyClasses c;
  double p20 = 0.0, p60 = 0.0;
  if (n > 0) {
    const auto rank = [&](double q) { return std::min(n - 1, uint64_t(q * double(n - 1) + 0.5)); };
    const std::vector<float> v = at_ranks(std::vector<uint64_t>{rank(0.2), rank(0.6)});
    p20 = double(v[0]);
    p60 = double(v[1]);
  }
  c.safe = std::max(p20, kInsignificantShare * largest);
  c.dangerous = std::max(p60, c.safe);
  return c;
}

Volume<uint8_t> class_labels(const Volume<float>& values, const SafetyClasses& classes,
                             const Volume<uint8_t>& region) {
  const bool with_region = region.voxel_count() > 0;
  if (with_region && !region.geometry().same_grid(values.geometry(), 1e-6)) {
    throw Error("the voxel states (roi) lie on another grid than the path safety volume");
  }
  Volume<uint8_t> labels(values.geometry(), kNoClassLabel);
  const int64_t n = values.voxel_count();
  for (int64_t v = 0; v < n; ++v) {
    if (with_region && region[v] == kRegionUnknown) {
      labels[v] = class_label(SafetyClass::kUnknown);
    } else if (!std::isnan(values[v])) {
      labels[v] = class_label(classes.classify(values[v]));
    }
  }
  return labels;
}

ValueStatistics value_statistics(const Volume<float>& volume, const RowRun& runs) {
  return scan_finite(volume.values(), volume.geometry().dims[0], runs,
                     [](const auto& chunks) { return chunks([](float) {}); });
}

SafetyClasses default_classes(unsigned value_bit, const Volume<float>& volume,
                              ValueStatistics* statistics, const RowRun& runs) {
  if (value_bit == kernels::kSvv) {
    if (statistics) *statistics = value_statistics(volume, runs);
    return default_classes_of(value_bit, {});
  }
  const PositiveValues positive(volume.values(), volume.geometry().dims[0], runs);
  if (statistics) *statistics = positive.statistics();
  return blocking_classes(positive.count(), double(positive.largest()),
                          [&](const std::vector<uint64_t>& r) { return positive.at_ranks(r); });
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
  return blocking_classes(uint64_t(v.size()), largest, [&](const std::vector<uint64_t>& ranks) {
    std::vector<float> out;
    for (const uint64_t i : ranks) {
      std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(i), v.end());
      out.push_back(v[size_t(i)]);
    }
    return out;
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
