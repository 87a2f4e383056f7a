// The four path safety values as bits of a value set (docs/ARCHITECTURE.md §4) and their slots in
// per-voxel arrays. Host and device code.
#pragma once

#include "kernels/hd.hpp"

namespace crepuscular::kernels {

// Bits of the value set: which path safety values a pass computes.
enum PathSafetyValue : unsigned {
  kSvv = 1u,   // surface visibility value, %: high is safe
  kIsbv = 2u,  // integral surface blocking value: low is safe
  kIvbv = 4u,  // integral volume blocking value: low is safe
  kBvv = 8u,   // blocker volume value: low is safe
};
constexpr unsigned kAllValues = kSvv | kIsbv | kIvbv | kBvv;
constexpr int kValueCount = 4;
// Slot of a value in per-voxel result arrays (svv 0, isbv 1, ivbv 2, bvv 3).
CREPUSCULAR_HD constexpr int value_slot(unsigned bit) {
  return bit == kSvv ? 0 : bit == kIsbv ? 1 : bit == kIvbv ? 2 : 3;
}

}  // namespace crepuscular::kernels
