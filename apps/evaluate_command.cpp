// `crepuscular evaluate`: how safe is a chosen straight needle trajectory, according to a plan.
#include <spdlog/spdlog.h>

#include <cstdio>
#include <memory>
#include <string>

#include "apps/commands.hpp"
#include "kernels/error.hpp"
#include "planning/evaluate.hpp"
#include "planning/output_files.hpp"

namespace crepuscular::apps {

void add_evaluate_command(CLI::App& app) {
  struct Args {
    std::string plan, entry, target, trajectory, batch, labels, out;
    bool json = false;
  };
  auto a = std::make_shared<Args>();
  CLI::App* cmd = app.add_subcommand(
      "evaluate",
      "Evaluate a straight needle trajectory against a plan (the paper's retrospective\n"
      "gold-standard check): the line integral of blocking along the path (sampled as the path\n"
      "safety computation samples it), every labelled structure the path passes (level, depth\n"
      "from the entry, length inside), the path safety at the entry with its class and its rank\n"
      "in the region of interest, and the area safety region of the entry with its leeway\n"
      "relative to the largest region. Points in LPS mm (as DICOM, ITK and Slicer's LPS files).\n"
      "Give --entry and --target, a 3D Slicer line markup (--trajectory), or a CSV (--batch).\n"
      "Examples:\n"
      "  crepuscular evaluate --plan demo/plan --entry -150,-60,4 --target -92,-22,4\n"
      "  crepuscular evaluate --plan demo/plan --batch paths.csv > results.csv");
  cmd->add_option("--plan", a->plan, "Plan folder written by `crepuscular plan`")
      ->required()
      ->check(CLI::ExistingDirectory);
  auto* entry = cmd->add_option("--entry", a->entry, "Skin entry point x,y,z (LPS mm)");
  auto* target = cmd->add_option("--target", a->target, "Needle tip in the tumor x,y,z (LPS mm)");
  auto* traj = cmd->add_option("--trajectory", a->trajectory,
                               "3D Slicer line markup (.mrk.json, LPS or RAS); the control "
                               "point nearer the tumor centre is the target")
                   ->check(CLI::ExistingFile);
  auto* batch = cmd->add_option("--batch", a->batch,
                                "CSV with header name,entry_x,entry_y,entry_z,target_x,target_y,"
                                "target_z (LPS mm); writes one CSV row per trajectory to stdout")
                    ->check(CLI::ExistingFile);
  entry->needs(target);
  target->needs(entry);
  entry->excludes(traj)->excludes(batch);
  traj->excludes(batch);
  cmd->add_option("--labels", a->labels,
                  "Label map for the structures (default: the plan's label map)")
      ->check(CLI::ExistingPath);
  cmd->add_flag("--json", a->json, "Print JSON instead of text (batch: a JSON array)");
  cmd->add_option("--out", a->out,
                  "Write the result to this file (written whole or not at all) instead of "
                  "standard output");
  cmd->callback([a] {
    if (a->entry.empty() && a->trajectory.empty() && a->batch.empty()) {
      throw Error("evaluate: give --entry and --target, --trajectory or --batch");
    }
    planning::PlanLoadOptions load;
    load.labels_override = a->labels;
    const planning::PlanData plan = planning::load_plan(a->plan, load);
    const planning::TrajectoryEvaluator evaluator(plan);
    std::vector<planning::Trajectory> trajectories;
    if (!a->batch.empty()) {
      trajectories = planning::read_trajectories_csv(a->batch);
    } else if (!a->trajectory.empty()) {
      trajectories.push_back(planning::trajectory_from_markup(a->trajectory, plan.tumor_centre));
    } else {
      planning::Trajectory t;
      t.name = "trajectory";
      t.entry = planning::parse_point(a->entry, "--entry");
      t.target = planning::parse_point(a->target, "--target");
      trajectories.push_back(t);
    }
    nlohmann::json all = nlohmann::json::array();
    std::string text;
    for (size_t i = 0; i < trajectories.size(); ++i) {
      const auto e = evaluator.evaluate(trajectories[i]);
      if (a->json) {
        all.push_back(planning::evaluation_json(e));
      } else if (!a->batch.empty()) {
        if (i == 0) text += planning::evaluation_csv_header(e) + "\n";
        text += planning::evaluation_csv_row(e) + "\n";
      } else {
        text += planning::evaluation_text(e);
      }
    }
    if (a->json) text = (a->batch.empty() ? all[0] : all).dump(2) + "\n";
    if (a->out.empty()) {
      std::fputs(text.c_str(), stdout);
    } else {
      planning::write_text_file(a->out, text);
      spdlog::info("{} trajectories evaluated: {}", trajectories.size(), a->out);
    }
  });
}

}  // namespace crepuscular::apps
