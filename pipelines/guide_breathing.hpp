// A breathing plan's phases for guidance (overlay::BreathingPhases): each phase's label map, tumor
// and blocking read again from the phase's inputs as plan.json records them, its path safety from
// the plan folder, its area safety (the plan's criterion) when the plan has one, and the skin's
// motion at the patient board.
#pragma once

#include <Eigen/Geometry>
#include <memory>

#include "overlay/guidance.hpp"
#include "planning/plan_folder/plan_folder.hpp"

namespace crepuscular::pipelines {

// nullptr for a plan without phases; a breathing plan made without per-phase volumes (plan
// --per-phase) is guided by its combination, which is said in the log. T_ct_patient: the
// registration, which places the patient board on the skin of phase 0. Throws Error naming the
// file or the field when a phase's input cannot be read or the board does not lie on the skin.
std::unique_ptr<overlay::BreathingPhases> load_breathing_phases(const planning::PlanData& plan,
                                                                const Eigen::Isometry3d& T_ct_patient);

}  // namespace crepuscular::pipelines
