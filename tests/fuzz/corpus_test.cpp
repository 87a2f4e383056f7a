// Every fuzz target over its corpus (tests/fuzz/corpus/<target>/) and over every input a fuzzing
// run found (tests/fuzz/findings/<target>/): each file is accepted or refused with
// crepuscular::Error, never a crash or another exception (run_fuzz_input aborts on those).
#include <gtest/gtest.h>
#include <spdlog/spdlog.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <set>

#include "foundation/error.hpp"
#include "tests/fuzz/targets.hpp"

namespace crepuscular::fuzz {
namespace {

namespace fs = std::filesystem;

std::vector<uint8_t> file_bytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

std::vector<fs::path> inputs_of(const std::string& target, const std::string& kind) {
  std::vector<fs::path> files;
  const fs::path folder = fs::path(CREPUSCULAR_FUZZ_DIR) / kind / target;
  if (!fs::is_directory(folder)) return files;
  for (const auto& entry : fs::directory_iterator(folder)) {
    if (entry.is_regular_file()) files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  return files;
}

class FuzzCorpus : public testing::TestWithParam<FuzzTarget> {
 protected:
  static void SetUpTestSuite() { spdlog::set_level(spdlog::level::off); }
  static void TearDownTestSuite() { spdlog::set_level(spdlog::level::info); }
};

TEST_P(FuzzCorpus, EveryCorpusFileAndFindingIsAcceptedOrRefusedWithAnError) {
  const FuzzTarget& target = GetParam();
  const std::vector<fs::path> corpus = inputs_of(target.name, "corpus");
  // A target without seeds would pass here without reading anything.
  ASSERT_GE(corpus.size(), 2u) << "tests/fuzz/corpus/" << target.name << " needs seed files";
  std::vector<fs::path> all = corpus;
  for (const fs::path& f : inputs_of(target.name, "findings")) all.push_back(f);
  int valid = 0;
  for (const fs::path& file : all) {
    SCOPED_TRACE(file.string());
    const std::vector<uint8_t> bytes = file_bytes(file);
    const std::string refusal = run_fuzz_input(target, bytes.data(), bytes.size());
    // Seeds named valid-* are real files of the format: the reader must accept them. Seeds
    // named refused-* hold what a reader must not pass over (a NaN voxel, a missing slice).
    if (file.filename().string().rfind("valid-", 0) == 0) {
      ++valid;
      EXPECT_EQ(refusal, "") << file << " is a valid seed but was refused";
    } else if (file.filename().string().rfind("refused-", 0) == 0) {
      EXPECT_NE(refusal, "") << file << " must be refused but was accepted";
    }
  }
  EXPECT_GE(valid, 1) << "tests/fuzz/corpus/" << target.name << " needs a valid-* seed";
}

INSTANTIATE_TEST_SUITE_P(Readers, FuzzCorpus, testing::ValuesIn(fuzz_targets()),
                         [](const testing::TestParamInfo<FuzzTarget>& info) {
                           return std::string(info.param.name);
                         });

TEST(FuzzCorpusLayout, EveryCorpusFolderBelongsToATarget) {
  for (const char* kind : {"corpus", "findings"}) {
    const fs::path folder = fs::path(CREPUSCULAR_FUZZ_DIR) / kind;
    if (!fs::is_directory(folder)) continue;
    for (const auto& entry : fs::directory_iterator(folder)) {
      EXPECT_NE(find_fuzz_target(entry.path().filename().string()), nullptr)
          << entry.path() << " names no fuzz target";
    }
  }
}

}  // namespace
}  // namespace crepuscular::fuzz
