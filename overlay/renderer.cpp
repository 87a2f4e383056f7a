#include "overlay/renderer.hpp"

#define GL_GLEXT_PROTOTYPES 1
#include <GL/glcorearb.h>
#define GLFW_INCLUDE_NONE
#include <GLFW/glfw3.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <mutex>

#include <opencv2/core.hpp>
#include <spdlog/spdlog.h>

#include "kernels/error.hpp"

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
out vec4 out_colour;
void main() {
  ivec2 texel = ivec2(int(gl_FragCoord.x), int(size.y) - 1 - int(gl_FragCoord.y));
  vec4 c = texelFetch(frame, texel, 0);
  out_colour = vec4(c.rgb, with_alpha > 0.5 ? c.a : 1.0);
}
)";

GLuint compile(GLenum type, const char* source) {
  const GLuint shader = glCreateShader(type);
  glShaderSource(shader, 1, &source, nullptr);
  glCompileShader(shader);
  GLint ok = 0;
  glGetShaderiv(shader, GL_COMPILE_STATUS, &ok);
  if (!ok) {
    char log[2048];
    glGetShaderInfoLog(shader, sizeof(log), nullptr, log);
    glDeleteShader(shader);
    throw Error(std::string("overlay renderer: shader compilation failed: ") + log);
  }
  return shader;
}

GLuint link(const char* vertex, const char* fragment) {
  const GLuint vs = compile(GL_VERTEX_SHADER, vertex);
  const GLuint fs = compile(GL_FRAGMENT_SHADER, fragment);
  const GLuint program = glCreateProgram();
  glAttachShader(program, vs);
  glAttachShader(program, fs);
  glLinkProgram(program);
  glDeleteShader(vs);
  glDeleteShader(fs);
  GLint ok = 0;
  glGetProgramiv(program, GL_LINK_STATUS, &ok);
  if (!ok) {
    char log[2048];
    glGetProgramInfoLog(program, sizeof(log), nullptr, log);
    glDeleteProgram(program);
    throw Error(std::string("overlay renderer: shader link failed: ") + log);
  }
  return program;
}

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
    GLuint image_texture = 0;
    bool has_image = false;
  };
  GLFWwindow* window = nullptr;
  std::vector<int> keys;  // pressed since the last poll_keys()
  GLuint fbo = 0, colour_rb = 0, frame_texture = 0;
  GLuint shape_program = 0, background_program = 0;
  GLuint vao = 0, vbo = 0;
  bool has_frame = false;
  std::vector<Layer> layers;

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
};

OverlayRenderer::OverlayRenderer(const calibration::CameraModel& camera, RendererOptions options)
    : camera_(camera), options_(options), impl_(std::make_unique<Impl>()) {
  camera_.validate("overlay renderer camera");
  if (!(options_.max_segment_px > 0) || !(options_.near_mm > 0)) {
    throw Error("overlay renderer: max_segment_px and near_mm must be > 0");
  }
  glfw_acquire();
  glfwWindowHint(GLFW_CONTEXT_VERSION_MAJOR, 3);
  glfwWindowHint(GLFW_CONTEXT_VERSION_MINOR, 3);
  glfwWindowHint(GLFW_OPENGL_PROFILE, GLFW_OPENGL_CORE_PROFILE);
  glfwWindowHint(GLFW_OPENGL_FORWARD_COMPAT, GLFW_TRUE);
  glfwWindowHint(GLFW_VISIBLE, options_.visible ? GLFW_TRUE : GLFW_FALSE);
  glfwWindowHint(GLFW_RESIZABLE, GLFW_FALSE);
  impl_->window = glfwCreateWindow(camera_.width, camera_.height, "Crepuscular", nullptr, nullptr);
  if (!impl_->window) {
    glfw_release();
    throw Error("overlay renderer: cannot create an OpenGL 3.3 core context (" + glfw_last_error +
                ")");
  }
  glfwMakeContextCurrent(impl_->window);
  glfwSetWindowUserPointer(impl_->window, impl_.get());
  glfwSetKeyCallback(impl_->window, [](GLFWwindow* w, int key, int, int action, int) {
    if (action == GLFW_PRESS) static_cast<Impl*>(glfwGetWindowUserPointer(w))->keys.push_back(key);
  });
  spdlog::debug("overlay renderer: {} / {}", reinterpret_cast<const char*>(glGetString(GL_RENDERER)),
                reinterpret_cast<const char*>(glGetString(GL_VERSION)));

  // Off-screen target of the image size: the same pixels whether the window is shown or hidden.
  glGenRenderbuffers(1, &impl_->colour_rb);
  glBindRenderbuffer(GL_RENDERBUFFER, impl_->colour_rb);
  glRenderbufferStorage(GL_RENDERBUFFER, GL_RGBA8, camera_.width, camera_.height);
  glGenFramebuffers(1, &impl_->fbo);
  glBindFramebuffer(GL_FRAMEBUFFER, impl_->fbo);
  glFramebufferRenderbuffer(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_RENDERBUFFER, impl_->colour_rb);
  if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE) {
    glfwDestroyWindow(impl_->window);
    glfw_release();
    throw Error("overlay renderer: off-screen framebuffer incomplete");
  }

  glGenTextures(1, &impl_->frame_texture);
  glBindTexture(GL_TEXTURE_2D, impl_->frame_texture);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  glTexImage2D(GL_TEXTURE_2D, 0, GL_RGB8, camera_.width, camera_.height, 0, GL_BGR,
               GL_UNSIGNED_BYTE, nullptr);

  impl_->shape_program = link(kShapeVertex, kShapeFragment);
  impl_->background_program = link(kBackgroundVertex, kBackgroundFragment);

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
  if (!impl_ || !impl_->window) return;
  glfwMakeContextCurrent(impl_->window);
  glDeleteBuffers(1, &impl_->vbo);
  glDeleteVertexArrays(1, &impl_->vao);
  glDeleteProgram(impl_->shape_program);
  glDeleteProgram(impl_->background_program);
  glDeleteTextures(1, &impl_->frame_texture);
  for (auto& l : impl_->layers)
    if (l.image_texture) glDeleteTextures(1, &l.image_texture);
  glDeleteFramebuffers(1, &impl_->fbo);
  glDeleteRenderbuffers(1, &impl_->colour_rb);
  glfwDestroyWindow(impl_->window);
  glfw_release();
}

