// `crepuscular view` in a real window under Xvfb, driven by input events sent through the X
// server: its slices against `crepuscular slices`' images pixel for pixel, a click on the skin and
// on a slice against the LPS point under it, a key hiding a class, the evaluation against
// `crepuscular evaluate`'s, and the saved line markup.
#include "pipelines/plan_viewer.hpp"

#include <X11/Xlib.h>
#include <X11/Xutil.h>
#include <X11/keysym.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <thread>

#include "pipelines/evaluate.hpp"
#include "pipelines/plan.hpp"
#include "pipelines/slices.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/trajectories/markups.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"
#include "tests/support/xvfb_environment.hpp"

namespace crepuscular::pipelines {
namespace {

namespace fs = std::filesystem;

// The mini plan with air anterior of y = 17 mm (label 0 on j < 4): the skin is that plane.
constexpr double kSkinY = 17.0;

class PlanViewerTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    folder_ = new test::TemporaryFolder();
    test::MiniPlanOptions mo;
    mo.ct = true;
    const test::MiniPlanInputs in = test::write_mini_plan_inputs(folder_->path(), mo);
    auto labels = planning::read_volume<int32_t>(in.labels);
    for (int64_t k = 0; k < labels.dims()[2]; ++k)
      for (int64_t j = 0; j < 4; ++j)
        for (int64_t i = 0; i < labels.dims()[0]; ++i) labels(i, j, k) = 0;
    planning::write_volume(labels, in.labels);
    run_plan(in.request((folder_->path() / "plan").string()));
    plan_dir_ = new std::string((folder_->path() / "plan").string());
    ct_ = new std::string(in.ct);
    // One connection for the whole suite: an X server resets when its last client leaves, and
    // refuses connections meanwhile.
    for (int attempt = 0; attempt < 50 && !display_; ++attempt) {
      display_ = XOpenDisplay(nullptr);
      if (!display_) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  }
  static void TearDownTestSuite() {
    if (display_) XCloseDisplay(display_);
    display_ = nullptr;
    delete folder_;
    delete plan_dir_;
    delete ct_;
  }

  // The window's X id (GLFW names it "Crepuscular"); 0 when not found.
  static Window find_window(Display* d, Window w) {
    char* name = nullptr;
    if (XFetchName(d, w, &name) && name) {
      const bool match = std::strcmp(name, "Crepuscular") == 0;
      XFree(name);
      if (match) return w;
    }
    Window root = 0, parent = 0, *children = nullptr;
    unsigned n = 0;
    if (!XQueryTree(d, w, &root, &parent, &children, &n)) return 0;
    Window found = 0;
    for (unsigned i = 0; i < n && !found; ++i) found = find_window(d, children[i]);
    if (children) XFree(children);
    return found;
  }

  void SetUp() override {
    ASSERT_NE(display_, nullptr) << "no X display (Xvfb)";
    inputs_ = std::make_unique<ViewInputs>(load_view_inputs(*plan_dir_, *ct_, "", {}, ""));
    ViewerOptions o;
    o.width = 1200;
    o.height = 800;
    o.angles = overlay::ViewAngles{0, 0};  // from anterior: the skin plane faces the camera
    o.view.resolution_scale = 1.0;
    viewer_ = std::make_unique<PlanViewer>(
        *inputs_, o, std::async(std::launch::async, load_full_plan, *plan_dir_, "",
                                std::vector<std::string>{}));
    viewer_->frame(true);
    window_ = find_window(display_, DefaultRootWindow(display_));
    ASSERT_NE(window_, 0u);
  }
  void TearDown() override { viewer_.reset(); }

  // Runs frames until `done` or 3 s.
  template <typename Done>
  bool frames_until(Done done) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(3);
    while (std::chrono::steady_clock::now() < end) {
      viewer_->frame();
      if (done()) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return false;
  }

  // A left click (Shift held when `shift`) at window pixel (x, y), as the X server delivers one.
  void click(int x, int y, bool shift = false) {
    XWarpPointer(display_, None, window_, 0, 0, 0, 0, x, y);
    XSync(display_, False);
    for (const int type : {ButtonPress, ButtonRelease}) {
      XEvent e{};
      e.xbutton.type = type;
      e.xbutton.display = display_;
      e.xbutton.window = window_;
      e.xbutton.root = DefaultRootWindow(display_);
      e.xbutton.x = x;
      e.xbutton.y = y;
      e.xbutton.button = Button1;
      e.xbutton.state = (shift ? ShiftMask : 0) | (type == ButtonRelease ? Button1Mask : 0);
      e.xbutton.same_screen = True;
      XSendEvent(display_, window_, True, ButtonPressMask | ButtonReleaseMask, &e);
      XSync(display_, False);
      viewer_->frame();
    }
  }

