// The render job: the 3D planning view of a plan (overlay/plan_view.hpp) as a picture, without a
// window (EGL on a GPU or Mesa), for reports; and the plan inputs that `render` and `view` share.
#pragma once

#include <future>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "overlay/plan_view.hpp"
#include "planning/plan_folder/plan_folder.hpp"

namespace crepuscular::pipelines {

// A plan with what its views show: one path safety value (`value`, else svv when computed, else
// the first), region states, labels, tumor, area safety, and the CT (`ct`, else the one plan.json
// records, when present), read side by side. `check_inputs`: compare the plan's inputs with their
// checksums (a full read of each).
struct ViewInputs {
  planning::PlanData plan;
  planning::Volume<float> ct;  // empty without one
  std::string ct_path;
};
ViewInputs load_view_inputs(const std::string& plan_dir, const std::string& ct,
                            const std::string& labels, const std::vector<std::string>& series,
                            const std::string& value, bool check_inputs = true);

// The same, with the CT still being read (the plan's first picture need not wait for it): `ct` is
// invalid without one. load_view_inputs is this with the CT taken.
struct ViewStart {
  ViewInputs inputs;  // inputs.ct empty
  std::future<planning::Volume<float>> ct;
};
ViewStart start_view_inputs(const std::string& plan_dir, const std::string& ct,
                            const std::string& labels, const std::vector<std::string>& series,
                            const std::string& value, bool check_inputs = true);

// Everything evaluating a path needs: every value, the blocking volume, labels and tumor, area
// safety, with the inputs checked.
planning::PlanData load_full_plan(const std::string& plan_dir, const std::string& labels,
                                  const std::vector<std::string>& series);

// Draws the legend on a picture of the 3D view (BGR): the value, where the camera looks from, the
// classes shown with their colours, and the surfaces.
void draw_view_legend(cv::Mat& bgr, const overlay::PlanView3D& view,
                      const overlay::ViewAngles& angles);

// One picture of the view from `angles`, width x height, with its legend (headless renderer).
cv::Mat render_plan_view(overlay::PlanView3D& view, const overlay::ViewAngles& angles, int width,
                         int height);

// "--hide" of `render` and `view`: any of safe, medium, dangerous, unknown (classes), skin, bone,
// tumor, structures (surfaces), anatomy (every surface); sets the options' hidden flags. Throws
// Error naming an unknown word.
void apply_hidden(const std::string& list, overlay::PlanViewOptions& options);

struct RenderRequest {
  std::string plan_dir;
  std::string ct;
  std::string labels;
  std::vector<std::string> series;
  std::string view = "anterior";
  int width = 1280, height = 960;
  overlay::PlanViewOptions options;
  std::string out;  // PNG, written whole or not at all
};

// Writes the picture; throws Error naming the input or output that is unusable.
void run_render(const RenderRequest& request);

}  // namespace crepuscular::pipelines
