// `crepuscular plan`: blocking volume and path safety volumes from a segmentation and a tumor.
#include "apps/commands.hpp"
#include "apps/enum_names.hpp"
#include "apps/plan_help.hpp"
#include "pipelines/plan.hpp"
#include "planning/trajectories/evaluate.hpp"

namespace crepuscular::apps {

namespace {

// Inputs: label maps, tumor and lesion, tables, CT, blocking volume. Returns where --lesion-at goes.
std::shared_ptr<std::string> add_plan_inputs(CLI::App* cmd, pipelines::PlanRequest& r) {
  auto* req = &r;
  cmd->add_option("--labels", req->labels,
                  "Label map FILE[:TABLE], repeatable: NIfTI, NRRD, MetaImage, DICOM folder, or a "
                  "3D Slicer segmentation (.seg.nrrd, segments matched to the table by name). "
                  "TABLE: a preset name or a vulnerability JSON (default: --vulnerability, "
                  "--preset, or vulnerability.json beside the map). Where maps overlap the higher "
                  "level wins");
  cmd->add_option("--tumor", req->tumor,
                  "Tumor FILE (a mask: voxels > 0.5) or FILE:LABEL (a label value, or a segment "
                  "name of a .seg.nrrd); required unless --phases");
  cmd->add_option("--lesion", req->lesion,
                  "Plan for the K-th largest lesion of the tumor mask (1 = largest); with several "
                  "lesions and neither --lesion nor --lesion-at, plan lists them and stops")
      ->check(in_range(1, 100000, true));
  auto lesion_at = std::make_shared<std::string>();
  cmd->add_option("--lesion-at", *lesion_at,
                  "Plan for the lesion at (or nearest to) this point: X,Y,Z in LPS mm");
  cmd->add_option("--vulnerability", req->vulnerability,
                  "Vulnerability table JSON: label -> level -> blocking per mm "
                  "(default: vulnerability.json beside the label map)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--preset", req->preset,
                  "Built-in vulnerability table: phantom, totalsegmentator, "
                  "totalsegmentator_liver_vessels")
      ->excludes("--vulnerability");
  cmd->add_option("--ct", req->ct,
                  "CT in HU; thresholded (bone, internal air) when no labels are given");
  cmd->add_option("--blocking", req->blocking,
                  "Ready blocking volume (risk per mm, >= 0), used as is; the tumor mask may lie "
                  "on another grid")
      ->check(CLI::ExistingPath);
  add_series_option(cmd, req->series);
  cmd->add_option("--phases", req->phases,
                  "Breathing: phases.json listing one label map, tumor (and CT) per phase of the "
                  "respiratory cycle (crepuscular phantom --phases writes one). Path safety is "
                  "computed per phase on one grid and combined: safe only if safe in every phase "
                  "(svv the minimum, the others the maximum; unknown in any phase is unknown). "
                  "4D NIfTI inputs do the same without a list: --labels, --tumor and --ct may "
                  "hold the phases along their 4th axis (the same count in each 4D file; a 3D "
                  "input serves every phase)")
      ->check(CLI::ExistingFile);
  cmd->add_flag("--per-phase", req->per_phase,
                "With --phases or 4D inputs: also write each phase's volumes, "
                "path_safety_<value>_<phase>.nii.gz (evaluate then names the worst phase)");
  cmd->add_option("--phases-at-once", req->phases_at_once,
                  "With phases: how many phases are computed at once. Default (0): 3 on a GPU, "
                  "where one phase's host steps run beside the others' rays, 1 on the cores. In "
                  "fast mode a phase does not refine a class boundary where the phases computed "
                  "before it are already at least as unsafe (the combined class cannot change); "
                  "the log prints which phases each one waits for. Each phase at once holds its "
                  "volumes in memory (about 2.2 GB at 513^3)")
      ->check(CLI::Range(0, 4));
  return lesion_at;
}

// The method: values, eps, grid, margin, device, mode, threads.
void add_plan_method(CLI::App* cmd, pipelines::PlanRequest& r, std::string& value_set) {
  auto* req = &r;
  auto* values = &value_set;
  cmd->add_option("--value", *values, "Values to compute: svv,isbv,ivbv,bvv or all")
      ->capture_default_str();
  cmd->add_option(
         "--eps", req->path_safety.eps,
         "Insignificant blocking for svv: a path whose line integral of blocking is <= eps is "
         "clear (0.5: 25 mm of muscle at 0.02/mm, or 0.5 mm of a vessel at 1/mm)")
      ->capture_default_str();
  cmd->add_option("--spacing", req->path_safety.spacing_mm,
                  "Output spacing in mm (default: smallest input spacing)")
      ->check(in_range(0.05, 20));
  cmd->add_option("--tumor-spacing", req->path_safety.tumor_spacing_mm,
                  "Spacing in mm the tumor mask is resampled to before rays are cast to its "
                  "surface (default: the output spacing, where the mask is finer; 0: the mask's "
                  "own voxels). A plan's cost grows with the tumor's surface points, about "
                  "(tumor size / spacing)^2")
      ->check(in_range(0, 20))
      ->default_str("output spacing");
  cmd->add_option("--radius", req->path_safety.radius_mm,
                  "Region of interest radius in mm (default: reaches the farthest voxel with "
                  "blocking > 0)")
      ->check(in_range(0.1, 2000));
  cmd->add_option("--margin", req->margin.fwhm_mm,
                  "Safety margin: FWHM in mm of the Gaussian added around each structure (0: none)")
      ->capture_default_str()
      ->check(in_range(0, 50));
  cmd->add_option("--device", req->path_safety.device, "auto, cpu or cuda")
      ->transform(enum_names(device_names()))
      ->default_str("auto");
  cmd->add_option("--mode", req->path_safety.mode,
                  "exact: every ray marched (the reference). fast: the grid sampled coarse to "
                  "fine, a lattice about 8 mm apart first; voxels where the safety classes change "
                  "are computed, the inside of a region of one class is interpolated (on one "
                  "GPU about 10x faster than exact on a 513^3 grid at 0.7 mm, the same class on "
                  "99.9 % or more of the voxels). Fast mode recomputes --fast-check-voxels random "
                  "voxels exactly and reports the difference in plan.json (fast_mode_vs_exact)")
      ->transform(enum_names(mode_names()))
      ->default_str("exact");
  cmd->add_option("--fast-surface-block", req->path_safety.fast.surface_block,
                  "Fast mode: one ray per block of this many tumor voxels a side, cast to the "
                  "block's middle surface point and counted for each of its surface points (1: "
                  "every surface point, as exact mode; 2: about a third of the rays, 1.5-2.5x "
                  "faster, exact mode's class on only 98-99.5 % of the voxels: a first look)")
      ->capture_default_str()
      ->check(in_range(1, 4));
  cmd->add_option("--fast-ray-stride", req->path_safety.fast.ray_stride,
                  "Fast mode: blocking samples per quadrature point along each ray (1: every "
                  "sample, as exact mode; 2: pairs of samples taken at their midpoint, half the "
                  "samples; 0: automatic, runs of at most 1.05 mm and 1.5 blocking voxels: 3 at "
                  "0.7 mm spacing, 2 at 1 mm, 1 from 1.4 mm on)")
      ->capture_default_str()
      ->check(in_range(0, 4));
  cmd->add_option("--fast-check-voxels", req->path_safety.fast.check_voxels,
                  "Fast mode: random voxels of the region recomputed exactly to measure fast "
                  "mode's difference from exact mode (0: none)")
      ->capture_default_str()
      ->check(in_range(0, 1000000));
  cmd->add_option("--threads", req->path_safety.threads,
                  "CPU threads, 1 to 1024 (default: all cores)")
      ->check(in_range(1, 1024, true));
}

}  // namespace

void add_plan_command(CLI::App& app) {
  auto req = std::make_shared<pipelines::PlanRequest>();
  auto values = std::make_shared<std::string>("all");
  CLI::App* cmd = app.add_subcommand("plan", kPlanHelp);
  const auto lesion_at = add_plan_inputs(cmd, *req);
  add_plan_method(cmd, *req, *values);
  // Area safety (§3.3), after path safety, for the first computed value.
  cmd->add_flag("!--no-area", req->area_safety.enabled,
                "Skip the area safety step (by default it writes PLAN_DIR/area_safety.vtk: the "
                "tumor's ellipsoid extruded along its normals until an unsafe point, with safe "
                "regions and their leeway; see `crepuscular area --help`)");
  cmd->add_option("--area-unsafe", req->area_safety.unsafe_class,
                  "Area safety: the path safety class where the extrusion stops: dangerous, or "
                  "medium (medium and dangerous)")
      ->check(CLI::IsMember({"dangerous", "medium"}))
      ->capture_default_str();
  cmd->add_option("--area-threshold", req->area_safety.threshold,
                  "Area safety: stop where the path safety value is past this number instead "
                  "(svv: below it; isbv, ivbv, bvv: above it) (default: the class threshold)");
  cmd->add_option("--area-max-distance", req->area_safety.max_distance_mm,
                  "Area safety: maximum extrusion in mm (default: the region of interest "
                  "radius R)")
      ->check(in_range(0.1, 2000));
  cmd->add_option("--area-angle", req->area_safety.angular_step_deg,
                  "Area safety: directions the mesh resolves, degrees (edges up to h near the "
                  "tumor, max-distance x angle far from it; 0: h everywhere, much finer)")
      ->check(in_range(0.0, 30.0))
      ->capture_default_str();
  cmd->add_flag("--crop-to-scan", req->crop_to_scan,
                "Leave the part of the region of interest outside the scan out (not computed) "
                "instead of marking it unknown");
  cmd->add_option("--out", req->out_dir, "Output plan folder (replaced only when complete)")
      ->required();
  auto overwrite = std::make_shared<bool>(false);
  add_overwrite_flag(cmd, *overwrite);
  cmd->callback([req, values, lesion_at, overwrite] {
    RunPaths paths{"plan",
                   {{"--tumor", pipelines::tumor_file(req->tumor)},
                    {"--vulnerability", req->vulnerability},
                    {"--ct", req->ct},
                    {"--blocking", req->blocking},
                    {"--phases", req->phases}},
                   {{"--out", req->out_dir, OutputKind::kFolder}},
                   *overwrite};
    for (const std::string& file : pipelines::label_files(req->labels)) {
      paths.inputs.push_back({"--labels", file});
    }
    claim_run_paths(paths);
    req->path_safety.values = planning::parse_value_set(*values);
    if (!lesion_at->empty()) req->lesion_at = planning::parse_point(*lesion_at, "--lesion-at");
    pipelines::run_plan(*req);
  });
}

}  // namespace crepuscular::apps
