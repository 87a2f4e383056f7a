// `crepuscular demo`: the whole job on the built-in data (pipelines/demo.hpp), written under
// demo/: phantom, plan, slice views, a synthetic recording guided headless, and report.md.
#include "apps/commands.hpp"
#include "apps/enum_names.hpp"
#include "pipelines/demo.hpp"
#include "planning/simulation/phantom.hpp"

namespace crepuscular::apps {

void add_demo_command(CLI::App& app) {
  auto a = std::make_shared<pipelines::DemoRequest>();
  CLI::App* cmd = app.add_subcommand(
      "demo",
      "Run Crepuscular end to end on the built-in data: build the phantom abdomen, plan all four\n"
      "path safety values and the area safety around its liver tumor, draw slice views, script a\n"
      "synthetic camera recording in which a tracked needle approaches the tumor first along a\n"
      "safe path and then along one that crosses a vessel, and guide it headless. DIR holds\n"
      "report.md, overlay.mp4, snapshots/, slices/, plan/ and phantom/ (open\n"
      "DIR/phantom/ct.nii.gz with DIR/plan/path_safety_svv.nii.gz in 3D Slicer).");
  cmd->add_option("--out", a->out_dir, "Output folder (replaced only when the demo completes)")
      ->capture_default_str();
  cmd->add_option("--spacing", a->spacing_mm, "Phantom voxel size in mm")->capture_default_str();
  cmd->add_option("--device", a->device, "auto, cpu or cuda")
      ->transform(enum_names(device_names()))
      ->default_str("auto");
  cmd->add_option("--mode", a->mode, "exact or fast (see `crepuscular plan --help`)")
      ->transform(enum_names(mode_names()))
      ->default_str("exact");
  cmd->add_option("--radius", a->radius_mm,
                  "Region of interest around the tumor, mm: the reach of a long needle. (The "
                  "plan's own default, the farthest voxel with any blocking, spans the whole "
                  "body here because muscle carries a low risk.)")
      ->capture_default_str();
  auto* mode_option = cmd->get_option("--mode");
  cmd->add_option("--breathing", a->breathing_phases,
                  "Breathing: make the phantom a cycle of N phases (10: a 4D CT; the anterior wall "
                  "rises with inhalation), plan svv over all of them with per-phase volumes (a "
                  "path is safe only if safe in every phase; fast mode unless --mode is given), "
                  "record a patient breathing 15 times a minute, guide phase by phase (the phase "
                  "from the patient board's motion) and report the phase estimate against the "
                  "truth and both approaches' safety per phase")
      ->check(in_range(2, 50, true));
  cmd->add_option("--amplitude", a->breathing_amplitude_mm,
                  "Breathing: cranio-caudal motion of the diaphragm's dome, mm")
      ->capture_default_str()
      ->check(in_range(0, planning::kMaxBreathingAmplitudeMm));
  cmd->add_flag("!--no-guidance", a->guidance,
                "Stop after the plan and the slice views (no recording, no overlay)");
  auto overwrite = std::make_shared<bool>(false);
  add_overwrite_flag(cmd, *overwrite);
  cmd->callback([a, mode_option, overwrite] {
    claim_run_paths({"demo", {}, {{"--out", a->out_dir, OutputKind::kFolder}}, *overwrite});
    if (a->breathing_phases > 0 && mode_option->count() == 0) a->mode = planning::Mode::kFast;
    pipelines::run_demo(*a);
  });
}

}  // namespace crepuscular::apps
