// `crepuscular view`: a plan in a window, in 3D and in slices, to try entry points on.
#include "apps/commands.hpp"
#include "apps/enum_names.hpp"
#include "foundation/error.hpp"
#include "pipelines/plan_viewer.hpp"

namespace crepuscular::apps {

void add_view_command(CLI::App& app) {
  auto req = std::make_shared<pipelines::ViewRequest>();
  auto hide = std::make_shared<std::string>("dangerous");
  auto size = std::make_shared<std::string>("1600x900");
  auto layout = std::make_shared<std::string>("2x2");
  auto angles = std::make_shared<std::string>("30,20");
  std::string keys;
  for (const auto& k : pipelines::viewer_key_help()) keys += "  " + k + "\n";
  CLI::App* cmd = app.add_subcommand(
      "view",
      "Look at a plan in a window, in 3D and in slices, and try entry points on it: the 3D view\n"
      "(the path safety volume rendered directly, green safe, yellow medium, red dangerous, grey\n"
      "unknown where the scan does not reach; skin, bone, tumor and structures as translucent\n"
      "surfaces) and axial, coronal and sagittal slices drawn as `crepuscular slices` draws\n"
      "them. Click on the skin to try an entry: the path to the tumor centre is drawn in every\n"
      "panel and evaluated as `crepuscular evaluate` does (line integral, structures crossed with\n"
      "depth, class, relative area safety); M saves it as a 3D Slicer line markup beside the plan\n"
      "(PLAN-trajectory-NN.mrk.json), P a picture of the window (PLAN-view-NN.png).\n"
      "Keys (also shown in the window):\n" +
          keys +
          "Example:\n"
          "  crepuscular view --plan demo/plan --ct demo/phantom/ct.nii.gz");
  cmd->add_option("--plan", req->plan_dir, "Plan folder written by `crepuscular plan`")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--ct", req->ct,
                  "CT in HU for the slices and the bone (default: the CT plan.json records)")
      ->check(CLI::ExistingPath);
  cmd->add_option("--labels", req->labels, "Label map (default: the plan's)")
      ->check(CLI::ExistingPath);
  add_series_option(cmd, req->series);
  cmd->add_option("--value", req->options.view.value,
                  "Path safety value shown first (Tab switches): svv, isbv, ivbv or bvv");
  cmd->add_option("--palette", req->options.view.palette,
                  "default (green/yellow/red) or colorblind (blue to yellow); C switches")
      ->transform(enum_names(palette_names()))
      ->default_str("default");
  cmd->add_option("--hide", *hide,
                  "Hidden at first: any of the classes safe,medium,dangerous,unknown and the "
                  "surfaces skin,bone,tumor,structures (anatomy: all surfaces); \"\" for none")
      ->capture_default_str();
  cmd->add_option("--layout", *layout, "2x2 (3D and three slices), 3d or slices; L switches")
      ->capture_default_str()
      ->check(CLI::IsMember({"2x2", "3d", "slices"}));
  cmd->add_option("--view", *angles,
                  "Where the 3D camera looks from at first: anterior, posterior, left, right, "
                  "superior, inferior or AZ,EL in degrees")
      ->capture_default_str();
  cmd->add_option("--size", *size, "Window size WxH in pixels")->capture_default_str();
  cmd->add_option("--window", req->options.slices.window_width, "CT window width in HU")
      ->capture_default_str()
      ->check(finite_number(true));
  cmd->add_option("--level", req->options.slices.window_level, "CT window level in HU")
      ->capture_default_str()
      ->check(finite_number());
  cmd->callback([req, hide, size, layout, angles] {
    parse_size(*size, req->options.width, req->options.height);
    req->options.layout = *layout == "3d"       ? pipelines::ViewLayout::k3d
                          : *layout == "slices" ? pipelines::ViewLayout::kSlices
                                                : pipelines::ViewLayout::kQuad;
    req->options.angles = overlay::parse_view_angles(*angles);
    pipelines::apply_hidden(*hide, req->options.view);
    req->stop = stop_on_signals();
    pipelines::run_view(*req);
  });
}

}  // namespace crepuscular::apps
