// Input checks and the vulnerability table choice shared by the planning jobs.
#include "pipelines/job_inputs.hpp"

#include <filesystem>

#include "foundation/error.hpp"
#include "foundation/log.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {

void require_input(const std::string& path, const std::string& role) {
  std::error_code ec;
  if (!fs::exists(path, ec)) throw Error(path + ": file does not exist (" + role + ")");
}

ChosenTable choose_vulnerability_table(const std::string& labels, const std::string& table_file,
                                       const std::string& preset) {
  using planning::VulnerabilityTable;
  if (!table_file.empty()) return {VulnerabilityTable::load(table_file), table_file};
  if (!preset.empty()) return {VulnerabilityTable::preset(preset), "preset " + preset};
  const fs::path beside = fs::path(labels).parent_path() / "vulnerability.json";
  if (!fs::exists(beside)) {
    std::string presets;
    for (const auto& n : VulnerabilityTable::preset_names()) {
      presets += (presets.empty() ? "" : ", ") + n;
    }
    throw Error(labels + ": no vulnerability table: give a table file or a preset (" + presets +
                "), or put vulnerability.json beside the label map");
  }
  spdlog::info("using vulnerability table {}", beside.string());
  return {VulnerabilityTable::load(beside.string()), beside.string()};
}

}  // namespace crepuscular::pipelines
