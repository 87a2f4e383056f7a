// `crepuscular demo`: the whole offline job on the built-in phantom, written under demo/.
#include <spdlog/spdlog.h>

#include <filesystem>
#include <memory>
#include <string>

#include "apps/commands.hpp"
#include "planning/phantom.hpp"
#include "planning/plan.hpp"

namespace crepuscular::apps {

void add_demo_command(CLI::App& app) {
  auto out = std::make_shared<std::string>("demo");
  auto spacing = std::make_shared<double>(3.0);
  auto device = std::make_shared<std::string>("auto");
  auto mode = std::make_shared<std::string>("exact");
  auto radius = std::make_shared<double>(120.0);
  CLI::App* cmd = app.add_subcommand(
      "demo",
      "Run Crepuscular end to end on the built-in phantom: generate the phantom abdomen\n"
      "(DIR/phantom), then plan all four path safety values around its liver tumor (DIR/plan).\n"
      "Open DIR/phantom/ct.nii.gz with DIR/plan/path_safety_svv.nii.gz in 3D Slicer.");
  cmd->add_option("--out", *out, "Output folder")->capture_default_str();
  cmd->add_option("--spacing", *spacing, "Phantom voxel size in mm")->capture_default_str();
  cmd->add_option("--device", *device, "auto, cpu or cuda")->capture_default_str();
  cmd->add_option("--mode", *mode, "exact or fast (see `crepuscular plan --help`)")
      ->capture_default_str();
  cmd->add_option("--radius", *radius,
                  "Region of interest around the tumor, mm: the reach of a long needle. (The "
                  "plan's own default, the farthest voxel with any blocking, spans the whole "
                  "body here because muscle carries a low risk.)")
      ->capture_default_str();
  cmd->callback([out, spacing, device, mode, radius] {
    const std::string phantom_dir = *out + "/phantom";
    planning::PhantomOptions po;
    po.spacing_mm = *spacing;
    spdlog::info("demo: building the phantom ({} mm) in {}", *spacing, phantom_dir);
    planning::write_phantom(planning::make_phantom(po), phantom_dir);

    planning::PlanRequest req;
    req.labels = phantom_dir + "/labels.nii.gz";
    req.tumor = phantom_dir + "/tumor.nii.gz";
    req.vulnerability = phantom_dir + "/vulnerability.json";
    req.path_safety.device = planning::parse_device(*device);
    req.path_safety.mode = planning::parse_mode(*mode);
    req.path_safety.radius_mm = *radius;
    req.out_dir = *out + "/plan";
    spdlog::info("demo: planning path safety in {} (radius {} mm)", req.out_dir, *radius);
    planning::run_plan(req);
    spdlog::info("demo: done. Outputs: {}/phantom (ct, labels, tumor), {}/plan (path safety, area "
                 "safety)",
                 *out, *out);
  });
}

}  // namespace crepuscular::apps
