// Overlay renderer: draws the video frame as background and, on top of it, drawings given in the
// camera frame (mm), projected with the calibrated camera model including its distortion, and
// reads the result back as an image. OpenGL 3.3 core, drawn into an off-screen framebuffer of the
// image size in every case, so the same code and the same pixels serve both targets:
// - live use: a GLFW window (X11/GLX) that present() shows the image in;
// - headless output (video file, PNG snapshots): an EGL context without any window or display
//   (a GPU's EGL device, or Mesa's surfaceless platform), or, where EGL is unavailable, a hidden
//   GLFW window.
//
// Projection happens on the CPU per vertex with CameraModel::project(); segments are subdivided in
// 3D so that no projected piece is longer than max_segment_px, which lets distortion bend them.
// Parts of a polyline closer than near_mm to the camera plane are clipped away.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "calibration/camera_model.hpp"

namespace crepuscular::overlay {

struct Polyline {
  std::vector<Eigen::Vector3d> points_cam;  // camera frame, mm
  cv::Scalar colour{0, 255, 0};             // BGR, 0..255
  double width_px = 2.0;
  bool closed = false;
  double opacity = 1.0;  // 0..1, blended over what is below
};

// What a layer's custom drawing step (set_layer_draw) gets: the renderer's OpenGL context is
// current, its off-screen framebuffer of the image size is bound, blending is on
// (GL_SRC_ALPHA, GL_ONE_MINUS_SRC_ALPHA). The step must leave the vertex array and program
// bindings to the renderer (it binds its own before drawing).
struct DrawContext {
  const calibration::CameraModel& camera;
  int width = 0, height = 0;
};

// A user's input in a renderer's window (poll_events).
struct InputEvent {
  enum class Kind { kKey, kPress, kRelease, kMove, kScroll };
  Kind kind = Kind::kKey;
  int key = 0;   // kKey: GLFW key code ('A', 256 = Escape, ...); kPress/kRelease: mouse button
                 // (0 left, 1 right, 2 middle)
  int mods = 0;  // GLFW modifier bits: 1 Shift, 2 Control, 4 Alt
  double x = 0, y = 0;  // the pointer in image pixels (OpenCV convention)
  double scroll = 0;    // kScroll: wheel steps, positive away from the user
};

// Where the OpenGL context comes from.
enum class RendererBackend {
  kAuto,  // visible: GLFW; headless: EGL, falling back to a hidden GLFW window
  kEgl,   // headless only: EGL device (eglQueryDevicesEXT), Mesa surfaceless, or default display
  kGlfw,  // a GLFW window (hidden when headless); needs an X display
};

struct RendererOptions {
  bool visible = false;          // show the window (live use); hidden for headless output
  RendererBackend backend = RendererBackend::kAuto;
  double max_segment_px = 4.0;   // longest projected straight piece of a polyline
  double near_mm = 1.0;          // drawings closer than this to the camera plane are clipped
};

class OverlayRenderer {
 public:
  // Creates the GL context and a framebuffer of the camera's image size. Throws Error when no
  // OpenGL 3.3 core context can be made (no display, no driver; the message says what was tried),
  // and for backend kEgl with visible = true (a window needs GLFW).
  explicit OverlayRenderer(const calibration::CameraModel& camera, RendererOptions options = {});
  ~OverlayRenderer();
  OverlayRenderer(const OverlayRenderer&) = delete;
  OverlayRenderer& operator=(const OverlayRenderer&) = delete;

  // Background video frame: CV_8UC3 BGR of the camera's image size. Throws Error otherwise.
  void set_frame(const cv::Mat& bgr);

