#include "overlay/renderer.hpp"

#define GL_GLEXT_PROTOTYPES 1
#include <GL/glcorearb.h>
#define EGL_NO_X11 1  // no X11 types in the EGL headers: the EGL path needs no display
#include <EGL/egl.h>
#include <EGL/eglext.h>
#define GLFW_INCLUDE_NONE
#include <GLFW/glfw3.h>

#include <algorithm>
#include <deque>
#include <atomic>
#include <cmath>
#include <cstring>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>

#include <opencv2/core.hpp>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "overlay/gl_program.hpp"

// Last: Xlib's macros (None, Success, Status, ...) must not reach the headers above.
#include <X11/Xlib.h>
#include <X11/Xutil.h>
// GLFW's X11 accessors as <GLFW/glfw3native.h> declares them (that header also wants the XRandR
// development headers, which nothing here needs).
extern "C" {
Display* glfwGetX11Display(void);
Window glfwGetX11Window(GLFWwindow* window);
}

namespace crepuscular::overlay {

namespace {

// Per vertex: position (pixels, OpenCV convention), colour RGBA 0..1, splat centre (pixels), mode
// (0 solid, 1 bilinear splat around the centre).
struct Vertex {
  float x, y;
  float r, g, b, a;
  float cx, cy;
  float mode;
};

const char* kShapeVertex = R"(#version 330 core
layout(location = 0) in vec2 pixel;
layout(location = 1) in vec4 colour;
layout(location = 2) in vec2 centre;
layout(location = 3) in float mode;
uniform vec2 size;
out vec4 v_colour;
flat out vec2 v_centre;
flat out float v_mode;
void main() {
  // OpenCV pixel (0,0) is the centre of the top-left pixel; GL's window origin is bottom-left.
  vec2 ndc = vec2(2.0 * (pixel.x + 0.5) / size.x - 1.0, 1.0 - 2.0 * (pixel.y + 0.5) / size.y);
  gl_Position = vec4(ndc, 0.0, 1.0);
  v_colour = colour;
  v_centre = centre;
  v_mode = mode;
}
)";

const char* kShapeFragment = R"(#version 330 core
in vec4 v_colour;
flat in vec2 v_centre;
flat in float v_mode;
uniform vec2 size;
out vec4 out_colour;
void main() {
  float weight = 1.0;
  if (v_mode > 0.5) {
    vec2 p = vec2(gl_FragCoord.x - 0.5, size.y - gl_FragCoord.y - 0.5);
    vec2 d = max(vec2(0.0), vec2(1.0) - abs(p - v_centre));
    weight = d.x * d.y;
  }
  out_colour = vec4(v_colour.rgb, v_colour.a * weight);
}
)";

const char* kBackgroundVertex = R"(#version 330 core
void main() {
  vec2 corners[3] = vec2[3](vec2(-1.0, -1.0), vec2(3.0, -1.0), vec2(-1.0, 3.0));
  gl_Position = vec4(corners[gl_VertexID], 0.0, 1.0);
}
)";

const char* kBackgroundFragment = R"(#version 330 core
uniform sampler2D frame;
uniform vec2 size;
uniform float with_alpha;  // 0: opaque video frame; 1: image layer with its own alpha
uniform ivec2 offset;      // image position (top-left pixel) in the frame
uniform float packed_bgr;  // 1: the video frame, B, G, R bytes side by side in one channel
uniform float warped;      // 1: image placed by an affine map (from_frame), sampled bilinearly
uniform mat3 from_frame;   // frame pixel -> image pixel (OpenCV convention: centres at integers)
uniform ivec2 extent;      // the image's size (the texture may be larger)
out vec4 out_colour;
// One texel with its colour premultiplied by its alpha; nothing outside the image.
vec4 premultiplied(ivec2 t) {
  if (t.x < 0 || t.y < 0 || t.x >= extent.x || t.y >= extent.y) return vec4(0.0);
  vec4 c = texelFetch(frame, t, 0);
  return vec4(c.rgb * c.a, c.a);
}
void main() {
  if (warped > 0.5) {
    // Bilinear in premultiplied colour, so that transparent texels darken no edge.
    vec2 pixel = vec2(gl_FragCoord.x - 0.5, size.y - gl_FragCoord.y - 0.5);
    vec2 q = (from_frame * vec3(pixel, 1.0)).xy;
    vec2 f0 = floor(q);
    vec2 w = q - f0;
    ivec2 t = ivec2(f0);
    vec4 c = mix(mix(premultiplied(t), premultiplied(t + ivec2(1, 0)), w.x),
                 mix(premultiplied(t + ivec2(0, 1)), premultiplied(t + ivec2(1, 1)), w.x), w.y);
    out_colour = c.a > 0.0 ? vec4(c.rgb / c.a, c.a) : vec4(0.0);
    return;
  }
  ivec2 texel = ivec2(int(gl_FragCoord.x), int(size.y) - 1 - int(gl_FragCoord.y)) - offset;
  vec4 c;
  if (packed_bgr > 0.5) {
    int x = 3 * texel.x;
    c = vec4(texelFetch(frame, ivec2(x + 2, texel.y), 0).r,
             texelFetch(frame, ivec2(x + 1, texel.y), 0).r,
             texelFetch(frame, ivec2(x, texel.y), 0).r, 1.0);
  } else {
    c = texelFetch(frame, texel, 0);
  }
  out_colour = vec4(c.rgb, with_alpha > 0.5 ? c.a : 1.0);
}
)";

std::mutex glfw_mutex;
int glfw_users = 0;
std::string glfw_last_error;

void glfw_error(int code, const char* description) {
  glfw_last_error = "GLFW error " + std::to_string(code) + ": " + description;
}

void glfw_acquire() {
  std::lock_guard<std::mutex> lock(glfw_mutex);
  if (glfw_users == 0) {
    glfwSetErrorCallback(glfw_error);
    if (!glfwInit()) {
      throw Error("overlay renderer: cannot initialise GLFW (is there a display? " +
                  glfw_last_error + ")");
    }
  }
  ++glfw_users;
}

