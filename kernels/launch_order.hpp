// The order in which a launch's blocks of points start: the longest first.
//
// A point's thread casts a ray to every tumor surface point, so its work grows with its distance
// from the tumor: at the headline's 18 cm radius the far points take about ten times as long as
// the near ones. The card starts blocks in the order of their index; a launch whose far points
// come last ends with a few of them alone on the card while the other multiprocessors idle. A
// launch of fast mode's finer levels holds only one to six waves of blocks, so that tail is a good
// part of it. Started longest first, the short blocks fill the card's last wave instead (the
// classic longest-processing-time rule). Each point is still computed by one thread exactly as
// before: the values do not change, only when each block runs.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <vector>

namespace crepuscular::kernels {

// The blocks of `block` consecutive points (the last may be short) of `count` output grid indices
// `ijk` (3 per point, grid position origin + i axes[0] + j axes[1] + k axes[2] in mm), ordered by
// their estimated work, largest first: a point's work is taken as its distance from `centre` (the
// tumor's) plus `reach` (the mean distance of the surface from it, so that points at the tumor
// still count their rays). Ties keep their order. Returns the index of the block to start at each
// position.
inline std::vector<int32_t> blocks_longest_first(const int32_t* ijk, int64_t count, int block,
                                                 const double origin[3], const double axes[3][3],
                                                 const double centre[3], double reach) {
  const int64_t blocks = (count + block - 1) / block;
  std::vector<double> work(static_cast<size_t>(blocks), 0.0);
  for (int64_t b = 0; b < blocks; ++b) {
    const int64_t end = std::min<int64_t>(count, (b + 1) * block);
    double sum = 0.0;
    for (int64_t p = b * block; p < end; ++p) {
      const int32_t* q = ijk + 3 * p;
      double d2 = 0.0;
      for (int a = 0; a < 3; ++a) {
        const double x =
            origin[a] + q[0] * axes[0][a] + q[1] * axes[1][a] + q[2] * axes[2][a] - centre[a];
        d2 += x * x;
      }
      sum += std::sqrt(d2) + reach;
    }
    work[size_t(b)] = sum;
  }
  std::vector<int32_t> order(static_cast<size_t>(blocks));
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(),
                   [&work](int32_t a, int32_t b) { return work[size_t(a)] > work[size_t(b)]; });
  return order;
}

}  // namespace crepuscular::kernels
