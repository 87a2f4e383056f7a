// The demo's report.md, section by section (Markdown).
#pragma once

#include <string>

#include "pipelines/demo_scenario.hpp"
#include "pipelines/guide.hpp"
#include "planning/plan_folder/plan_folder.hpp"

namespace crepuscular::pipelines {

// Title, the phantom and the plan: class shares of every value and the area safety regions.
std::string demo_plan_report(const planning::PlanData& plan, double spacing_mm,
                             const std::string& mode, double plan_s);

// The needle along the recording: both approaches, frames per needle safety class in each, the
// tracking and latency figures of the guidance run.
std::string demo_guidance_report(const GuidanceScenario& scenario, const GuideSummary& guide);

// Breathing plans: both approaches' path safety at the entry in every phase (the plan's
// per-phase volumes), the combination and the share of the region whose class changes; from the
// guidance run on the breathing recording, the phase estimated against the true one and the
// phases in which each approach's line was safe at its end.
std::string demo_breathing_report(const planning::PlanData& plan,
                                  const GuidanceScenario& scenario, const GuideSummary& guide);

// The list of files and the demo's duration.
std::string demo_files_report(bool guidance, double total_s);

}  // namespace crepuscular::pipelines