void glfw_release() {
  std::lock_guard<std::mutex> lock(glfw_mutex);
  if (--glfw_users == 0) glfwTerminate();
}

// A thread has one current context across GLX and EGL (libglvnd refuses to make one current while
// the other API's is): each backend releases the other's before making its own current.
void release_glfw_current() {
  std::lock_guard<std::mutex> lock(glfw_mutex);
  if (glfw_users > 0 && glfwGetCurrentContext()) glfwMakeContextCurrent(nullptr);
}

void release_egl_current() {
  eglBindAPI(EGL_OPENGL_API);
  if (eglGetCurrentContext() != EGL_NO_CONTEXT) {
    eglMakeCurrent(eglGetCurrentDisplay(), EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
  }
}

// EGL: displays are per process and eglTerminate ends every context on them, so initialisations
// are counted per display and the last renderer using one terminates it.
std::mutex egl_mutex;
std::map<EGLDisplay, int> egl_users;

bool egl_initialise(EGLDisplay display) {
  std::lock_guard<std::mutex> lock(egl_mutex);
  EGLint major = 0, minor = 0;
  if (!eglInitialize(display, &major, &minor)) return false;
  ++egl_users[display];
  return true;
}

void egl_release(EGLDisplay display) {
  std::lock_guard<std::mutex> lock(egl_mutex);
  auto it = egl_users.find(display);
  if (it == egl_users.end()) return;
  if (--it->second == 0) {
    eglTerminate(display);
    egl_users.erase(it);
  }
}

std::string egl_error() {
  std::ostringstream s;
  s << "EGL error 0x" << std::hex << eglGetError();
  return s.str();
}

bool has_extension(const char* list, const char* name) {
  if (!list) return false;
  const size_t n = std::strlen(name);
  for (const char* p = list; (p = std::strstr(p, name)) != nullptr; p += n) {
    if ((p == list || p[-1] == ' ') && (p[n] == ' ' || p[n] == '\0')) return true;
  }
  return false;
}

struct EglTarget {
  EGLDisplay display = EGL_NO_DISPLAY;
  EGLContext context = EGL_NO_CONTEXT;
  EGLSurface surface = EGL_NO_SURFACE;  // a 1x1 pbuffer only where surfaceless contexts are missing
};

// An OpenGL 3.3 core context on `display`, made current without a surface (everything is drawn
// into the renderer's own framebuffer). Returns false with the reason in `why`.
bool egl_make_context(EGLDisplay display, EglTarget& out, std::string& why) {
  if (display == EGL_NO_DISPLAY) {
    why = "no display (" + egl_error() + ")";
    return false;
  }
  if (!egl_initialise(display)) {
    why = "eglInitialize failed (" + egl_error() + ")";
    return false;
  }
  const char* extensions = eglQueryString(display, EGL_EXTENSIONS);
  const bool surfaceless = has_extension(extensions, "EGL_KHR_surfaceless_context");
  const EGLint pbuffer_config[] = {EGL_SURFACE_TYPE, EGL_PBUFFER_BIT, EGL_RENDERABLE_TYPE,
                                   EGL_OPENGL_BIT, EGL_RED_SIZE, 8, EGL_GREEN_SIZE, 8,
                                   EGL_BLUE_SIZE, 8, EGL_NONE};
  const EGLint any_config[] = {EGL_SURFACE_TYPE, 0, EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT, EGL_NONE};
  EGLConfig config = nullptr;
  EGLint count = 0;
  bool pbuffer = eglChooseConfig(display, pbuffer_config, &config, 1, &count) && count > 0;
  if (!pbuffer && surfaceless) {
    if (!(eglChooseConfig(display, any_config, &config, 1, &count) && count > 0)) {
      if (has_extension(extensions, "EGL_KHR_no_config_context")) config = EGL_NO_CONFIG_KHR;
      else count = 0;
    }
  }
  if (!pbuffer && !(surfaceless && (count > 0 || config == EGL_NO_CONFIG_KHR))) {
    why = "no OpenGL configuration";
    egl_release(display);
    return false;
  }
  if (!eglBindAPI(EGL_OPENGL_API)) {
    why = "desktop OpenGL not supported (" + egl_error() + ")";
    egl_release(display);
    return false;
  }
  const EGLint context_attributes[] = {EGL_CONTEXT_MAJOR_VERSION, 3, EGL_CONTEXT_MINOR_VERSION, 3,
                                       EGL_CONTEXT_OPENGL_PROFILE_MASK,
                                       EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT, EGL_NONE};
  const EGLContext context = eglCreateContext(display, config, EGL_NO_CONTEXT, context_attributes);
  if (context == EGL_NO_CONTEXT) {
    why = "no OpenGL 3.3 core context (" + egl_error() + ")";
    egl_release(display);
    return false;
  }
  EGLSurface surface = EGL_NO_SURFACE;
  if (!surfaceless) {
    const EGLint pbuffer_attributes[] = {EGL_WIDTH, 1, EGL_HEIGHT, 1, EGL_NONE};
    surface = eglCreatePbufferSurface(display, config, pbuffer_attributes);
    if (surface == EGL_NO_SURFACE) {
      why = "neither EGL_KHR_surfaceless_context nor a pbuffer (" + egl_error() + ")";
      eglDestroyContext(display, context);
      egl_release(display);
      return false;
    }
  }
  release_glfw_current();
  if (!eglMakeCurrent(display, surface, surface, context)) {
    why = "eglMakeCurrent failed (" + egl_error() + ")";
    if (surface != EGL_NO_SURFACE) eglDestroySurface(display, surface);
    eglDestroyContext(display, context);
    egl_release(display);
    return false;
  }
  out = EglTarget{display, context, surface};
  return true;
}

// Tries, in order: each EGL device (a GPU without any display server), Mesa's surfaceless
// platform, the default display. Returns false with what was tried in `why`.
bool egl_create(EglTarget& out, std::string& kind, std::string& why) {
  std::vector<std::string> tried;
  std::string reason;
  // Client extensions; null (and an EGL_BAD_DISPLAY error) where the library has none.
  const char* client = eglQueryString(EGL_NO_DISPLAY, EGL_EXTENSIONS);
  eglGetError();
  const auto get_platform_display = reinterpret_cast<PFNEGLGETPLATFORMDISPLAYEXTPROC>(
      eglGetProcAddress("eglGetPlatformDisplayEXT"));
  const auto query_devices =
      reinterpret_cast<PFNEGLQUERYDEVICESEXTPROC>(eglGetProcAddress("eglQueryDevicesEXT"));
  if (get_platform_display && query_devices && has_extension(client, "EGL_EXT_platform_device")) {
    EGLDeviceEXT devices[16];
    EGLint n = 0;
    if (query_devices(16, devices, &n) && n > 0) {
      for (EGLint i = 0; i < n; ++i) {
        const EGLDisplay display = get_platform_display(EGL_PLATFORM_DEVICE_EXT, devices[i], nullptr);
        if (egl_make_context(display, out, reason)) {
          kind = "EGL device";
          return true;
        }
        tried.push_back("EGL device " + std::to_string(i) + ": " + reason);
      }
    } else {
      tried.push_back("EGL devices: none found");
    }
  } else {
    tried.push_back("EGL devices: EGL_EXT_device_enumeration/EGL_EXT_platform_device missing");
  }
  if (get_platform_display && has_extension(client, "EGL_MESA_platform_surfaceless")) {
    const EGLDisplay display =
        get_platform_display(EGL_PLATFORM_SURFACELESS_MESA, EGL_DEFAULT_DISPLAY, nullptr);
    if (egl_make_context(display, out, reason)) {
      kind = "EGL surfaceless";
      return true;
    }
    tried.push_back("EGL surfaceless: " + reason);
  }
  if (egl_make_context(eglGetDisplay(EGL_DEFAULT_DISPLAY), out, reason)) {
    kind = "EGL default display";
    return true;
  }
  tried.push_back("EGL default display: " + reason);
  why.clear();
  for (const auto& t : tried) why += (why.empty() ? "" : "; ") + t;
  return false;
}

Vertex make_vertex(const Eigen::Vector2d& p, const cv::Scalar& bgr, const Eigen::Vector2d& centre,
                   float mode, double opacity = 1.0) {
  return Vertex{static_cast<float>(p.x()),         static_cast<float>(p.y()),
                static_cast<float>(bgr[2] / 255.0), static_cast<float>(bgr[1] / 255.0),
                static_cast<float>(bgr[0] / 255.0), static_cast<float>(std::clamp(opacity, 0.0, 1.0)),
                static_cast<float>(centre.x()),     static_cast<float>(centre.y()),
                mode};
}

// Two triangles for the quad a, b, c, d (in order around it).
void push_quad(std::vector<Vertex>& out, const Vertex& a, const Vertex& b, const Vertex& c,
               const Vertex& d) {
  out.insert(out.end(), {a, b, c, a, c, d});
}

// A straight piece a -> b of a line of half width `half`, with square caps of half the width that
// close the joints between pieces.
void push_piece(std::vector<Vertex>& out, const Eigen::Vector2d& a, const Eigen::Vector2d& b,
                double half, const cv::Scalar& colour, double opacity) {
  Eigen::Vector2d dir = b - a;
  const double n = dir.norm();
  dir = n > 1e-9 ? Eigen::Vector2d(dir / n) : Eigen::Vector2d(1, 0);
  const Eigen::Vector2d normal(-dir.y(), dir.x());
  const Eigen::Vector2d s0 = a - dir * half, s1 = b + dir * half;
  const Eigen::Vector2d zero(0, 0);
  push_quad(out, make_vertex(s0 + normal * half, colour, zero, 0, opacity),
            make_vertex(s1 + normal * half, colour, zero, 0, opacity),
            make_vertex(s1 - normal * half, colour, zero, 0, opacity),
            make_vertex(s0 - normal * half, colour, zero, 0, opacity));
}

}  // namespace

