// `crepuscular plan`: blocking volume and path safety volumes from a segmentation and a tumor.
#include "apps/commands.hpp"
#include "apps/enum_names.hpp"
#include "pipelines/plan.hpp"
#include "planning/trajectories/evaluate.hpp"

namespace crepuscular::apps {

void add_plan_command(CLI::App& app) {
  auto req = std::make_shared<pipelines::PlanRequest>();
  auto values = std::make_shared<std::string>("all");
  CLI::App* cmd = app.add_subcommand(
      "plan",
      "Compute the path safety volume around a tumor.\n"
      "For every point in a ball around the tumor, all straight paths from that point to the\n"
      "tumor surface are traced through the blocking volume (risk per mm), and summarised as:\n"
      "  svv   surface visibility value: % of the visible tumor surface reachable with a line\n"
      "        integral of blocking <= eps (high = safe)\n"
      "  isbv  integral surface blocking value: sum of line integrals to the visible surface\n"
      "  ivbv  integral volume blocking value: line integrals weighted by tumor chord length\n"
      "  bvv   blocker volume value: blocking weighted by the volume each sample stands for\n"
      "        (isbv, ivbv, bvv: low = safe)\n"
      "Blocking comes from label maps and vulnerability tables (--labels, repeatable, with\n"
      "--vulnerability or --preset or a table per map), a ready blocking volume (--blocking), or\n"
      "CT thresholds (--ct alone). Voxels of the region of interest outside the scan (the\n"
      "inputs' grids) are UNKNOWN: no value, 2 in roi.nii.gz, never shown as safe.\n"
      "Writes PLAN_DIR/blocking.nii.gz, PLAN_DIR/path_safety_<value>.nii.gz (float32, LPS,\n"
      "NaN outside the region of interest; open in 3D Slicer), PLAN_DIR/area_safety.vtk (the\n"
      "safe access regions around the tumor and their leeway, for the first value; a model in\n"
      "3D Slicer or ParaView) and PLAN_DIR/plan.json.\n"
      "Examples:\n"
      "  crepuscular phantom --out data && crepuscular plan --labels data/labels.nii.gz \\\n"
      "      --tumor data/tumor.nii.gz --preset phantom --out plan\n"
      "  crepuscular plan --labels seg_total.nii.gz:totalsegmentator \\\n"
      "      --labels seg_vessels.nii.gz:totalsegmentator_liver_vessels \\\n"
      "      --tumor seg_vessels.nii.gz:2 --lesion 1 --ct ct.nii.gz --mode fast --out plan");
  cmd->add_option("--labels", req->labels,
                  "Label map FILE[:TABLE], repeatable: NIfTI, NRRD, MetaImage, DICOM folder, or a "
                  "3D Slicer segmentation (.seg.nrrd, segments matched to the table by name). "
                  "TABLE: a preset name or a vulnerability JSON (default: --vulnerability, "
                  "--preset, or vulnerability.json beside the map). Where maps overlap the higher "
                  "level wins");
  cmd->add_option("--tumor", req->tumor,
                  "Tumor FILE (a mask: voxels > 0.5) or FILE:LABEL (a label value, or a segment "
                  "name of a .seg.nrrd)")
      ->required();
  cmd->add_option("--lesion", req->lesion,
                  "Plan for the K-th largest lesion of the tumor mask (1 = largest); with several "
                  "lesions and neither --lesion nor --lesion-at, plan lists them and stops")
      ->check(CLI::PositiveNumber);
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
  cmd->add_option("--value", *values, "Values to compute: svv,isbv,ivbv,bvv or all")
      ->capture_default_str();
  cmd->add_option(
         "--eps", req->path_safety.eps,
         "Insignificant blocking for svv: a path whose line integral of blocking is <= eps is "
         "clear (0.5: 25 mm of muscle at 0.02/mm, or 0.5 mm of a vessel at 1/mm)")
      ->capture_default_str();
  cmd->add_option("--spacing", req->path_safety.spacing_mm,
                  "Output spacing in mm (default: smallest input spacing)");
  cmd->add_option("--radius", req->path_safety.radius_mm,
                  "Region of interest radius in mm (default: reaches the farthest voxel with "
                  "blocking > 0)");
  cmd->add_option("--margin", req->margin.fwhm_mm,
                  "Safety margin: FWHM in mm of the Gaussian added around each structure (0: none)")
      ->capture_default_str();
  cmd->add_option("--device", req->path_safety.device, "auto, cpu or cuda")
      ->transform(enum_names(device_names()))
      ->default_str("auto");
  cmd->add_option("--mode", req->path_safety.mode,
                  "exact: every ray marched (the reference); fast: rays cast once from each "
                  "tumor surface point and looked up by direction and distance. Fast mode "
                  "recomputes 1000 random voxels exactly and reports the difference in plan.json")
      ->transform(enum_names(mode_names()))
      ->default_str("exact");
  cmd->add_option("--threads", req->path_safety.threads, "CPU threads (default: all cores)");
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
                  "radius R)");
  cmd->add_flag("--crop-to-scan", req->crop_to_scan,
                "Leave the part of the region of interest outside the scan out (not computed) "
                "instead of marking it unknown");
  cmd->add_option("--out", req->out_dir, "Output plan folder (replaced only when complete)")
      ->required();
  cmd->callback([req, values, lesion_at] {
    req->path_safety.values = planning::parse_value_set(*values);
    if (!lesion_at->empty()) req->lesion_at = planning::parse_point(*lesion_at, "--lesion-at");
    pipelines::run_plan(*req);
  });
}

}  // namespace crepuscular::apps
