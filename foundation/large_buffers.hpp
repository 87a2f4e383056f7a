// Large buffers backed by transparent huge pages where the system offers them ("madvise" mode,
// as Debian's kernels default to). A fresh 513^3 float volume is 132 000 pages of 4 KiB, and the
// kernel's clearing of each on first touch costs a plan ~0.2 s per volume (bench/RESULTS.md,
// 2026-11-26, the headline's whole command under 5 s); as 2 MiB pages it is a few hundred faults.
#pragma once

#include <cstddef>
#include <vector>

namespace crepuscular {

// Asks the kernel to back [data, data + bytes) with huge pages (madvise MADV_HUGEPAGE on the whole
// pages inside it). Buffers under 4 MiB, and systems without it, are left as they are.
void advise_huge_pages(void* data, size_t bytes);

// v resized to n elements of `value`, its memory first reserved and advised (a vector already
// holding n or more elements' capacity is only assigned).
template <typename T>
void assign_large(std::vector<T>& v, size_t n, const T& value) {
  if (v.capacity() < n) {
    std::vector<T>().swap(v);
    v.reserve(n);
    advise_huge_pages(v.data(), n * sizeof(T));
  }
  v.assign(n, value);
}

}  // namespace crepuscular