struct OverlayRenderer::Impl {
  struct Layer {
    std::string name;
    bool visible = true;
    std::vector<Vertex> vertices;
    std::function<void(const DrawContext&)> draw;
    struct Image {
      GLuint texture = 0;
      int width = 0, height = 0;              // the image shown (top-left part of the texture)
      int texture_width = 0, texture_height = 0;  // allocated; grows, never shrinks
      cv::Point origin;
      uint64_t revision = 0;  // of the pixels in the texture (0: not to be reused)
      // add_layer_image_warped: image pixel -> frame pixel; unset: at `origin`, texel for pixel.
      std::optional<Eigen::Matrix<double, 2, 3>> warp;
    };
    std::vector<Image> images;  // textures are kept for reuse; the first image_count are shown
    size_t image_count = 0;
  };
  GLFWwindow* window = nullptr;  // GLFW backend
  EglTarget egl;                 // EGL backend
  std::string kind;              // "EGL device", "EGL surfaceless", ..., "GLFW/GLX"
  std::vector<int> keys;  // pressed since the last poll_keys()
  std::deque<InputEvent> events;  // since the last poll_events()
  int image_width = 0, image_height = 0;

  void push(InputEvent e) {
    if (events.size() >= 4096) events.pop_front();
    events.push_back(e);
  }
  // The pointer in image pixels (the window may be scaled to the image).
  void pointer(double& x, double& y) const {
    double wx = 0, wy = 0;
    glfwGetCursorPos(window, &wx, &wy);
    int ww = 0, wh = 0;
    glfwGetWindowSize(window, &ww, &wh);
    x = ww > 0 ? wx * image_width / ww - 0.5 : wx;
    y = wh > 0 ? wy * image_height / wh - 0.5 : wy;
  }
  GLuint fbo = 0, colour_rb = 0, frame_texture = 0;
  GLuint shape_program = 0, background_program = 0;
  GLuint vao = 0, vbo = 0;
  bool has_frame = false;
  std::vector<Layer> layers;
  cv::Mat readback;  // render()'s glReadPixels target (bottom row first)

  Layer& layer(const std::string& name) {
    for (auto& l : layers)
      if (l.name == name) return l;
    layers.push_back(Layer{});
    layers.back().name = name;
    return layers.back();
  }
  const Layer* find(const std::string& name) const {
    for (const auto& l : layers)
      if (l.name == name) return &l;
    return nullptr;
  }

