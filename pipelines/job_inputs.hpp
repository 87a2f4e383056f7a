// What the planning jobs share: input checks that name the input's role (never a flag), the
// vulnerability table chosen for a label map, wall-clock timing.
#pragma once

#include <chrono>
#include <string>

#include "planning/preprocessing/vulnerability.hpp"

namespace crepuscular::pipelines {

// Throws Error "<path>: file does not exist (<role>)" when nothing exists at `path`.
void require_input(const std::string& path, const std::string& role);

struct ChosenTable {
  planning::VulnerabilityTable table;
  std::string source;  // the file, or "preset NAME"
};

// The vulnerability table of a label map: `table_file` when given, else the preset named, else
// vulnerability.json beside the label map. Throws Error naming the label map when there is none.
ChosenTable choose_vulnerability_table(const std::string& labels, const std::string& table_file,
                                       const std::string& preset);

using Clock = std::chrono::steady_clock;
inline double seconds_since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

}  // namespace crepuscular::pipelines
