// The view job: a plan in a window to look at from all sides, scroll through and try entry points
// on (paper §3.4: the 3D view and the 2D slices used together). Four panels (2x2): the 3D view
// (overlay/plan_view.hpp, the overlay's volume rendering from a planning camera) and axial,
// coronal and sagittal slices drawn by the same code as `crepuscular slices`
// (planning/views/slices.hpp); or the 3D view alone, or the slices alone. A click on the skin sets
// the entry of a trial path to the tumor centre (or to a second, Shift-click point); the path is
// drawn in every panel and evaluated as `crepuscular evaluate` does; a key saves it as a 3D Slicer
// line markup beside the plan.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <atomic>
#include <future>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "overlay/plan_view.hpp"
#include "overlay/renderer.hpp"
#include "pipelines/render.hpp"
#include "planning/trajectories/evaluate.hpp"
#include "planning/views/slices.hpp"

namespace crepuscular::pipelines {

enum class ViewLayout { kQuad, k3d, kSlices };
enum class ViewPanel { k3d = 0, kAxial, kCoronal, kSagittal };
inline constexpr int kViewPanels = 4;

struct ViewerOptions {
  overlay::PlanViewOptions view;
  planning::SliceOptions slices;  // window and level, opacity (palette and hidden follow `view`)
  int width = 1600, height = 900;
  ViewLayout layout = ViewLayout::kQuad;
  overlay::ViewAngles angles{30, 20};
  // false: drawn without a window (EGL), for benchmarks and tests without a display.
  bool window = true;
};

// The keys, one line each ("Tab  next path safety value"), as the window and --help list them.
const std::vector<std::string>& viewer_key_help();

class PlanViewer {
 public:
  // `inputs` must outlive the viewer. Opens the window (or the headless renderer). Throws Error
  // when no OpenGL context can be made or the plan cannot be shown. `full`: the plan with every
  // value and its blocking volume, for the other values and for evaluating paths (read meanwhile;
  // the first path waits for it).
  // `ct`: the CT still being read, when inputs.ct is empty (the slices and the bone follow it).
  PlanViewer(const ViewInputs& inputs, ViewerOptions options,
             std::future<planning::PlanData> full,
             std::future<planning::Volume<float>> ct = {});
  ~PlanViewer();
  PlanViewer(const PlanViewer&) = delete;
  PlanViewer& operator=(const PlanViewer&) = delete;

  // Handles the input since the last frame, redraws what changed and shows it. Returns false once
  // the window was closed or Escape pressed. `force`: redraw even when nothing changed.
  bool frame(bool force = false);
  // One input, as frame() handles it (tests may call it directly).
  void handle(const overlay::InputEvent& event);

  // --- State, for tests and benchmarks
  overlay::OrbitCamera& orbit() { return orbit_; }
  overlay::PlanView3D& view3d() { return *view_; }
  ViewLayout layout() const { return layout_; }
  // The panel's rectangle in the window (empty when not shown).
  cv::Rect panel_rect(ViewPanel panel) const;
  // The slice a panel shows (its image as `slices` draws it; empty without a CT).
  const planning::SliceView& slice(ViewPanel panel) const { return slices_[size_t(panel)]; }
  // The slice image's top-left pixel in the window.
  cv::Point slice_origin(ViewPanel panel) const;
  // The 3D panel's camera (image of the panel's size).
  calibration::CameraModel camera3d() const;
  // The point all three slices pass through (LPS mm).
  const Eigen::Vector3d& cursor() const { return cursor_; }
  const std::optional<Eigen::Vector3d>& entry() const { return entry_; }
  const Eigen::Vector3d& target() const { return target_; }
  // The trial path's evaluation (when an entry is set) and its text as shown.
  const std::optional<planning::TrajectoryEvaluation>& evaluation() const { return evaluation_; }
  std::string evaluation_text() const;
  // The last saved markup file ("" before the first).
  const std::string& saved_markup() const { return saved_markup_; }
  double slice_pixel_mm() const { return slice_options_.pixel_mm; }
  // What the window shows (the last frame), BGR of the window's size.
  cv::Mat picture();
  overlay::OverlayRenderer& renderer() { return *renderer_; }

