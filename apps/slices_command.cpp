// `crepuscular slices`: 2D slice images of a plan for radiologists (PNG).
#include "apps/commands.hpp"
#include "apps/enum_names.hpp"
#include "pipelines/slices.hpp"
#include "planning/trajectories/evaluate.hpp"

namespace crepuscular::apps {

void add_slices_command(CLI::App& app) {
  auto req = std::make_shared<pipelines::SlicesRequest>();
  auto at = std::make_shared<std::string>();
  auto hide = std::make_shared<std::string>();
  CLI::App* cmd = app.add_subcommand(
      "slices",
      "Write 2D slice images (PNG) of a plan: the CT in a soft-tissue window, the path safety\n"
      "classes over it (green safe, yellow medium, red dangerous), outlines of the labelled\n"
      "structures and of the tumor, and the area safety contour: where the plane cuts the area\n"
      "safety geometry, a band on its outer side whose width (up to 10 mm in the patient) and\n"
      "colour show the leeway of the safe region; thin red lines where the extrusion stopped.\n"
      "Radiological convention: axial and coronal images show the patient's left on the image\n"
      "right; orientation letters, a scale bar and a legend are drawn on every image.\n"
      "Writes OUT/<plane>.png and OUT/slices.json (pixel <-> LPS mm of every image).\n"
      "Example:\n"
      "  crepuscular slices --plan demo/plan --ct demo/phantom/ct.nii.gz --out demo/slices");
  cmd->add_option("--plan", req->plan_dir, "Plan folder written by `crepuscular plan`")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--ct", req->ct, "CT in HU (NIfTI, NRRD, MetaImage or DICOM folder)")
      ->required()
      ->check(CLI::ExistingPath);
  cmd->add_option("--labels", req->labels,
                  "Label map whose structures are outlined (default: the plan's label map)")
      ->check(CLI::ExistingPath);
  add_series_option(cmd, req->series);
  cmd->add_option("--value", req->value,
                  "Path safety value shown: svv, isbv, ivbv or bvv (default: svv when the plan "
                  "has it, else its first value)");
  auto* at_opt = cmd->add_option("--at", *at,
                                 "Point the planes pass through, x,y,z in LPS mm (default: the "
                                 "tumor centre, or the region's centre with --region)");
  cmd->add_option("--region", req->region,
                  "Centre on safe area region K of the area safety geometry (0 = largest); the "
                  "oblique plane follows its main axis (default: none; oblique uses region 0)");
  cmd->add_option("--planes", req->planes, "Planes: any of axial,coronal,sagittal,oblique")
      ->delimiter(',')
      ->transform(enum_names(plane_names()))
      ->default_str("axial,coronal,sagittal");
  cmd->add_option("--palette", req->options.palette,
                  "default (green/yellow/red) or colorblind (blue to yellow)")
      ->transform(enum_names(palette_names()))
      ->default_str("default");
  cmd->add_option("--hide", *hide,
                  "Path safety classes not drawn: any of safe,medium,dangerous (default: none)")
      ->check(safety_class_list());
  cmd->add_option("--pixel", req->options.pixel_mm,
                  "Pixel size in mm (default: the finest spacing of the CT and the plan, divided "
                  "so that each image is at least 512 pixels wide)")
      ->check(in_range(0.01, 20));
  cmd->add_option("--window", req->options.window_width, "CT window width in HU")
      ->capture_default_str()
      ->check(finite_number(true));
  cmd->add_option("--level", req->options.window_level, "CT window level in HU")
      ->capture_default_str()
      ->check(finite_number());
  cmd->add_option("--opacity", req->options.overlay_opacity,
                  "Opacity of the path safety colours over the CT, 0..1")
      ->capture_default_str();
  cmd->add_option("--out", req->out_dir, "Output folder (replaced only when complete)")->required();
  auto overwrite = std::make_shared<bool>(false);
  add_overwrite_flag(cmd, *overwrite);
  cmd->callback([req, at, at_opt, hide, overwrite] {
    claim_run_paths({"slices",
                     {{"--plan", req->plan_dir}, {"--ct", req->ct}, {"--labels", req->labels}},
                     {{"--out", req->out_dir, OutputKind::kFolder}},
                     *overwrite});
    if (at_opt->count() > 0) {
      req->have_at = true;
      req->at = planning::parse_point(*at, "--at");
    }
    req->options.hidden = planning::parse_hidden_classes(*hide);
    pipelines::run_slices(*req);
  });
}

}  // namespace crepuscular::apps