  void make_current() {
    if (window) {
      release_egl_current();
      if (glfwGetCurrentContext() != window) glfwMakeContextCurrent(window);
      return;
    }
    eglBindAPI(EGL_OPENGL_API);
    if (eglGetCurrentContext() == egl.context) return;
    release_glfw_current();
    if (!eglMakeCurrent(egl.display, egl.surface, egl.surface, egl.context)) {
      throw Error("overlay renderer: cannot make the EGL context current (" + egl_error() + ")");
    }
  }

  // Ends the context (the caller has deleted its GL objects).
  void release_context() {
    if (window) {
      glfwDestroyWindow(window);
      window = nullptr;
      glfw_release();
    } else if (egl.context != EGL_NO_CONTEXT) {
      eglMakeCurrent(egl.display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
      if (egl.surface != EGL_NO_SURFACE) eglDestroySurface(egl.display, egl.surface);
      eglDestroyContext(egl.display, egl.context);
      egl_release(egl.display);
      egl = EglTarget{};
    }
  }

  // A hidden or shown GLFW window of the image size; false with the reason in `why`.
  bool create_glfw(int width, int height, bool shown, std::string& why) {
    try {
      glfw_acquire();
    } catch (const Error& e) {
      why = e.what();
      return false;
    }
    glfwWindowHint(GLFW_CONTEXT_VERSION_MAJOR, 3);
    glfwWindowHint(GLFW_CONTEXT_VERSION_MINOR, 3);
    glfwWindowHint(GLFW_OPENGL_PROFILE, GLFW_OPENGL_CORE_PROFILE);
    glfwWindowHint(GLFW_OPENGL_FORWARD_COMPAT, GLFW_TRUE);
    glfwWindowHint(GLFW_VISIBLE, shown ? GLFW_TRUE : GLFW_FALSE);
    glfwWindowHint(GLFW_RESIZABLE, GLFW_FALSE);
    release_egl_current();
    window = glfwCreateWindow(width, height, "Crepuscular", nullptr, nullptr);
    if (!window) {
      glfw_release();
      why = "cannot create an OpenGL 3.3 core window (" + glfw_last_error + ")";
      return false;
    }
    glfwMakeContextCurrent(window);
    glfwSetWindowUserPointer(window, this);
    image_width = width;
    image_height = height;
    glfwSetKeyCallback(window, [](GLFWwindow* w, int key, int, int action, int mods) {
      if (action != GLFW_PRESS && action != GLFW_REPEAT) return;
      auto* impl = static_cast<Impl*>(glfwGetWindowUserPointer(w));
      if (action == GLFW_PRESS) impl->keys.push_back(key);
      InputEvent e;
      e.kind = InputEvent::Kind::kKey;
      e.key = key;
      e.mods = mods;
      impl->pointer(e.x, e.y);
      impl->push(e);
    });
    glfwSetMouseButtonCallback(window, [](GLFWwindow* w, int button, int action, int mods) {
      auto* impl = static_cast<Impl*>(glfwGetWindowUserPointer(w));
      InputEvent e;
      e.kind = action == GLFW_PRESS ? InputEvent::Kind::kPress : InputEvent::Kind::kRelease;
      e.key = button;
      e.mods = mods;
      impl->pointer(e.x, e.y);
      impl->push(e);
    });
    glfwSetCursorPosCallback(window, [](GLFWwindow* w, double, double) {
      auto* impl = static_cast<Impl*>(glfwGetWindowUserPointer(w));
      InputEvent e;
      e.kind = InputEvent::Kind::kMove;
      impl->pointer(e.x, e.y);
      impl->push(e);
    });
    glfwSetScrollCallback(window, [](GLFWwindow* w, double, double dy) {
      auto* impl = static_cast<Impl*>(glfwGetWindowUserPointer(w));
      InputEvent e;
      e.kind = InputEvent::Kind::kScroll;
      e.scroll = dy;
      impl->pointer(e.x, e.y);
      impl->push(e);
    });
    kind = "GLFW/GLX";
    return true;
  }
};

OverlayRenderer::OverlayRenderer(const calibration::CameraModel& camera, RendererOptions options)
    : camera_(camera), options_(options), impl_(std::make_unique<Impl>()) {
  camera_.validate("overlay renderer camera");
  if (!(options_.max_segment_px > 0) || !(options_.near_mm > 0)) {
    throw Error("overlay renderer: max_segment_px and near_mm must be > 0");
  }
  if (options_.visible && options_.backend == RendererBackend::kEgl) {
    throw Error("overlay renderer: a visible window needs the GLFW backend (EGL is headless only)");
  }
  // Headless: EGL first (no display needed), then a hidden GLFW window. Visible: a GLFW window.
  std::string egl_why, glfw_why;
  bool made = false;
  if (!options_.visible && options_.backend != RendererBackend::kGlfw) {
    made = egl_create(impl_->egl, impl_->kind, egl_why);
    if (!made) spdlog::debug("overlay renderer: EGL unavailable: {}", egl_why);
  }
  if (!made && options_.backend != RendererBackend::kEgl) {
    made = impl_->create_glfw(camera_.width, camera_.height, options_.visible, glfw_why);
  }
  if (!made) {
    std::string message = "overlay renderer: no OpenGL 3.3 core context. ";
    if (!egl_why.empty()) message += "EGL: " + egl_why + ". ";
    if (!glfw_why.empty()) message += "GLFW: " + glfw_why + ". ";
    const char* display = std::getenv("DISPLAY");
    if (options_.visible || options_.backend == RendererBackend::kGlfw) {
      message += (display && *display) ? "Check that the X display is reachable and has GLX."
                                       : "There is no X display: set DISPLAY or run under "
                                         "xvfb-run -a.";
    } else if (options_.backend == RendererBackend::kEgl) {
      message += "Install an EGL driver (libegl-mesa0 or the GPU driver's EGL library), or use the "
                 "GLFW backend on an X display (xvfb-run -a).";
    } else {
      message += (display && *display)
                     ? "Install an EGL driver (libegl-mesa0 or the GPU driver's EGL library)."
                     : "No display and no EGL device: run under xvfb-run -a, or install an EGL "
                       "driver (libegl-mesa0 or the GPU driver's EGL library).";
    }
    throw Error(message);
  }
  spdlog::debug("overlay renderer: {} / {} [{}]",
                reinterpret_cast<const char*>(glGetString(GL_RENDERER)),
                reinterpret_cast<const char*>(glGetString(GL_VERSION)), impl_->kind);
  try {
    create_gl_objects();
  } catch (...) {
    impl_->release_context();
    throw;
  }
}

void OverlayRenderer::create_gl_objects() {

  // Off-screen target of the image size: the same pixels whether the window is shown or hidden.
  glGenRenderbuffers(1, &impl_->colour_rb);
  glBindRenderbuffer(GL_RENDERBUFFER, impl_->colour_rb);
  glRenderbufferStorage(GL_RENDERBUFFER, GL_RGBA8, camera_.width, camera_.height);
  glGenFramebuffers(1, &impl_->fbo);
  glBindFramebuffer(GL_FRAMEBUFFER, impl_->fbo);
  glFramebufferRenderbuffer(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_RENDERBUFFER, impl_->colour_rb);
  if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE) {
    throw Error("overlay renderer: off-screen framebuffer incomplete");
  }

