// `crepuscular register`: the patient marker board's frame in the CT (T_ct_patient) from the
// board's CT-visible fiducials, found in the CT or read from Slicer markups.
#include "apps/commands.hpp"
#include "pipelines/registration.hpp"

namespace crepuscular::apps {

void add_register_command(CLI::App& app) {
  auto a = std::make_shared<pipelines::RegistrationRequest>();
  auto target = std::make_shared<std::vector<double>>();
  CLI::App* cmd = app.add_subcommand(
      "register",
      "Register the patient marker board to the CT (T_ct_patient) by its CT-visible fiducials.\n"
      "Fiducials are paired by the board's known layout (any order; missing and extra ones are\n"
      "tolerated), fitted rigidly (closed form, then a robust refinement); reports the FRE per\n"
      "fiducial and the expected TRE at the tumor. Mirrored, collinear and symmetric\n"
      "configurations are refused.");
  cmd->add_option("--ct", a->ct, "The CT (NIfTI, NRRD, MetaImage or a DICOM folder), LPS mm")
      ->required();
  add_series_option(cmd, a->series);
  cmd->add_option("--boards", a->boards,
                  "Marker boards (boards.json) with the patient board's fiducials; default: the "
                  "recording's boards.json");
  cmd->add_option("--board-name", a->board_name,
                  "The patient board (default: the board named \"patient\", else the first with "
                  "fiducials)");
  cmd->add_option("--ct-fiducials", a->ct_fiducials,
                  "Fiducials placed in 3D Slicer (.mrk.json, LPS or RAS); default: beads found "
                  "automatically in the CT");
  cmd->add_option("--points", a->points,
                  "Fiducial positions in the patient board frame (CSV x,y,z or label,x,y,z, mm); "
                  "default: the board definition's");
  cmd->add_option("--recording", a->recording,
                  "A recording in which the calibrated needle tip rests on each fiducial in turn "
                  "(digitises their board-frame positions; needs --needle)");
  cmd->add_option("--needle", a->needle, "Needle calibration (needle.yaml) for --recording");
  cmd->add_option("--camera", a->camera,
                  "Camera model for --recording (default: the recording's camera.yaml)");
  cmd->add_option("--tumor", a->tumor, "Tumor mask: the expected TRE is given at its centroid");
  cmd->add_option("--target", *target, "Or a point (LPS mm) for the expected TRE: --target=X,Y,Z")
      ->expected(3)
      ->delimiter(',');
  cmd->add_option("--fle-mm", a->fle_mm,
                  "Fiducial localisation error for the expected TRE (0: estimated from the FRE)")
      ->capture_default_str()
      ->check(in_range(0, 100));
  cmd->add_option("--threshold", a->threshold_hu,
                  "Automatic bead detection: beads are brighter than this (HU)")
      ->capture_default_str();
  cmd->add_option("--tolerance-mm", a->tolerance_mm,
                  "Pairing tolerance: fiducial distances and fitted positions agree this well")
      ->capture_default_str()
      ->check(in_range(0.001, 1000));
  cmd->add_option("--still-mm", a->still_mm,
                  "Digitising: the tip counts as resting while it stays within this distance")
      ->capture_default_str();
  cmd->add_option("--still-frames", a->still_frames,
                  "Digitising: frames the tip must rest to record a fiducial")
      ->capture_default_str();
  cmd->add_flag("--in-order", a->in_order,
                "Pair fiducials by their order (the CT list in the board's order) instead of by "
                "the layout: for symmetric layouts");
  cmd->add_option("--save-ct-fiducials", a->save_ct_fiducials,
                  "Also write the CT fiducials as a Slicer .mrk.json (to check them)");
  cmd->add_option("--out", a->out, "Registration file to write (YAML)")->capture_default_str();
  cmd->callback([a, target] {
    if (!target->empty()) a->target = Eigen::Vector3d((*target)[0], (*target)[1], (*target)[2]);
    claim_run_paths({"register",
                     {{"--ct", a->ct},
                      {"--boards", a->boards},
                      {"--ct-fiducials", a->ct_fiducials},
                      {"--points", a->points},
                      {"--recording", a->recording},
                      {"--needle", a->needle},
                      {"--camera", a->camera},
                      {"--tumor", a->tumor}},
                     {{"--out", a->out}, {"--save-ct-fiducials", a->save_ct_fiducials}}});
    pipelines::run_registration(*a);
  });
}

}  // namespace crepuscular::apps