  // Layers are named groups drawn in the order they were first used; all start visible.
  void add_polyline(const std::string& layer, const Polyline& polyline);
  // Dots at 3D points, each drawn as a bilinear splat of one pixel's footprint centred at the exact
  // projected position (its intensity-weighted centroid is the projection, to sub-pixel accuracy).
  void add_points(const std::string& layer, const std::vector<Eigen::Vector3d>& points_cam,
                  const cv::Scalar& colour);
  // Drawings given in image pixels (OpenCV convention: (0,0) is the centre of the top-left pixel),
  // for outlines found in the image and screen-fixed marks.
  void add_polyline_px(const std::string& layer, const std::vector<Eigen::Vector2d>& points_px,
                       const cv::Scalar& colour, double width_px, bool closed = false,
                       double opacity = 1.0);
  // An image of the camera's size (CV_8UC4, BGRA, alpha 0 = transparent) drawn over the layer's
  // other drawings, e.g. text from cv::putText. Replaces the layer's previous image; an empty Mat
  // removes it.
  void set_layer_image(const std::string& layer, const cv::Mat& bgra);
  // Adds an image (CV_8UC4 BGRA) of any size at `origin` (its top-left pixel in the frame; it must
  // lie inside the frame) to the layer's images, e.g. a text panel; cheaper than a full-frame
  // image. clear_layer() removes them.
  // revision (from new_image_revision()) marks images that stay the same over many frames: when
  // it equals that of the image last given at the same place in the layer (the same count of
  // images added before it since clear_layer()) with the same size, the texture is kept and the
  // pixels are not uploaded again. 0: always uploaded.
  void add_layer_image(const std::string& layer, const cv::Mat& bgra, const cv::Point& origin,
                       uint64_t revision = 0);
  // The same image placed by an affine map `warp` (2x3, frame pixels where the image would lie at
  // `origin` -> frame pixels where it is shown; OpenCV convention) and sampled bilinearly, e.g. a
  // picture drawn for a slightly earlier pose moved to the present one. Throws Error when the
  // map is not invertible.
  void add_layer_image_warped(const std::string& layer, const cv::Mat& bgra,
                              const cv::Point& origin, const Eigen::Matrix<double, 2, 3>& warp,
                              uint64_t revision = 0);
  // A revision number for add_layer_image(), unique in the process (never 0).
  static uint64_t new_image_revision();
  // A drawing step of the layer's own (e.g. a volume rendering), run before its shapes. An empty
  // function removes it.
  void set_layer_draw(const std::string& layer, std::function<void(const DrawContext&)> draw);
  // Removes the layer's shapes, image and drawing step (it stays in the list, with its visibility).
  void clear_layer(const std::string& layer);
  void set_layer_visible(const std::string& layer, bool visible);
  bool layer_visible(const std::string& layer) const;
  std::vector<std::string> layer_names() const;

  // Draws everything and returns the image (CV_8UC3 BGR, image row order).
  cv::Mat render();
  // Draws everything without reading the image back (for the window; render() reads it back).
  void draw();
  // Waits until the GPU has finished everything drawn so far (glFinish), for timing.
  void finish();

  // Window (visible renderers): shows the last drawn image, scaled to the window, and handles
  // window events. Returns false once the user has closed the window. Keys pressed since the
  // last call come from poll_keys() (GLFW key codes, e.g. '1', 'S', 256 = Escape).
  // Headless renderers have nothing to show: present() returns true and poll_keys() is empty.
  bool present();
  std::vector<int> poll_keys();
  // Keys, mouse buttons, pointer moves and the wheel since the last call, in order (the most recent
  // 4096 kept). Headless renderers: empty.
  std::vector<InputEvent> poll_events();
  // Whether the window is still open (false once the user closed it); headless: true.
  bool window_open() const;
  bool visible() const { return options_.visible; }
  // The window's pixels as the X server holds them (XGetImage of the GLFW window: what the user
  // sees after present()), CV_8UC3 BGR of the window's size. Throws Error for renderers without a
  // window (EGL) and when the window system is not X11. For tests and for checking the live view.
  cv::Mat screenshot_window();

  // The backend in use (kEgl or kGlfw, never kAuto).
  RendererBackend backend() const;

  const calibration::CameraModel& camera() const { return camera_; }
  // The OpenGL implementation in use and where its context comes from, e.g.
  // "llvmpipe (LLVM 15.0.6, 256 bits) / 4.5 (Core Profile) Mesa 22.3.6 [EGL device]"; the bracket
  // is one of "EGL device", "EGL surfaceless", "EGL default display", "GLFW/GLX".
  std::string gl_description() const;

 private:
  struct Impl;
  void create_gl_objects();  // framebuffer, textures, programs, buffers (context current)
  calibration::CameraModel camera_;
  RendererOptions options_;
  std::unique_ptr<Impl> impl_;
};

}  // namespace crepuscular::overlay