  GLint max_texture = 0;
  glGetIntegerv(GL_MAX_TEXTURE_SIZE, &max_texture);
  if (3 * camera_.width > max_texture || camera_.height > max_texture) {
    throw Error("overlay renderer: a " + std::to_string(camera_.width) + "x" +
                std::to_string(camera_.height) + " video frame exceeds this OpenGL's texture limit (" +
                std::to_string(max_texture) + " texels)");
  }
  glGenTextures(1, &impl_->frame_texture);
  glBindTexture(GL_TEXTURE_2D, impl_->frame_texture);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  // The video frame's bytes as they are (B, G, R, B, ...), one byte per texel: no format conversion
  // in the driver on upload (NVIDIA's converts 3-byte BGR on the CPU); the shader unpacks it.
  glTexImage2D(GL_TEXTURE_2D, 0, GL_R8, 3 * camera_.width, camera_.height, 0, GL_RED,
               GL_UNSIGNED_BYTE, nullptr);

  impl_->shape_program = link_gl_program(kShapeVertex, kShapeFragment, "overlay renderer");
  impl_->background_program =
      link_gl_program(kBackgroundVertex, kBackgroundFragment, "overlay renderer");

  glGenVertexArrays(1, &impl_->vao);
  glGenBuffers(1, &impl_->vbo);
  glBindVertexArray(impl_->vao);
  glBindBuffer(GL_ARRAY_BUFFER, impl_->vbo);
  const auto stride = static_cast<GLsizei>(sizeof(Vertex));
  glVertexAttribPointer(0, 2, GL_FLOAT, GL_FALSE, stride, reinterpret_cast<void*>(offsetof(Vertex, x)));
  glVertexAttribPointer(1, 4, GL_FLOAT, GL_FALSE, stride, reinterpret_cast<void*>(offsetof(Vertex, r)));
  glVertexAttribPointer(2, 2, GL_FLOAT, GL_FALSE, stride, reinterpret_cast<void*>(offsetof(Vertex, cx)));
  glVertexAttribPointer(3, 1, GL_FLOAT, GL_FALSE, stride, reinterpret_cast<void*>(offsetof(Vertex, mode)));
  for (GLuint i = 0; i < 4; ++i) glEnableVertexAttribArray(i);
}

OverlayRenderer::~OverlayRenderer() {
  if (!impl_ || (!impl_->window && impl_->egl.context == EGL_NO_CONTEXT)) return;
  try {
    impl_->make_current();
  } catch (const Error& e) {
    spdlog::warn("{}", e.what());
  }
  glDeleteBuffers(1, &impl_->vbo);
  glDeleteVertexArrays(1, &impl_->vao);
  glDeleteProgram(impl_->shape_program);
  glDeleteProgram(impl_->background_program);
  glDeleteTextures(1, &impl_->frame_texture);
  for (auto& l : impl_->layers)
    for (auto& image : l.images) glDeleteTextures(1, &image.texture);
  glDeleteFramebuffers(1, &impl_->fbo);
  glDeleteRenderbuffers(1, &impl_->colour_rb);
  impl_->release_context();
}

std::string OverlayRenderer::gl_description() const {
  impl_->make_current();
  return std::string(reinterpret_cast<const char*>(glGetString(GL_RENDERER))) + " / " +
         reinterpret_cast<const char*>(glGetString(GL_VERSION)) + " [" + impl_->kind + "]";
}

RendererBackend OverlayRenderer::backend() const {
  return impl_->window ? RendererBackend::kGlfw : RendererBackend::kEgl;
}

void OverlayRenderer::set_frame(const cv::Mat& bgr) {
  if (bgr.type() != CV_8UC3 || bgr.cols != camera_.width || bgr.rows != camera_.height) {
    throw Error("overlay renderer: video frame must be 8-bit BGR of " +
                std::to_string(camera_.width) + "x" + std::to_string(camera_.height) +
                " (the camera's image size), got " + std::to_string(bgr.cols) + "x" +
                std::to_string(bgr.rows) + " with " + std::to_string(bgr.channels()) +
                " channel(s)");
  }
  const cv::Mat contiguous = bgr.isContinuous() ? bgr : bgr.clone();
  impl_->make_current();
  glBindTexture(GL_TEXTURE_2D, impl_->frame_texture);
  glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
  glTexSubImage2D(GL_TEXTURE_2D, 0, 0, 0, 3 * camera_.width, camera_.height, GL_RED,
                  GL_UNSIGNED_BYTE, contiguous.data);
  impl_->has_frame = true;
}

