// Fuzz targets: every reader of data from outside (image headers, vulnerability tables, boards,
// scenes, camera/needle/registration YAML, frames.csv and poses CSV, markups, batch CSV,
// plan.json, area safety meshes, OpenIGTLink streams from a tracking server), each behind one
// function of the bytes of one file.
//
// The contract they check is docs/ARCHITECTURE.md §3's: a reader either accepts its file or refuses
// it with crepuscular::Error (a message naming the file). Any other exception, a crash, a hang or
// an allocation beyond the fuzzer's limit is a finding. The same functions run under libFuzzer
// (tests/fuzz/libfuzzer_main.cpp, scripts/fuzz.sh) and, through fuzz_corpus_test, over the
// corpus and every past finding in the ordinary test suite.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace crepuscular::fuzz {

struct FuzzTarget {
  const char* name;       // also the folder of its corpus: tests/fuzz/corpus/<name>/
  const char* file_name;  // what the bytes are written as (the reader looks at the extension)
  void (*read)(const std::string& path);
};

const std::vector<FuzzTarget>& fuzz_targets();
const FuzzTarget* find_fuzz_target(const std::string& name);

// Writes the bytes to this process's scratch folder as the target's file and runs its reader.
// Returns "" when the reader accepted the file, the message when it refused with
// crepuscular::Error; otherwise prints what escaped and aborts (which libFuzzer reports as a
// crash, and a test as a failure).
std::string run_fuzz_input(const FuzzTarget& target, const uint8_t* data, size_t size);

}  // namespace crepuscular::fuzz
