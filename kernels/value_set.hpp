// Runtime value set (bits of PathSafetyValue) -> compile-time instantiation, shared by the CPU
// backend and the CUDA launchers so both instantiate the same 15 combinations. Host code only.
#pragma once

#include <type_traits>
#include <utility>

#include "foundation/error.hpp"
#include "kernels/path_safety_math.hpp"

namespace crepuscular::kernels {

// Calls f(std::integral_constant<unsigned, V>{}) with V == values; values must be in 1..15.
template <typename F>
void with_value_set(unsigned values, F&& f) {
  switch (values) {
#define CREPUSCULAR_VALUE_CASE(v) \
  case v:                         \
    return std::forward<F>(f)(std::integral_constant<unsigned, v>{});
    CREPUSCULAR_VALUE_CASE(1)
    CREPUSCULAR_VALUE_CASE(2)
    CREPUSCULAR_VALUE_CASE(3)
    CREPUSCULAR_VALUE_CASE(4)
    CREPUSCULAR_VALUE_CASE(5)
    CREPUSCULAR_VALUE_CASE(6)
    CREPUSCULAR_VALUE_CASE(7)
    CREPUSCULAR_VALUE_CASE(8)
    CREPUSCULAR_VALUE_CASE(9)
    CREPUSCULAR_VALUE_CASE(10)
    CREPUSCULAR_VALUE_CASE(11)
    CREPUSCULAR_VALUE_CASE(12)
    CREPUSCULAR_VALUE_CASE(13)
    CREPUSCULAR_VALUE_CASE(14)
    CREPUSCULAR_VALUE_CASE(15)
#undef CREPUSCULAR_VALUE_CASE
    default:
      throw Error("path safety: empty or unknown value set");
  }
}

}  // namespace crepuscular::kernels
