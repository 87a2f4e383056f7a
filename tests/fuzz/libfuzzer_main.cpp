// One libFuzzer program per target: CREPUSCULAR_FUZZ_TARGET names it (tests/fuzz/targets.cpp).
#include <spdlog/spdlog.h>

#include <cstdio>
#include <cstdlib>

#include "tests/fuzz/targets.hpp"

namespace {
const crepuscular::fuzz::FuzzTarget* target = nullptr;
}

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  spdlog::set_level(spdlog::level::off);  // readers' warnings would drown the fuzzer's lines
  target = crepuscular::fuzz::find_fuzz_target(CREPUSCULAR_FUZZ_TARGET);
  if (target == nullptr) {
    std::fprintf(stderr, "no fuzz target named %s\n", CREPUSCULAR_FUZZ_TARGET);
    std::exit(2);
  }
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  crepuscular::fuzz::run_fuzz_input(*target, data, size);
  return 0;
}