std::string OverlayRenderer::gl_description() const {
  glfwMakeContextCurrent(impl_->window);
  return std::string(reinterpret_cast<const char*>(glGetString(GL_RENDERER))) + " / " +
         reinterpret_cast<const char*>(glGetString(GL_VERSION));
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
  glfwMakeContextCurrent(impl_->window);
  glBindTexture(GL_TEXTURE_2D, impl_->frame_texture);
  glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
  glTexSubImage2D(GL_TEXTURE_2D, 0, 0, 0, camera_.width, camera_.height, GL_BGR, GL_UNSIGNED_BYTE,
                  contiguous.data);
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
  auto& layer = impl_->layer(layer_name);
  if (bgra.empty()) {
    layer.has_image = false;
    return;
  }
  if (bgra.type() != CV_8UC4 || bgra.cols != camera_.width || bgra.rows != camera_.height) {
    throw Error("overlay renderer: layer image of '" + layer_name + "' must be 8-bit BGRA of " +
                std::to_string(camera_.width) + "x" + std::to_string(camera_.height));
  }
  const cv::Mat contiguous = bgra.isContinuous() ? bgra : bgra.clone();
  glfwMakeContextCurrent(impl_->window);
  if (!layer.image_texture) {
    glGenTextures(1, &layer.image_texture);
    glBindTexture(GL_TEXTURE_2D, layer.image_texture);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA8, camera_.width, camera_.height, 0, GL_BGRA,
                 GL_UNSIGNED_BYTE, nullptr);
  }
  glBindTexture(GL_TEXTURE_2D, layer.image_texture);
  glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
  glTexSubImage2D(GL_TEXTURE_2D, 0, 0, 0, camera_.width, camera_.height, GL_BGRA,
                  GL_UNSIGNED_BYTE, contiguous.data);
  layer.has_image = true;
}

void OverlayRenderer::set_layer_draw(const std::string& layer,
                                     std::function<void(const DrawContext&)> draw) {
  impl_->layer(layer).draw = std::move(draw);
}

void OverlayRenderer::clear_layer(const std::string& layer_name) {
  auto& layer = impl_->layer(layer_name);
  layer.vertices.clear();
  layer.has_image = false;
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
  glfwMakeContextCurrent(impl_->window);
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
    if (l.has_image) {
      glUseProgram(impl_->background_program);
      glActiveTexture(GL_TEXTURE0);
      glBindTexture(GL_TEXTURE_2D, l.image_texture);
      glUniform1i(glGetUniformLocation(impl_->background_program, "frame"), 0);
      glUniform2f(glGetUniformLocation(impl_->background_program, "size"), w, h);
      glUniform1f(glGetUniformLocation(impl_->background_program, "with_alpha"), 1.0f);
      glDrawArrays(GL_TRIANGLES, 0, 3);
    }
  }
  const GLenum err = glGetError();
  if (err != GL_NO_ERROR) {
    throw Error("overlay renderer: OpenGL error " + std::to_string(err) + " while drawing");
  }
}

bool OverlayRenderer::present() {
  glfwMakeContextCurrent(impl_->window);
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
  glfwPollEvents();
  std::vector<int> keys;
  keys.swap(impl_->keys);
  return keys;
}

cv::Mat OverlayRenderer::render() {
  draw();
  glfwMakeContextCurrent(impl_->window);
  glBindFramebuffer(GL_FRAMEBUFFER, impl_->fbo);
  cv::Mat flipped(camera_.height, camera_.width, CV_8UC3);
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
