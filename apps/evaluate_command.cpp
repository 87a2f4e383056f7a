// `crepuscular evaluate`: how safe is a chosen straight needle trajectory, according to a plan.
#include <cstdio>

#include "apps/commands.hpp"
#include "foundation/error.hpp"
#include "pipelines/evaluate.hpp"

namespace crepuscular::apps {

void add_evaluate_command(CLI::App& app) {
  struct Args {
    pipelines::EvaluateRequest req;
    std::string entry, target;
  };
  auto a = std::make_shared<Args>();
  pipelines::EvaluateRequest& r = a->req;
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
  cmd->add_option("--plan", r.plan_dir, "Plan folder written by `crepuscular plan`")
      ->required()
      ->check(CLI::ExistingDirectory);
  auto* entry = cmd->add_option("--entry", a->entry, "Skin entry point x,y,z (LPS mm)");
  auto* target = cmd->add_option("--target", a->target, "Needle tip in the tumor x,y,z (LPS mm)");
  auto* traj = cmd->add_option("--trajectory", r.markup,
                               "3D Slicer line markup (.mrk.json, LPS or RAS); the control "
                               "point nearer the tumor centre is the target")
                   ->check(CLI::ExistingFile);
  auto* batch = cmd->add_option("--batch", r.batch,
                                "CSV with header name,entry_x,entry_y,entry_z,target_x,target_y,"
                                "target_z (LPS mm); writes one CSV row per trajectory to stdout")
                    ->check(CLI::ExistingFile);
  entry->needs(target);
  target->needs(entry);
  entry->excludes(traj)->excludes(batch);
  traj->excludes(batch);
  cmd->add_option("--labels", r.labels,
                  "Label map for the structures (default: the plan's label map)")
      ->check(CLI::ExistingPath);
  add_series_option(cmd, r.series);
  cmd->add_flag("--json", r.json, "Print JSON instead of text (batch: a JSON array)");
  cmd->add_option("--out", r.out,
                  "Write the result to this file (written whole or not at all) instead of "
                  "standard output");
  cmd->callback([a] {
    if (a->entry.empty() && a->req.markup.empty() && a->req.batch.empty()) {
      throw Error("evaluate: give --entry and --target, --trajectory or --batch");
    }
    const pipelines::EvaluateRequest& r = a->req;
    claim_run_paths({"evaluate",
                     {{"--plan", r.plan_dir},
                      {"--trajectory", r.markup},
                      {"--batch", r.batch},
                      {"--labels", r.labels}},
                     {{"--out", r.out}}});
    if (!a->entry.empty()) {
      planning::Trajectory t;
      t.name = "trajectory";
      t.entry = planning::parse_point(a->entry, "--entry");
      t.target = planning::parse_point(a->target, "--target");
      a->req.trajectory = t;
    }
    const std::string text = pipelines::run_evaluate(a->req);
    if (a->req.out.empty()) std::fputs(text.c_str(), stdout);
  });
}

}  // namespace crepuscular::apps
