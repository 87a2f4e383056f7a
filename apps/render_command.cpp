// `crepuscular render`: the 3D planning view of a plan as a picture (no window needed).
#include "apps/commands.hpp"
#include "apps/enum_names.hpp"
#include "foundation/error.hpp"
#include "pipelines/render.hpp"

namespace crepuscular::apps {

void add_render_command(CLI::App& app) {
  auto req = std::make_shared<pipelines::RenderRequest>();
  auto hide = std::make_shared<std::string>("dangerous");
  auto size = std::make_shared<std::string>("1280x960");
  CLI::App* cmd = app.add_subcommand(
      "render",
      "Write the 3D planning view of a plan as a PNG picture, as `crepuscular view` shows it:\n"
      "the path safety volume rendered directly (green safe, yellow medium, red dangerous; grey\n"
      "where the scan does not reach: unknown, never safe), with the skin, bone (from the CT),\n"
      "the tumor (violet) and the vulnerable structures as translucent surfaces. Needs no\n"
      "display: EGL on a GPU, or Mesa's software renderer.\n"
      "Examples:\n"
      "  crepuscular render --plan demo/plan --ct demo/phantom/ct.nii.gz --view anterior \\\n"
      "      --out anterior.png\n"
      "  crepuscular render --plan demo/plan --view 30,20 --hide dangerous,skin --out 3d.png");
  cmd->add_option("--plan", req->plan_dir, "Plan folder written by `crepuscular plan`")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--ct", req->ct,
                  "CT in HU for the bone (default: the CT plan.json records, when present)")
      ->check(CLI::ExistingPath);
  cmd->add_option("--labels", req->labels,
                  "Label map of the body and the structures (default: the plan's)")
      ->check(CLI::ExistingPath);
  add_series_option(cmd, req->series);
  cmd->add_option("--view", req->view,
                  "Where the camera looks from, at the tumor: anterior, posterior, left, right, "
                  "superior, inferior, or AZ,EL in degrees (azimuth from anterior toward the "
                  "patient's left, elevation toward superior)")
      ->capture_default_str();
  cmd->add_option("--size", *size, "Picture size WxH in pixels")->capture_default_str();
  cmd->add_option("--value", req->options.value,
                  "Path safety value shown: svv, isbv, ivbv or bvv (default: svv when the plan "
                  "has it, else its first value)");
  cmd->add_option("--palette", req->options.palette,
                  "default (green/yellow/red) or colorblind (blue to yellow)")
      ->transform(enum_names(palette_names()))
      ->default_str("default");
  cmd->add_option("--hide", *hide,
                  "Not drawn: any of the classes safe,medium,dangerous,unknown and the surfaces "
                  "skin,bone,tumor,structures (anatomy: all surfaces); \"\" shows everything")
      ->capture_default_str();
  cmd->add_flag("--area-mesh", req->options.area_mesh,
                "Also the area safety mesh's vertices, coloured by the leeway of their safe "
                "region (dangerous colour where unsafe)");
  cmd->add_option("--opacity", req->options.opacity_scale,
                  "Absorption of the classes relative to the overlay's (1: the operating-room "
                  "video's, light)")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 100.0));
  cmd->add_option("--out", req->out, "PNG file (written whole or not at all)")->required();
  auto overwrite = std::make_shared<bool>(false);
  add_overwrite_flag(cmd, *overwrite);
  cmd->callback([req, hide, size, overwrite] {
    claim_run_paths({"render",
                     {{"--plan", req->plan_dir}, {"--ct", req->ct}, {"--labels", req->labels}},
                     {{"--out", req->out}},
                     *overwrite});
    parse_size(*size, req->width, req->height);
    pipelines::apply_hidden(*hide, req->options);
    pipelines::run_render(*req);
  });
}

}  // namespace crepuscular::apps