  void key(KeySym symbol) {
    for (const int type : {KeyPress, KeyRelease}) {
      XEvent e{};
      e.xkey.type = type;
      e.xkey.display = display_;
      e.xkey.window = window_;
      e.xkey.root = DefaultRootWindow(display_);
      e.xkey.keycode = XKeysymToKeycode(display_, symbol);
      e.xkey.same_screen = True;
      XSendEvent(display_, window_, True, KeyPressMask | KeyReleaseMask, &e);
      XSync(display_, False);
    }
  }

  static test::TemporaryFolder* folder_;
  static std::string* plan_dir_;
  static std::string* ct_;
  static Display* display_;
  Window window_ = 0;
  std::unique_ptr<ViewInputs> inputs_;
  std::unique_ptr<PlanViewer> viewer_;
};
test::TemporaryFolder* PlanViewerTest::folder_ = nullptr;
std::string* PlanViewerTest::plan_dir_ = nullptr;
std::string* PlanViewerTest::ct_ = nullptr;
Display* PlanViewerTest::display_ = nullptr;

TEST_F(PlanViewerTest, SlicesEqualTheSlicesCommandPixelForPixel) {
  SlicesRequest sr;
  sr.plan_dir = *plan_dir_;
  sr.ct = *ct_;
  sr.have_at = true;
  sr.at = viewer_->cursor();
  sr.options.pixel_mm = viewer_->slice_pixel_mm();
  sr.out_dir = (folder_->path() / "slices").string();
  fs::remove_all(sr.out_dir);
  run_slices(sr);
  const cv::Mat window = viewer_->renderer().screenshot_window();
  const std::pair<ViewPanel, const char*> panels[] = {{ViewPanel::kAxial, "axial"},
                                                     {ViewPanel::kCoronal, "coronal"},
                                                     {ViewPanel::kSagittal, "sagittal"}};
  for (const auto& [panel, name] : panels) {
    const auto& s = viewer_->slice(panel);
    ASSERT_GT(s.view_width, 20) << name;
    const cv::Mat png = cv::imread(sr.out_dir + "/" + name + ".png", cv::IMREAD_COLOR);
    ASSERT_FALSE(png.empty()) << name;
    // The command's image: the view, then its legend; the viewer shows the view.
    ASSERT_EQ(png.rows, s.view_height) << name;
    const cv::Mat expected = png(cv::Rect(0, 0, s.view_width, s.view_height));
    cv::Mat shown_rgb(s.image.height, s.image.width, CV_8UC3,
                      const_cast<uint8_t*>(s.image.rgb.data()));
    cv::Mat shown;
    cv::cvtColor(shown_rgb(cv::Rect(0, 0, s.view_width, s.view_height)), shown,
                 cv::COLOR_RGB2BGR);
    EXPECT_EQ(cv::norm(expected, shown, cv::NORM_INF), 0) << name << ": the viewer's slice";
    // What the window shows there, pixel for pixel.
    const cv::Point o = viewer_->slice_origin(panel);
    const cv::Mat on_screen = window(cv::Rect(o.x, o.y, s.view_width, s.view_height));
    cv::Mat diff;
    cv::absdiff(on_screen, expected, diff);
    EXPECT_EQ(cv::countNonZero(diff.reshape(1)), 0) << name << ": on the screen";
  }
}

TEST_F(PlanViewerTest, ACtReadAfterTheFirstPictureBringsTheSlices) {
  viewer_.reset();
  ViewStart start = start_view_inputs(*plan_dir_, *ct_, "", {}, "");
  ViewerOptions o;
  o.width = 1200;
  o.height = 800;
  o.view.resolution_scale = 1.0;
  viewer_ = std::make_unique<PlanViewer>(start.inputs, o, std::future<planning::PlanData>(),
                                         std::move(start.ct));
  ASSERT_TRUE(frames_until([&] { return viewer_->slice(ViewPanel::kAxial).view_width > 0; }));
  // The same slice as a viewer given the CT at once.
  const planning::SliceView late = viewer_->slice(ViewPanel::kCoronal);
  viewer_.reset();  // before `start`, whose inputs it shows
  const PlanViewer given_at_once(*inputs_, o, std::future<planning::PlanData>());
  const planning::SliceView& at_once = given_at_once.slice(ViewPanel::kCoronal);
  ASSERT_EQ(late.image.width, at_once.image.width);
  ASSERT_EQ(late.image.height, at_once.image.height);
  EXPECT_TRUE(late.image.rgb == at_once.image.rgb);
}

TEST_F(PlanViewerTest, ClickOnTheSkinInThe3dViewSetsTheEntryThere) {
  // The ray of a pixel left of and above the panel's centre, met with the skin plane y = 17.
  const cv::Rect r = viewer_->panel_rect(ViewPanel::k3d);
  const int u = r.width / 2 - 40, v = r.height / 2 - 30;
  const calibration::CameraModel cam = viewer_->camera3d();
  const Eigen::Isometry3d T_ct_cam = viewer_->orbit().pose().inverse();
  const Eigen::Vector3d d =
      T_ct_cam.linear() * Eigen::Vector3d((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0);
  const Eigen::Vector3d c = T_ct_cam.translation();
  const Eigen::Vector3d expected = c + d * ((kSkinY - c.y()) / d.y());
  click(r.x + u, r.y + v);
  ASSERT_TRUE(frames_until([&] { return viewer_->entry().has_value(); })) << "no entry set";
  const double voxel = inputs_->plan.grid.spacing.maxCoeff();
  EXPECT_LT((*viewer_->entry() - expected).norm(), voxel)
      << "entry " << viewer_->entry()->transpose() << ", expected " << expected.transpose();
  // The patient's left is on the image right from anterior; superior is up.
  EXPECT_LT(viewer_->entry()->x(), inputs_->plan.tumor_centre.x());
  EXPECT_GT(viewer_->entry()->z(), inputs_->plan.tumor_centre.z());
  EXPECT_EQ(viewer_->target(), inputs_->plan.tumor_centre);
}

TEST_F(PlanViewerTest, ClickOnASliceSetsTheEntryAndShiftClickTheTarget) {
  const auto& s = viewer_->slice(ViewPanel::kAxial);
  const cv::Point o = viewer_->slice_origin(ViewPanel::kAxial);
  const int x = s.view_width / 2 + 25, y = s.view_height / 2 - 30;
  click(o.x + x, o.y + y);
  ASSERT_TRUE(frames_until([&] { return viewer_->entry().has_value(); }));
  // Within one voxel of the point under the pixel (clicks land on whole pixels).
  const double voxel = inputs_->plan.grid.spacing.maxCoeff();
  EXPECT_LT((*viewer_->entry() - s.point_of(x, y)).norm(), voxel);
  EXPECT_NEAR(viewer_->entry()->z(), viewer_->cursor().z(), 1e-6) << "on the axial plane";
  click(o.x + x - 10, o.y + y + 10, true);
  ASSERT_TRUE(frames_until([&] { return viewer_->target() != inputs_->plan.tumor_centre; }));
  EXPECT_LT((viewer_->target() - s.point_of(x - 10, y + 10)).norm(), voxel);
}

// Pixels of the 3D panel in the safe colour.
int safe_pixels(PlanViewer& viewer) {
  const cv::Mat picture = viewer.picture();
  const cv::Mat panel = picture(viewer.panel_rect(ViewPanel::k3d));
  int n = 0;
  for (int y = 0; y < panel.rows; ++y) {
    for (int x = 0; x < panel.cols; ++x) {
      const cv::Vec3b p = panel.at<cv::Vec3b>(y, x);  // BGR: green well above red and blue
      if (p[1] > 60 && p[1] > 2 * p[2] && p[1] > 2 * p[0]) ++n;
    }
  }
  return n;
}

TEST_F(PlanViewerTest, KeyOneHidesTheSafeClassAndItsPixelsVanish) {
  const int before = safe_pixels(*viewer_);
  EXPECT_GT(before, 500) << "the mini plan's safe region shows from anterior";
  key(XK_1);
  ASSERT_TRUE(frames_until([&] { return viewer_->view3d().options().hidden[0]; }));
  EXPECT_EQ(safe_pixels(*viewer_), 0);
  key(XK_1);
  ASSERT_TRUE(frames_until([&] { return !viewer_->view3d().options().hidden[0]; }));
  EXPECT_EQ(safe_pixels(*viewer_), before);
}

TEST_F(PlanViewerTest, TheEvaluationShownIsEvaluatesAndMSavesTheLine) {
  const auto& s = viewer_->slice(ViewPanel::kAxial);
  const cv::Point o = viewer_->slice_origin(ViewPanel::kAxial);
  click(o.x + s.view_width / 2 - 20, o.y + s.view_height / 2 - 25);
  ASSERT_TRUE(frames_until([&] { return viewer_->evaluation().has_value(); }));
  EvaluateRequest er;
  er.plan_dir = *plan_dir_;
  planning::Trajectory t;
  t.name = "trial";
  t.entry = *viewer_->entry();
  t.target = viewer_->target();
  er.trajectory = t;
  EXPECT_EQ(viewer_->evaluation_text(), run_evaluate(er));
  EXPECT_GT(viewer_->evaluation()->samples, 0);

  key(XK_m);
  ASSERT_TRUE(frames_until([&] { return !viewer_->saved_markup().empty(); }));
  const std::string path = viewer_->saved_markup();
  EXPECT_EQ(fs::path(path).parent_path(), fs::path(*plan_dir_).parent_path());
  EXPECT_EQ(fs::path(path).filename().string(), "plan-trajectory-01.mrk.json");
  const planning::LineMarkup line = planning::read_line_markup(path);
  EXPECT_LT((line.first - *viewer_->entry()).norm(), 1e-3);
  EXPECT_LT((line.second - viewer_->target()).norm(), 1e-3);
  fs::remove(path);
}

}  // namespace
}  // namespace crepuscular::pipelines