void OverlayRenderer::add_polyline(const std::string& layer_name, const Polyline& polyline) {
  auto& out = impl_->layer(layer_name).vertices;
  const auto& pts = polyline.points_cam;
  if (pts.size() < 2) return;
  const double half = std::max(0.5, polyline.width_px / 2.0);
  const double near = options_.near_mm;
  const size_t segments = polyline.closed ? pts.size() : pts.size() - 1;
  for (size_t s = 0; s < segments; ++s) {
    Eigen::Vector3d p = pts[s];
    Eigen::Vector3d q = pts[(s + 1) % pts.size()];
    // Clip to z >= near in 3D (a straight line in space stays a straight line in the undistorted
    // image, so clipping and subdividing in 3D are exact).
    if (p.z() < near && q.z() < near) continue;
    if (p.z() < near) p = q + (p - q) * ((q.z() - near) / (q.z() - p.z()));
    if (q.z() < near) q = p + (q - p) * ((p.z() - near) / (p.z() - q.z()));
    const Eigen::Vector2d a = camera_.project(p);
    const Eigen::Vector2d b = camera_.project(q);
    const double length = (b - a).norm();
    if (!std::isfinite(length)) continue;
    const int pieces =
        std::clamp(static_cast<int>(std::ceil(length / options_.max_segment_px)), 1, 4096);
    Eigen::Vector2d prev = a;
    for (int i = 1; i <= pieces; ++i) {
      const Eigen::Vector2d next =
          i == pieces ? b : camera_.project(p + (q - p) * (static_cast<double>(i) / pieces));
      push_piece(out, prev, next, half, polyline.colour, polyline.opacity);
      prev = next;
    }
  }
}

void OverlayRenderer::add_points(const std::string& layer_name,
                                 const std::vector<Eigen::Vector3d>& points_cam,
                                 const cv::Scalar& colour) {
  auto& out = impl_->layer(layer_name).vertices;
  for (const auto& p : points_cam) {
    if (p.z() < options_.near_mm) continue;
    const Eigen::Vector2d c = camera_.project(p);
    if (!c.allFinite()) continue;
    const double r = 1.5;  // covers every pixel centre within one pixel of c
    push_quad(out, make_vertex(c + Eigen::Vector2d(-r, -r), colour, c, 1),
              make_vertex(c + Eigen::Vector2d(r, -r), colour, c, 1),
              make_vertex(c + Eigen::Vector2d(r, r), colour, c, 1),
              make_vertex(c + Eigen::Vector2d(-r, r), colour, c, 1));
  }
}

void OverlayRenderer::add_polyline_px(const std::string& layer_name,
                                      const std::vector<Eigen::Vector2d>& points_px,
                                      const cv::Scalar& colour, double width_px, bool closed,
                                      double opacity) {
  auto& out = impl_->layer(layer_name).vertices;
  if (points_px.size() < 2) return;
  const double half = std::max(0.5, width_px / 2.0);
  const size_t segments = closed ? points_px.size() : points_px.size() - 1;
  for (size_t s = 0; s < segments; ++s) {
    const Eigen::Vector2d& a = points_px[s];
    const Eigen::Vector2d& b = points_px[(s + 1) % points_px.size()];
    if (a.allFinite() && b.allFinite()) push_piece(out, a, b, half, colour, opacity);
  }
}

void OverlayRenderer::set_layer_image(const std::string& layer_name, const cv::Mat& bgra) {
  impl_->layer(layer_name).image_count = 0;
  if (bgra.empty()) return;
  if (bgra.cols != camera_.width || bgra.rows != camera_.height) {
    throw Error("overlay renderer: layer image of '" + layer_name + "' must be 8-bit BGRA of " +
                std::to_string(camera_.width) + "x" + std::to_string(camera_.height));
  }
  add_layer_image(layer_name, bgra, cv::Point(0, 0));
}

uint64_t OverlayRenderer::new_image_revision() {
  static std::atomic<uint64_t> next{1};
  return next++;
}

void OverlayRenderer::add_layer_image(const std::string& layer_name, const cv::Mat& bgra,
                                      const cv::Point& origin, uint64_t revision) {
  auto& layer = impl_->layer(layer_name);
  if (bgra.empty()) return;
  if (bgra.type() != CV_8UC4 || origin.x < 0 || origin.y < 0 ||
      origin.x + bgra.cols > camera_.width || origin.y + bgra.rows > camera_.height) {
    throw Error("overlay renderer: an image of layer '" + layer_name +
                "' must be 8-bit BGRA and lie inside the " + std::to_string(camera_.width) + "x" +
                std::to_string(camera_.height) + " frame");
  }
  if (revision != 0 && layer.image_count < layer.images.size()) {
    auto& kept = layer.images[layer.image_count];
    if (kept.revision == revision && kept.width == bgra.cols && kept.height == bgra.rows) {
      kept.origin = origin;  // the same pixels: already in the texture
      kept.warp.reset();
      ++layer.image_count;
      return;
    }
  }
  const cv::Mat contiguous = bgra.isContinuous() ? bgra : bgra.clone();
  impl_->make_current();
  if (layer.image_count == layer.images.size()) {
    Impl::Layer::Image image;
    glGenTextures(1, &image.texture);
    glBindTexture(GL_TEXTURE_2D, image.texture);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    layer.images.push_back(image);
  }
  auto& image = layer.images[layer.image_count++];
  image.origin = origin;
  image.revision = revision;
  image.warp.reset();
  glBindTexture(GL_TEXTURE_2D, image.texture);
  glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
  image.width = bgra.cols;
  image.height = bgra.rows;
  // Text panels change size from frame to frame: re-allocate only when one outgrows the texture
  // (re-specifying a texture every frame costs drivers a synchronisation).
  if (image.width > image.texture_width || image.height > image.texture_height) {
    image.texture_width = std::max(image.width, image.texture_width);
    image.texture_height = std::max(image.height, image.texture_height);
    glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA8, image.texture_width, image.texture_height, 0, GL_BGRA,
                 GL_UNSIGNED_BYTE, nullptr);
  }
  glTexSubImage2D(GL_TEXTURE_2D, 0, 0, 0, image.width, image.height, GL_BGRA, GL_UNSIGNED_BYTE,
                  contiguous.data);
}

