// `crepuscular area`: the area safety geometry (§3.3) alone, as a fast preview from the blocking
// volume or from an existing plan's path safety volume.
#include "apps/commands.hpp"
#include "pipelines/area.hpp"

namespace crepuscular::apps {

void add_area_command(CLI::App& app) {
  auto req = std::make_shared<pipelines::AreaRequest>();
  CLI::App* cmd = app.add_subcommand(
      "area",
      "Area safety, how much room each safe access region around the tumor leaves.\n"
      "The tumor is approximated by the ellipsoid of its principal axes; every vertex of a\n"
      "fine spherical grid on it is pushed outward along its normal until the maximum distance\n"
      "(safe) or the first unsafe point (unsafe). Connected safe vertices form regions; each\n"
      "region's size is the volume its part of the surface encloses, and its leeway is that size\n"
      "relative to the largest region (1 = the roomiest access).\n"
      "Two modes:\n"
      "  --preview   unsafe where the blocking volume (risk per mm, from --labels with\n"
      "              --vulnerability/--preset, or a ready --blocking volume) reaches a threshold.\n"
      "              Needs no path safety and runs in seconds, but sees only the straight rays\n"
      "              along the normals: a preview, not a replacement for `crepuscular plan`.\n"
      "  --plan DIR  unsafe where the plan's path safety value falls in the dangerous class\n"
      "              (or --unsafe medium, or past --threshold).\n"
      "Writes OUT/area_safety.vtk (VTK PolyData in LPS mm with per-vertex safe, region, leeway\n"
      "and extrusion_mm; open in 3D Slicer or ParaView and colour by leeway) and OUT/area.json\n"
      "(the regions: size, centre, main axis, leeway).\n"
      "Examples:\n"
      "  crepuscular area --preview --labels data/labels.nii.gz --preset phantom \\\n"
      "      --tumor data/tumor.nii.gz --out area_preview\n"
      "  crepuscular area --plan plan --out area_medium --unsafe medium");
  cmd->add_flag("--preview", req->preview,
                "Preview mode: unsafe where blocking >= --threshold; needs no plan");
  cmd->add_option("--plan", req->plan_dir,
                  "Plan folder (from `crepuscular plan`) whose path safety volume decides what is "
                  "unsafe (without --preview)")
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--tumor", req->tumor,
                  "Tumor mask (voxels > 0.5 are tumor) (default with --plan: the plan's tumor)")
      ->check(CLI::ExistingPath);
  cmd->add_option("--labels", req->labels,
                  "Preview: label map (NIfTI, NRRD, MetaImage or DICOM folder)")
      ->check(CLI::ExistingPath);
  cmd->add_option("--vulnerability", req->vulnerability,
                  "Preview: vulnerability table JSON (default: vulnerability.json beside the "
                  "label map)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--preset", req->preset,
                  "Preview: built-in vulnerability table: phantom, totalsegmentator")
      ->excludes("--vulnerability");
  cmd->add_option("--blocking", req->blocking,
                  "Preview: ready blocking volume (risk per mm) instead of --labels; needs "
                  "--threshold")
      ->check(CLI::ExistingPath);
  add_series_option(cmd, req->series);
  cmd->add_option("--margin", req->margin_fwhm_mm,
                  "Preview: safety margin around each labelled structure, FWHM in mm (0: none), "
                  "as in `crepuscular plan`")
      ->capture_default_str();
  cmd->add_option("--value", req->value,
                  "With --plan: path safety value to use: svv, isbv, ivbv or bvv (default: the "
                  "first the plan computed)");
  cmd->add_option("--unsafe", req->unsafe_class,
                  "With --plan: the class where the extrusion stops: dangerous, or medium "
                  "(medium and dangerous)")
      ->check(CLI::IsMember({"dangerous", "medium"}))
      ->capture_default_str();
  cmd->add_option("--threshold", req->threshold,
                  "Unsafe threshold. Preview: blocking per mm (default: the table's "
                  "second-lowest non-zero coefficient, i.e. everything above the lowest risk "
                  "level blocks; 0.1 for the phantom). With --plan: the path safety value "
                  "(svv: unsafe below it; others: above it) (default: the plan's class "
                  "threshold)")
      ->check(finite_number());
  cmd->add_option("--max-distance", req->max_distance_mm,
                  "Maximum extrusion along the normals, mm (default: the plan's region of "
                  "interest radius R; preview: 120 mm, the reach of a long needle)")
      ->check(in_range(0.1, 2000));
  cmd->add_option("--spacing", req->spacing_mm,
                  "Edge bound h in mm: no mesh edge longer than h when fully extruded; samples "
                  "every h/2 (default: the plan's spacing; preview: the smallest input spacing)")
      ->check(in_range(0.05, 20));
  cmd->add_option("--angle", req->angular_step_deg,
                  "Directions the mesh resolves, degrees: far from the tumor edges may grow to "
                  "max-distance x angle (1 degree: 1.7 mm per 100 mm, about a needle's width); "
                  "0: edges within h everywhere, as in the paper (much finer, slower)")
      ->check(in_range(0.0, 30.0))
      ->capture_default_str();
  cmd->add_option("--out", req->out_dir,
                  "Output folder for area_safety.vtk and area.json (replaced only when complete; "
                  "never a plan folder)")
      ->required();
  auto overwrite = std::make_shared<bool>(false);
  add_overwrite_flag(cmd, *overwrite);
  cmd->callback([req, overwrite] {
    claim_run_paths({"area",
                     {{"--plan", req->plan_dir},
                      {"--tumor", req->tumor},
                      {"--labels", req->labels},
                      {"--vulnerability", req->vulnerability},
                      {"--blocking", req->blocking}},
                     {{"--out", req->out_dir, OutputKind::kFolder}},
                     *overwrite});
    pipelines::run_area(*req);
  });
}

}  // namespace crepuscular::apps
