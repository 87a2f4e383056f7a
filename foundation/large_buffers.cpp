#include "foundation/large_buffers.hpp"

#include <sys/mman.h>
#include <unistd.h>

#include <cstdint>

namespace crepuscular {

void advise_huge_pages(void* data, size_t bytes) {
  constexpr size_t kAtLeast = size_t(4) << 20;
  if (data == nullptr || bytes < kAtLeast) return;
  const uintptr_t page = uintptr_t(sysconf(_SC_PAGESIZE));
  const uintptr_t begin = (uintptr_t(data) + page - 1) / page * page;
  const uintptr_t end = (uintptr_t(data) + bytes) / page * page;
  if (end <= begin) return;
  // Advice only: where the kernel has no transparent huge pages, the buffer keeps small ones.
  (void)madvise(reinterpret_cast<void*>(begin), end - begin, MADV_HUGEPAGE);
}

}  // namespace crepuscular