  // Actions that keys and clicks trigger.
  void set_entry(const Eigen::Vector3d& entry);
  void set_target(const Eigen::Vector3d& target);
  void save_markup();
  // A picture of the window beside the plan (PLAN-view-NN.png).
  void save_picture();
  const std::string& saved_picture() const { return saved_picture_; }

 private:
  void place_panels();
  // Draws the slices (all, or only the third, the oblique one) at a pixel size at which each fits
  // its panel.
  void update_slices(bool all);
  void render_slices(const planning::SliceScene& scene, bool all);
  void update_layers();
  void evaluate();
  // Takes up the full plan once it has been read (`wait`: until then).
  void take_full_plan(bool wait);
  // Takes up the CT once it has been read: the anatomy and the slices follow it.
  void take_ct();
  // The CT into ct_ when it has been read (false when not yet, or unusable: ct_problem_).
  bool receive_ct();
  std::optional<ViewPanel> panel_at(double x, double y) const;
  // The LPS point under window pixel (x, y) of a panel: on the slice's plane, or, in the 3D panel,
  // where the ray first meets the body.
  std::optional<Eigen::Vector3d> point_at(ViewPanel panel, double x, double y) const;

  const ViewInputs& inputs_;
  ViewerOptions options_;
  std::unique_ptr<overlay::PlanView3D> view_;
  std::future<planning::PlanData> full_future_;
  std::future<planning::Volume<float>> ct_future_;
  std::unique_ptr<planning::Volume<float>> late_ct_;
  const planning::Volume<float>* ct_ = nullptr;  // the CT when read (inputs' or late_ct_)
  std::string ct_problem_;
  std::unique_ptr<planning::PlanData> full_;
  std::unique_ptr<planning::TrajectoryEvaluator> evaluator_;
  std::unique_ptr<overlay::OverlayRenderer> renderer_;
  bool software_ = false;
  ViewLayout layout_;
  overlay::OrbitCamera orbit_;
  std::array<cv::Rect, kViewPanels> panels_{};
  bool oblique_ = false;  // the third slice panel shows the oblique plane through the tumor
  Eigen::Vector3d cursor_ = Eigen::Vector3d::Zero();
  planning::SliceOptions slice_options_;
  std::array<planning::SliceView, kViewPanels> slices_{};
  std::array<uint64_t, kViewPanels> slice_revisions_{};
  std::array<cv::Mat, kViewPanels> slice_pictures_{};  // what the window shows of each slice
  cv::Mat help_picture_;
  std::optional<Eigen::Vector3d> entry_;
  Eigen::Vector3d target_ = Eigen::Vector3d::Zero();
  std::optional<planning::TrajectoryEvaluation> evaluation_;
  std::string saved_markup_, saved_picture_;
  std::string save_problem_;  // why the last save failed ("" when it did not)
  bool help_ = false, show_evaluation_ = true;
  bool dirty_ = true;
  bool moving_ = false, drawn_once_ = false;
  Eigen::Isometry3d drawn_pose_ = Eigen::Isometry3d::Identity();
  // Mouse: the button held, where it went down, and where it was last.
  int held_button_ = -1;
  int held_mods_ = 0;
  std::optional<ViewPanel> held_panel_;
  Eigen::Vector2d press_at_ = Eigen::Vector2d::Zero(), last_at_ = Eigen::Vector2d::Zero();
  bool dragged_ = false;
  bool open_ = true;
  uint64_t text_revision_ = 0;
};

struct ViewRequest {
  std::string plan_dir;
  std::string ct;
  std::string labels;
  std::vector<std::string> series;
  ViewerOptions options;
  const std::atomic<bool>* stop = nullptr;  // set by Ctrl-C
};

// Opens the view and runs it until the window closes: the first picture as soon as the shown value
// and the CT are read; every other value, the blocking volume and the inputs' checks meanwhile.
void run_view(const ViewRequest& request);

}  // namespace crepuscular::pipelines