void OverlayRenderer::add_layer_image_warped(const std::string& layer_name, const cv::Mat& bgra,
                                             const cv::Point& origin,
                                             const Eigen::Matrix<double, 2, 3>& warp,
                                             uint64_t revision) {
  if (!warp.allFinite() || std::abs(warp.leftCols<2>().determinant()) < 1e-6) {
    throw Error("overlay renderer: the placement of an image of layer '" + layer_name +
                "' is not an invertible affine map");
  }
  add_layer_image(layer_name, bgra, origin, revision);
  auto& layer = impl_->layer(layer_name);
  if (!bgra.empty()) layer.images[layer.image_count - 1].warp = warp;
}

void OverlayRenderer::set_layer_draw(const std::string& layer,
                                     std::function<void(const DrawContext&)> draw) {
  impl_->layer(layer).draw = std::move(draw);
}

void OverlayRenderer::clear_layer(const std::string& layer_name) {
  auto& layer = impl_->layer(layer_name);
  layer.vertices.clear();
  layer.image_count = 0;
  layer.draw = nullptr;
}

void OverlayRenderer::set_layer_visible(const std::string& layer, bool visible) {
  impl_->layer(layer).visible = visible;
}

bool OverlayRenderer::layer_visible(const std::string& layer) const {
  const auto* l = impl_->find(layer);
  return l ? l->visible : false;
}

std::vector<std::string> OverlayRenderer::layer_names() const {
  std::vector<std::string> names;
  for (const auto& l : impl_->layers) names.push_back(l.name);
  return names;
}

void OverlayRenderer::draw() {
  impl_->make_current();
  glBindFramebuffer(GL_FRAMEBUFFER, impl_->fbo);
  glViewport(0, 0, camera_.width, camera_.height);
  glDisable(GL_DEPTH_TEST);
  glClearColor(0, 0, 0, 1);
  glClear(GL_COLOR_BUFFER_BIT);
  glBindVertexArray(impl_->vao);
  const auto w = static_cast<float>(camera_.width), h = static_cast<float>(camera_.height);

  if (impl_->has_frame) {
    glDisable(GL_BLEND);
    glUseProgram(impl_->background_program);
    glActiveTexture(GL_TEXTURE0);
    glBindTexture(GL_TEXTURE_2D, impl_->frame_texture);
    glUniform1i(glGetUniformLocation(impl_->background_program, "frame"), 0);
    glUniform2f(glGetUniformLocation(impl_->background_program, "size"), w, h);
    glUniform1f(glGetUniformLocation(impl_->background_program, "with_alpha"), 0.0f);
    glUniform1f(glGetUniformLocation(impl_->background_program, "packed_bgr"), 1.0f);
    glUniform2i(glGetUniformLocation(impl_->background_program, "offset"), 0, 0);
    glDrawArrays(GL_TRIANGLES, 0, 3);
  }

  // Layer by layer, in order: its own drawing step, its shapes, its image.
  glEnable(GL_BLEND);
  glBlendFunc(GL_SRC_ALPHA, GL_ONE_MINUS_SRC_ALPHA);
  const DrawContext context{camera_, camera_.width, camera_.height};
  for (const auto& l : impl_->layers) {
    if (!l.visible) continue;
    if (l.draw) {
      l.draw(context);
      glBindFramebuffer(GL_FRAMEBUFFER, impl_->fbo);
      glViewport(0, 0, camera_.width, camera_.height);
      glEnable(GL_BLEND);
      glBlendFunc(GL_SRC_ALPHA, GL_ONE_MINUS_SRC_ALPHA);
      glBindVertexArray(impl_->vao);
    }
    if (!l.vertices.empty()) {
      glUseProgram(impl_->shape_program);
      glUniform2f(glGetUniformLocation(impl_->shape_program, "size"), w, h);
      glBindBuffer(GL_ARRAY_BUFFER, impl_->vbo);
      glBufferData(GL_ARRAY_BUFFER, static_cast<GLsizeiptr>(l.vertices.size() * sizeof(Vertex)),
                   l.vertices.data(), GL_STREAM_DRAW);
      glDrawArrays(GL_TRIANGLES, 0, static_cast<GLsizei>(l.vertices.size()));
    }
    if (l.image_count > 0) {
      // Each image over its own rectangle only (scissor), sampled texel for pixel.
      glUseProgram(impl_->background_program);
      glActiveTexture(GL_TEXTURE0);
      glUniform1i(glGetUniformLocation(impl_->background_program, "frame"), 0);
      glUniform2f(glGetUniformLocation(impl_->background_program, "size"), w, h);
      glUniform1f(glGetUniformLocation(impl_->background_program, "with_alpha"), 1.0f);
      glUniform1f(glGetUniformLocation(impl_->background_program, "packed_bgr"), 0.0f);
      glEnable(GL_SCISSOR_TEST);
      const GLint warped = glGetUniformLocation(impl_->background_program, "warped");
      for (size_t i = 0; i < l.image_count; ++i) {
        const auto& image = l.images[i];
        glBindTexture(GL_TEXTURE_2D, image.texture);
        glUniform2i(glGetUniformLocation(impl_->background_program, "offset"), image.origin.x,
                    image.origin.y);
        if (!image.warp) {
          glUniform1f(warped, 0.0f);
          glScissor(image.origin.x, camera_.height - image.origin.y - image.height, image.width,
                    image.height);
        } else {
          // Frame pixel -> image texel: the inverse of the placement, after the origin.
          Eigen::Matrix3d forward = Eigen::Matrix3d::Identity();
          forward.topRows<2>() = *image.warp;
          Eigen::Matrix3d to_texel = forward.inverse();
          to_texel.row(0) -= image.origin.x * to_texel.row(2);
          to_texel.row(1) -= image.origin.y * to_texel.row(2);
          const Eigen::Matrix3f m = to_texel.cast<float>();
          glUniform1f(warped, 1.0f);
          glUniformMatrix3fv(glGetUniformLocation(impl_->background_program, "from_frame"), 1,
                             GL_FALSE, m.data());  // Eigen is column-major too
          glUniform2i(glGetUniformLocation(impl_->background_program, "extent"), image.width,
                      image.height);
          // Only over the placed image's bounding box, a pixel to spare.
          double lo[2] = {1e30, 1e30}, hi[2] = {-1e30, -1e30};
          for (const double cx : {-1.0, double(image.width)}) {
            for (const double cy : {-1.0, double(image.height)}) {
              const Eigen::Vector2d c =
                  *image.warp * Eigen::Vector3d(image.origin.x + cx, image.origin.y + cy, 1.0);
              for (int a = 0; a < 2; ++a) {
                lo[a] = std::min(lo[a], c[a]);
                hi[a] = std::max(hi[a], c[a]);
              }
            }
          }
          const int x0 = std::clamp(int(std::floor(lo[0])), 0, camera_.width);
          const int x1 = std::clamp(int(std::ceil(hi[0])) + 1, 0, camera_.width);
          const int y0 = std::clamp(int(std::floor(lo[1])), 0, camera_.height);
          const int y1 = std::clamp(int(std::ceil(hi[1])) + 1, 0, camera_.height);
          glScissor(x0, camera_.height - y1, x1 - x0, y1 - y0);
        }
        glDrawArrays(GL_TRIANGLES, 0, 3);
      }
      glUniform1f(warped, 0.0f);
      glDisable(GL_SCISSOR_TEST);
    }
  }
  const GLenum err = glGetError();
  if (err != GL_NO_ERROR) {
    throw Error("overlay renderer: OpenGL error " + std::to_string(err) + " while drawing");
  }
}

