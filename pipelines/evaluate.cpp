// The evaluate job: the plan, the trajectories, their evaluations as text, JSON or CSV.
#include "pipelines/evaluate.hpp"

#include <nlohmann/json.hpp>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "planning/plan_folder/plan_folder.hpp"

namespace crepuscular::pipelines {

namespace {

std::vector<planning::Trajectory> trajectories_of(const EvaluateRequest& r,
                                                  const planning::PlanData& plan) {
  if (!r.batch.empty()) return planning::read_trajectories_csv(r.batch);
  if (!r.markup.empty()) return {planning::trajectory_from_markup(r.markup, plan.tumor_centre)};
  return {*r.trajectory};
}

}  // namespace

std::string run_evaluate(const EvaluateRequest& r) {
  if (!r.trajectory && r.markup.empty() && r.batch.empty()) {
    throw Error("evaluate: give a trajectory (entry and target), a line markup or a batch CSV");
  }
  planning::PlanLoadOptions load;
  load.labels_override = r.labels;
  load.series = r.series;
  const planning::PlanData plan = planning::load_plan(r.plan_dir, load);
  const planning::TrajectoryEvaluator evaluator(plan);
  const std::vector<planning::Trajectory> trajectories = trajectories_of(r, plan);
  nlohmann::json all = nlohmann::json::array();
  std::string text;
  for (size_t i = 0; i < trajectories.size(); ++i) {
    const auto e = evaluator.evaluate(trajectories[i]);
    if (r.json) {
      nlohmann::json one = planning::evaluation_json(e);
      // Inputs changed since planning travel with every answer, not only on stderr.
      one["changed_inputs"] = nlohmann::json::array();
      for (const auto& c : plan.changed_inputs) one["changed_inputs"].push_back(c.message);
      all.push_back(std::move(one));
    } else if (!r.batch.empty()) {
      if (i == 0) text += planning::evaluation_csv_header(e) + "\n";
      text += planning::evaluation_csv_row(e) + "\n";
    } else {
      text += planning::evaluation_text(e);
    }
  }
  if (r.json) text = (r.batch.empty() ? all[0] : all).dump(2) + "\n";
  if (!r.json && r.batch.empty()) {
    for (const auto& c : plan.changed_inputs) text = "WARNING: " + c.message + "\n" + text;
  }
  if (!r.out.empty()) {
    write_text_file(r.out, text);
    spdlog::info("{} trajectories evaluated: {}", trajectories.size(), r.out);
  }
  return text;
}

}  // namespace crepuscular::pipelines