bool OverlayRenderer::present() {
  if (!impl_->window) return true;  // headless EGL: nothing to show
  impl_->make_current();
  int fw = 0, fh = 0;
  glfwGetFramebufferSize(impl_->window, &fw, &fh);
  glBindFramebuffer(GL_READ_FRAMEBUFFER, impl_->fbo);
  glBindFramebuffer(GL_DRAW_FRAMEBUFFER, 0);
  glDrawBuffer(GL_BACK);
  glBlitFramebuffer(0, 0, camera_.width, camera_.height, 0, 0, fw, fh, GL_COLOR_BUFFER_BIT,
                    (fw == camera_.width && fh == camera_.height) ? GL_NEAREST : GL_LINEAR);
  glBindFramebuffer(GL_FRAMEBUFFER, impl_->fbo);
  glfwSwapBuffers(impl_->window);
  glfwPollEvents();
  return !glfwWindowShouldClose(impl_->window);
}

std::vector<int> OverlayRenderer::poll_keys() {
  if (!impl_->window) return {};
  glfwPollEvents();
  std::vector<int> keys;
  keys.swap(impl_->keys);
  return keys;
}

bool OverlayRenderer::window_open() const {
  return !impl_->window || !glfwWindowShouldClose(impl_->window);
}

std::vector<InputEvent> OverlayRenderer::poll_events() {
  if (!impl_->window) return {};
  glfwPollEvents();
  std::vector<InputEvent> events(impl_->events.begin(), impl_->events.end());
  impl_->events.clear();
  return events;
}

cv::Mat OverlayRenderer::render() {
  draw();
  impl_->make_current();
  glBindFramebuffer(GL_FRAMEBUFFER, impl_->fbo);
  // The readback buffer is kept between frames: a fresh 6 MB buffer per 1080p frame costs more in
  // page faults than the readback itself.
  cv::Mat& flipped = impl_->readback;
  flipped.create(camera_.height, camera_.width, CV_8UC3);
  glPixelStorei(GL_PACK_ALIGNMENT, 1);
  glReadBuffer(GL_COLOR_ATTACHMENT0);
  glReadPixels(0, 0, camera_.width, camera_.height, GL_BGR, GL_UNSIGNED_BYTE, flipped.data);
  const GLenum err = glGetError();
  if (err != GL_NO_ERROR) {
    throw Error("overlay renderer: OpenGL error " + std::to_string(err) + " while rendering");
  }
  cv::Mat image;
  cv::flip(flipped, image, 0);
  return image;
}

}  // namespace crepuscular::overlay

namespace crepuscular::overlay {

void OverlayRenderer::finish() {
  impl_->make_current();
  glFinish();
}

cv::Mat OverlayRenderer::screenshot_window() {
  if (!impl_->window) {
    throw Error("overlay renderer: screenshot_window() needs a window; this renderer is headless (" +
                impl_->kind + ")");
  }
  if (!options_.visible) {
    throw Error("overlay renderer: screenshot_window() needs a shown window (visible = true)");
  }
  impl_->make_current();
  glFinish();
  Display* display = glfwGetX11Display();
  const Window window = glfwGetX11Window(impl_->window);
  if (!display || !window) {
    throw Error("overlay renderer: screenshot_window() needs an X11 window");
  }
  XSync(display, False);
  XWindowAttributes attributes;
  if (!XGetWindowAttributes(display, window, &attributes) || attributes.map_state != IsViewable) {
    throw Error("overlay renderer: screenshot_window(): the window is not mapped on the X server");
  }
  XImage* image =
      XGetImage(display, window, 0, 0, static_cast<unsigned>(attributes.width),
                static_cast<unsigned>(attributes.height), AllPlanes, ZPixmap);
  if (!image) throw Error("overlay renderer: screenshot_window(): XGetImage failed");
  // Each channel from its mask in the server's pixel format, scaled to 8 bits.
  const auto channel = [](unsigned long pixel, unsigned long mask) {
    if (!mask) return static_cast<uchar>(0);
    int shift = 0;
    while (!((mask >> shift) & 1UL)) ++shift;
    const unsigned long max = mask >> shift;
    return static_cast<uchar>(((pixel & mask) >> shift) * 255UL / max);
  };
  cv::Mat bgr(attributes.height, attributes.width, CV_8UC3);
  for (int y = 0; y < bgr.rows; ++y) {
    auto* row = bgr.ptr<cv::Vec3b>(y);
    for (int x = 0; x < bgr.cols; ++x) {
      const unsigned long p = XGetPixel(image, x, y);
      row[x] = cv::Vec3b(channel(p, image->blue_mask), channel(p, image->green_mask),
                         channel(p, image->red_mask));
    }
  }
  XDestroyImage(image);
  return bgr;
}

}  // namespace crepuscular::overlay
