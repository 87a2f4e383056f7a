#include "overlay/volume_rendering.hpp"

#define GL_GLEXT_PROTOTYPES 1
#include <GL/glcorearb.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <string>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "overlay/gl_program.hpp"
#include "planning/safety/unknown.hpp"

namespace crepuscular::overlay {

namespace {

// Most samples one ray takes (a 512^3 grid's diagonal at half a voxel per step is ~1800).
constexpr int kMaxSteps = 8192;

const char* kFullScreenVertex = R"(#version 330 core
void main() {
  vec2 corners[3] = vec2[3](vec2(-1.0, -1.0), vec2(3.0, -1.0), vec2(-1.0, 3.0));
  gl_Position = vec4(corners[gl_VertexID], 0.0, 1.0);
}
)";

// Ray casting (§3.4): one ray per pixel of the viewport from the camera centre along the pixel's
// undistorted direction, into the voxel grid's index space; the box of classified (or anatomy)
// voxels is crossed in steps of step_mm, each step sampled at its middle from the nearest voxel,
// composited front to back. A sample whose anatomy kind differs from the previous sample's adds
// that kind's surface (alpha, lit by the angle between the ray and the kind's gradient); a
// sample's class adds alpha = 1 - exp(-k * length), unlit. Output is premultiplied.
// reference_pixel() is the same computation on the CPU: keep the two in step.
const char* kMarchFragment = R"(#version 330 core
uniform usampler3D classes;  // r: class, g: leap distance, b: anatomy kind
uniform sampler2D rays;
uniform mat3 M;
uniform vec3 m0;
uniform vec3 box_lo;
uniform vec3 box_hi;
uniform ivec3 dims;
uniform vec3 spacing;
uniform vec2 origin;  // the viewport's lower-left corner in the framebuffer
uniform float opacity[5];
uniform vec3 colour[5];
uniform vec4 full_step[5];  // a whole step of each class: premultiplied colour, alpha
uniform vec4 surface[16];   // per anatomy kind: colour, alpha (0: not drawn)
uniform float ambient;
uniform float step_mm;
uniform int rows;
uniform int max_steps;
uniform float opaque;
out vec4 out_colour;
float inside(ivec3 v, uint s) {
  return texelFetch(classes, clamp(v, ivec3(0), dims - 1), 0).b == s ? 1.0 : 0.0;
}
// Lighting of a surface of kind s at voxel v seen along D: its gradient from central differences
// of the kind's indicator, compared with the ray in physical space.
float shade(ivec3 v, uint s, vec3 D) {
  vec3 g = vec3(inside(v + ivec3(1, 0, 0), s) - inside(v - ivec3(1, 0, 0), s),
                inside(v + ivec3(0, 1, 0), s) - inside(v - ivec3(0, 1, 0), s),
                inside(v + ivec3(0, 0, 1), s) - inside(v - ivec3(0, 0, 1), s));
  float len = length(g / spacing) * length(D * spacing);
  float c = len > 0.0 ? abs(dot(g, D)) / len : 1.0;
  return ambient + (1.0 - ambient) * c;
}
void main() {
  out_colour = vec4(0.0);
  ivec2 p = ivec2(int(gl_FragCoord.x - origin.x), rows - 1 - int(gl_FragCoord.y - origin.y));
  vec3 d = texelFetch(rays, p, 0).xyz;
  if (dot(d, d) < 0.5) return;
  vec3 D = M * d;
  float t_in = 0.0;
  float t_out = 1e30;
  for (int a = 0; a < 3; ++a) {
    if (abs(D[a]) < 1e-12) {
      if (m0[a] < box_lo[a] || m0[a] > box_hi[a]) return;
    } else {
      float t1 = (box_lo[a] - m0[a]) / D[a];
      float t2 = (box_hi[a] - m0[a]) / D[a];
      t_in = max(t_in, min(t1, t2));
      t_out = min(t_out, max(t1, t2));
    }
  }
  if (!(t_out > t_in)) return;
  int n = min(int(ceil((t_out - t_in) / step_mm)), max_steps);
  // Empty-space leaping: a voxel `g` (Chebyshev, in voxels) away from any voxel of a shown class
  // and any anatomy surface lets the samples whose positions move less than g - 1 voxels per axis
  // be passed over: they all fall in voxels of no shown class, of one kind (the CPU reference takes
  // them and adds nothing there).
  float reach = max(abs(D.x), max(abs(D.y), abs(D.z))) * step_mm;
  vec3 C = vec3(0.0);
  float A = 0.0;
  // Anatomy kind of the previous sample; the first sample's kind shows no surface (the grid's
  // faces cut through the anatomy, they are not surfaces of it).
  uint kind = 255u;
  int i = 0;
  while (i < n) {
    float t0 = t_in + float(i) * step_mm;
    float dt = i < n - 1 ? step_mm : t_out - t0;
    float t = t0 + 0.5 * dt;
    ivec3 v = clamp(ivec3(floor(m0 + t * D + 0.5)), ivec3(0), dims - 1);
    uvec3 cg = texelFetch(classes, v, 0).rgb;
    if (kind == 255u) kind = cg.b;
    if (cg.b != kind) {
      kind = cg.b;
      vec4 s = surface[kind];
      if (s.a > 0.0) {
        float a = s.a;
        C += (1.0 - A) * a * shade(v, kind, D) * s.rgb;
        A += (1.0 - A) * a;
        if (A >= opaque) break;
      }
    }
    int c = int(cg.r);
    if (c == 0 || opacity[c] <= 0.0) {  // nothing shown here: leap as far as nothing is shown
      i += 1 + max(0, int(floor((float(cg.g) - 1.01) / reach)));
      continue;
    }
    {
      vec4 s = i < n - 1 ? full_step[c] : vec4(colour[c], 1.0) * (1.0 - exp(-opacity[c] * dt));
      C += (1.0 - A) * s.rgb;
      A += (1.0 - A) * s.a;
      if (A >= opaque) break;
    }
    ++i;
  }
  out_colour = vec4(C, A);
}
)";

// Reduced-resolution result over the full image: bilinear in premultiplied colour.
const char* kCompositeFragment = R"(#version 330 core
uniform sampler2D image;
uniform vec2 size;
uniform vec2 origin;  // the viewport's lower-left corner in the framebuffer
out vec4 out_colour;
void main() {
  out_colour = texture(image, (gl_FragCoord.xy - origin) / size);
}
)";

bool same_camera(const calibration::CameraModel& a, const calibration::CameraModel& b) {
  return a.width == b.width && a.height == b.height && a.fx == b.fx && a.fy == b.fy &&
         a.cx == b.cx && a.cy == b.cy && a.model == b.model && a.distortion == b.distortion;
}

void validate_options(const VolumeRenderingOptions& o) {
  for (int c = 0; c < 3; ++c) {
    if (!(o.opacity_per_mm[c] >= 0) || !std::isfinite(o.opacity_per_mm[c])) {
      throw Error("volume rendering: opacity_per_mm[" + std::to_string(c) + "] is " +
                  std::to_string(o.opacity_per_mm[c]) + ", expected a finite value >= 0");
    }
  }
  if (!(o.unknown_opacity_per_mm >= 0) || !std::isfinite(o.unknown_opacity_per_mm)) {
    throw Error("volume rendering: unknown_opacity_per_mm is " +
                std::to_string(o.unknown_opacity_per_mm) + ", expected a finite value >= 0");
  }
  if (!(o.step_mm >= 0) || !std::isfinite(o.step_mm)) {
    throw Error("volume rendering: step_mm is " + std::to_string(o.step_mm) +
                ", expected >= 0 (0: half the smallest voxel spacing)");
  }
  if (!(o.resolution_scale > 0 && o.resolution_scale <= 1)) {
    throw Error("volume rendering: resolution_scale is " + std::to_string(o.resolution_scale) +
                ", expected 0 < scale <= 1");
  }
}

// Chebyshev distance (in voxels, capped at kMaxLeap) from each voxel to the nearest voxel with a
// class: every voxel closer than that to it (in each index) has none. Separable: exact 1D distance
// along i, then min over j' of max(|j - j'|, g(j')), then the same along k.
constexpr int kMaxLeap = 32;
// Voxels that stop a leap: those of a shown class (bit c of `shown`), and those with a
// 6-neighbour of another anatomy kind (a ray crossing into another kind passes one of them).
std::vector<uint8_t> empty_distance(const planning::Index3& dims, const std::vector<uint8_t>& classes,
                                    const std::vector<uint8_t>& kinds, unsigned shown) {
  const int64_t nx = dims[0], ny = dims[1], nz = dims[2];
  std::vector<uint8_t> g(classes.size());
#pragma omp parallel for schedule(static)
  for (size_t v = 0; v < classes.size(); ++v) {
    g[v] = classes[v] && ((shown >> classes[v]) & 1u) ? 0 : kMaxLeap;
  }
  if (!kinds.empty()) {
    const int64_t strides[3] = {1, nx, nx * ny};
    const int64_t n[3] = {nx, ny, nz};
    // Each voxel marks itself where a neighbour differs (both sides of a face mark themselves).
#pragma omp parallel for schedule(static)
    for (int64_t k = 0; k < nz; ++k) {
      for (int64_t j = 0; j < ny; ++j) {
        for (int64_t i = 0; i < nx; ++i) {
          const int64_t v = i + nx * (j + ny * k);
          const int64_t at[3] = {i, j, k};
          for (int a = 0; a < 3 && g[size_t(v)]; ++a) {
            if ((at[a] + 1 < n[a] && kinds[size_t(v + strides[a])] != kinds[size_t(v)]) ||
                (at[a] > 0 && kinds[size_t(v - strides[a])] != kinds[size_t(v)])) {
              g[size_t(v)] = 0;
            }
          }
        }
      }
    }
  }
  // One pass along an axis: g(x) <- min over x' of max(|x - x'|, g(x')), within kMaxLeap.
  const auto pass = [&](int64_t n, int64_t stride, int64_t lines, auto&& line_start) {
#pragma omp parallel for schedule(static)
    for (int64_t l = 0; l < lines; ++l) {
      std::vector<uint8_t> in(size_t(n), 0);
      const int64_t start = line_start(l);
      for (int64_t x = 0; x < n; ++x) in[size_t(x)] = g[size_t(start + x * stride)];
      for (int64_t x = 0; x < n; ++x) {
        int best = in[size_t(x)];
        for (int64_t r = 1; r < best; ++r) {
          if (x - r >= 0) best = std::min(best, std::max(int(r), int(in[size_t(x - r)])));
          if (x + r < n) best = std::min(best, std::max(int(r), int(in[size_t(x + r)])));
        }
        g[size_t(start + x * stride)] = uint8_t(best);
      }
    }
  };
  pass(nx, 1, ny * nz, [&](int64_t l) { return l * nx; });
  pass(ny, nx, nx * nz, [&](int64_t l) { return (l % nx) + (l / nx) * nx * ny; });
  pass(nz, nx * ny, nx * ny, [&](int64_t l) { return l; });
  return g;
}

// Throws Error when OpenGL reports an error (`during`: what was being done).
void throw_on_gl_error(const char* during) {
  const GLenum err = glGetError();
  if (err != GL_NO_ERROR) {
    throw Error("volume rendering: OpenGL error " + std::to_string(err) + " " + during);
  }
}

// Pixels per axis the rays are cast on: the image's, or its reduced version's.
int cast_size(int image_size, double resolution_scale) {
  return resolution_scale < 1 ? std::max(1, int(std::lround(image_size * resolution_scale)))
                              : image_size;
}

// Classes of the transfer function: 0 none, 1..3 safe, medium, dangerous, 4 unknown.
constexpr int kClassCount = 5;
constexpr uint8_t kUnknownClass = 4;

// Per class: absorption per mm (0 when hidden) and colour (RGB 0..255).
struct ClassLook {
  double opacity = 0;
  planning::Rgb colour{0, 0, 0};
};
std::array<ClassLook, kClassCount> class_looks(const VolumeRenderingOptions& options) {
  std::array<ClassLook, kClassCount> looks{};
  const bool shown[3] = {options.show_safe, options.show_medium, options.show_dangerous};
  const auto colours = planning::class_colours(options.palette);
  for (size_t c = 0; c < 3; ++c) {
    looks[c + 1] = {shown[c] ? options.opacity_per_mm[c] : 0.0, colours[c]};
  }
  looks[kUnknownClass] = {options.show_unknown ? options.unknown_opacity_per_mm : 0.0,
                          kUnknownGrey};
  return looks;
}

// The alpha of one crossing of each anatomy kind's surface (0 when hidden or kind 0).
std::array<double, kMaxAnatomyKinds> surface_alphas(const std::vector<AnatomySurface>& surfaces,
                                                    uint32_t hidden) {
  std::array<double, kMaxAnatomyKinds> a{};
  for (size_t k = 1; k < surfaces.size() && k < a.size(); ++k) {
    a[k] = (hidden >> k) & 1u ? 0.0 : surfaces[k].opacity;
  }
  return a;
}

// The march shader's per-class uniforms, index 0 being "no class": absorption per mm (0 when the
// class is hidden), colour 0..1, and one whole step's premultiplied colour and alpha.
struct ClassUniforms {
  float opacity[kClassCount] = {};
  float colour[kClassCount * 3] = {};
  float full_step[kClassCount * 4] = {};
};

ClassUniforms class_uniforms(const VolumeRenderingOptions& options, float step_mm) {
  ClassUniforms u;
  const auto looks = class_looks(options);
  for (int c = 1; c < kClassCount; ++c) {
    u.opacity[c] = float(looks[size_t(c)].opacity);
    for (int ch = 0; ch < 3; ++ch)
      u.colour[c * 3 + ch] = float(looks[size_t(c)].colour[size_t(ch)] / 255.0);
  }
  for (int c = 1; c < kClassCount; ++c) {
    const double a = 1.0 - std::exp(-double(u.opacity[c]) * double(step_mm));
    for (int ch = 0; ch < 3; ++ch) u.full_step[c * 4 + ch] = float(u.colour[c * 3 + ch] * a);
    u.full_step[c * 4 + 3] = float(a);
  }
  return u;
}

}  // namespace

Eigen::Vector3f pixel_ray(const calibration::CameraModel& camera, double u, double v) {
  const Eigen::Vector2d xy = camera.unproject(Eigen::Vector2d(u, v));
  if (!xy.allFinite()) return Eigen::Vector3f::Zero();
  return Eigen::Vector3d(xy.x(), xy.y(), 1.0).normalized().cast<float>();
}

struct SafetyVolumeRendering::Gl {
  GLuint march_program = 0, composite_program = 0, vao = 0;
  GLuint class_texture = 0, ray_texture = 0;
  GLuint low_texture = 0, low_fbo = 0;  // reduced-resolution target
  int low_width = 0, low_height = 0;
  calibration::CameraModel ray_camera;  // the camera the rays were made for
  int ray_width = 0, ray_height = 0;

  // The programs, the vertex array, the class texture (per voxel: class, and Chebyshev distance
  // in voxels to the nearest classified voxel) and the ray texture, in the current context.
  // Throws Error when the grid exceeds the 3D texture limit or a program does not link; the
  // caller checks glGetError.
  static std::unique_ptr<Gl> create(const planning::Index3& dims);
  // (Re)fills the class texture: per voxel its class, its leap distance for the classes shown
  // (bit c of `shown`; the march leaps over hidden classes), its anatomy kind.
  void upload(const planning::Index3& dims, const std::vector<uint8_t>& voxel_classes,
              const std::vector<uint8_t>& voxel_kinds, unsigned shown);
  unsigned uploaded_shown = ~0u;  // the `shown` of the texture's leap distances (~0: none yet)
  // Re-makes the per-pixel rays of the width x height grid the rays are cast on (the image, or
  // its reduced version whose pixel centres map to image positions by the size ratio) when the
  // camera or that size changed.
  void update_rays(const DrawContext& context, int width, int height);
  // (Re)makes the width x height reduced-resolution target when its size changed. Throws Error
  // when it is incomplete, with target_fbo bound again.
  void update_low_target(int width, int height, GLint target_fbo);
  // Binds the march program with its textures and uniforms, for a cast of `rows` rows.
  void bind_march(const RaySetup& ray, const Eigen::Vector3f& box_lo, const Eigen::Vector3f& box_hi,
                  const planning::ImageGeometry& grid, const ClassUniforms& classes,
                  const float surfaces[4 * kMaxAnatomyKinds], float step_mm, int rows,
                  const GLint viewport[4]) const;
  // Casts into the reduced-resolution target, then binds target_fbo, its viewport and the
  // composite program that draws the target over it.
  void cast_reduced(int width, int height, GLint target_fbo, const GLint viewport[4],
                    const DrawContext& context) const;
};

std::unique_ptr<SafetyVolumeRendering::Gl> SafetyVolumeRendering::Gl::create(
    const planning::Index3& dims) {
  auto gl = std::make_unique<Gl>();
  GLint max_size = 0;
  glGetIntegerv(GL_MAX_3D_TEXTURE_SIZE, &max_size);
  if (dims[0] > max_size || dims[1] > max_size || dims[2] > max_size) {
    throw Error("volume rendering: path safety grid " + std::to_string(dims[0]) + "x" +
                std::to_string(dims[1]) + "x" + std::to_string(dims[2]) +
                " exceeds the OpenGL 3D texture limit of " + std::to_string(max_size));
  }
  gl->march_program = link_gl_program(kFullScreenVertex, kMarchFragment, "volume rendering");
  gl->composite_program =
      link_gl_program(kFullScreenVertex, kCompositeFragment, "volume rendering");
  glGenVertexArrays(1, &gl->vao);
  glGenTextures(1, &gl->class_texture);
  glBindTexture(GL_TEXTURE_3D, gl->class_texture);
  glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
  glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  glTexParameteri(GL_TEXTURE_3D, GL_TEXTURE_MAX_LEVEL, 0);
  glGenTextures(1, &gl->ray_texture);
  glBindTexture(GL_TEXTURE_2D, gl->ray_texture);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAX_LEVEL, 0);
  return gl;
}

void SafetyVolumeRendering::Gl::upload(const planning::Index3& dims,
                                       const std::vector<uint8_t>& voxel_classes,
                                       const std::vector<uint8_t>& voxel_kinds, unsigned shown) {
  const std::vector<uint8_t> distance = empty_distance(dims, voxel_classes, voxel_kinds, shown);
  std::vector<uint8_t> texels(voxel_classes.size() * 4, 0);
#pragma omp parallel for schedule(static)
  for (size_t v = 0; v < voxel_classes.size(); ++v) {
    texels[4 * v] = voxel_classes[v];
    texels[4 * v + 1] = distance[v];
    texels[4 * v + 2] = voxel_kinds.empty() ? 0 : voxel_kinds[v];
  }
  glBindTexture(GL_TEXTURE_3D, class_texture);
  glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
  glTexImage3D(GL_TEXTURE_3D, 0, GL_RGBA8UI, GLsizei(dims[0]), GLsizei(dims[1]),
               GLsizei(dims[2]), 0, GL_RGBA_INTEGER, GL_UNSIGNED_BYTE, texels.data());
  uploaded_shown = shown;
}

void SafetyVolumeRendering::Gl::update_rays(const DrawContext& context, int width, int height) {
  const auto& camera = context.camera;
  if (same_camera(ray_camera, camera) && ray_width == width && ray_height == height) return;
  std::vector<float> rays(size_t(width) * size_t(height) * 3);
  const double sx = double(context.width) / width, sy = double(context.height) / height;
  for (int r = 0; r < height; ++r) {
    for (int c = 0; c < width; ++c) {
      const Eigen::Vector3f d = pixel_ray(camera, (c + 0.5) * sx - 0.5, (r + 0.5) * sy - 0.5);
      std::copy(d.data(), d.data() + 3, rays.begin() + (size_t(r) * size_t(width) + size_t(c)) * 3);
    }
  }
  glBindTexture(GL_TEXTURE_2D, ray_texture);
  glPixelStorei(GL_UNPACK_ALIGNMENT, 4);
  glTexImage2D(GL_TEXTURE_2D, 0, GL_RGB32F, width, height, 0, GL_RGB, GL_FLOAT, rays.data());
  ray_camera = camera;
  ray_width = width;
  ray_height = height;
}

void SafetyVolumeRendering::Gl::update_low_target(int width, int height, GLint target_fbo) {
  if (low_width == width && low_height == height) return;
  if (!low_texture) glGenTextures(1, &low_texture);
  if (!low_fbo) glGenFramebuffers(1, &low_fbo);
  glBindTexture(GL_TEXTURE_2D, low_texture);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_WRAP_S, GL_CLAMP_TO_EDGE);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_WRAP_T, GL_CLAMP_TO_EDGE);
  glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAX_LEVEL, 0);
  glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA16F, width, height, 0, GL_RGBA, GL_FLOAT, nullptr);
  glBindFramebuffer(GL_FRAMEBUFFER, low_fbo);
  glFramebufferTexture2D(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_TEXTURE_2D, low_texture, 0);
  if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE) {
    glBindFramebuffer(GL_FRAMEBUFFER, GLuint(target_fbo));
    throw Error("volume rendering: reduced-resolution framebuffer incomplete");
  }
  low_width = width;
  low_height = height;
}

void SafetyVolumeRendering::Gl::bind_march(const RaySetup& ray, const Eigen::Vector3f& box_lo,
                                           const Eigen::Vector3f& box_hi,
                                           const planning::ImageGeometry& grid,
                                           const ClassUniforms& classes,
                                           const float surfaces[4 * kMaxAnatomyKinds],
                                           float step_mm, int rows,
                                           const GLint viewport[4]) const {
  const auto& dims = grid.dims;
  const GLuint program = march_program;
  glUseProgram(program);
  glBindVertexArray(vao);
  glActiveTexture(GL_TEXTURE0);
  glBindTexture(GL_TEXTURE_3D, class_texture);
  glActiveTexture(GL_TEXTURE1);
  glBindTexture(GL_TEXTURE_2D, ray_texture);
  glUniform1i(glGetUniformLocation(program, "classes"), 0);
  glUniform1i(glGetUniformLocation(program, "rays"), 1);
  glUniformMatrix3fv(glGetUniformLocation(program, "M"), 1, GL_FALSE,
                     ray.M.data());  // column-major
  glUniform3fv(glGetUniformLocation(program, "m0"), 1, ray.m0.data());
  glUniform3fv(glGetUniformLocation(program, "box_lo"), 1, box_lo.data());
  glUniform3fv(glGetUniformLocation(program, "box_hi"), 1, box_hi.data());
  glUniform3i(glGetUniformLocation(program, "dims"), GLint(dims[0]), GLint(dims[1]),
              GLint(dims[2]));
  glUniform4fv(glGetUniformLocation(program, "full_step"), kClassCount, classes.full_step);
  glUniform1fv(glGetUniformLocation(program, "opacity"), kClassCount, classes.opacity);
  glUniform3fv(glGetUniformLocation(program, "colour"), kClassCount, classes.colour);
  glUniform4fv(glGetUniformLocation(program, "surface"), kMaxAnatomyKinds, surfaces);
  glUniform1f(glGetUniformLocation(program, "ambient"), float(kSurfaceAmbient));
  const Eigen::Vector3f spacing = grid.spacing.cast<float>();
  glUniform3fv(glGetUniformLocation(program, "spacing"), 1, spacing.data());
  glUniform2f(glGetUniformLocation(program, "origin"), float(viewport[0]), float(viewport[1]));
  glUniform1f(glGetUniformLocation(program, "step_mm"), step_mm);
  glUniform1i(glGetUniformLocation(program, "rows"), rows);
  glUniform1i(glGetUniformLocation(program, "max_steps"), kMaxSteps);
  glUniform1f(glGetUniformLocation(program, "opaque"), float(kVolumeRenderingOpaque));
}

void SafetyVolumeRendering::Gl::cast_reduced(int width, int height, GLint target_fbo,
                                             const GLint viewport[4],
                                             const DrawContext& context) const {
  glBindFramebuffer(GL_FRAMEBUFFER, low_fbo);
  glViewport(0, 0, width, height);
  glDisable(GL_BLEND);
  glClearColor(0, 0, 0, 0);
  glClear(GL_COLOR_BUFFER_BIT);
  glDrawArrays(GL_TRIANGLES, 0, 3);
  glBindFramebuffer(GL_FRAMEBUFFER, GLuint(target_fbo));
  glViewport(viewport[0], viewport[1], viewport[2], viewport[3]);
  glUseProgram(composite_program);
  glActiveTexture(GL_TEXTURE0);
  glBindTexture(GL_TEXTURE_2D, low_texture);
  glUniform1i(glGetUniformLocation(composite_program, "image"), 0);
  glUniform2f(glGetUniformLocation(composite_program, "size"), float(context.width),
              float(context.height));
  glUniform2f(glGetUniformLocation(composite_program, "origin"), float(viewport[0]),
              float(viewport[1]));
}

SafetyVolumeRendering::SafetyVolumeRendering(const planning::Volume<float>& path_safety,
                                             const planning::SafetyClasses& classes,
                                             VolumeRenderingOptions options,
                                             const planning::Volume<uint8_t>* region_state,
                                             const AnatomyContext* context)
    : geometry_(path_safety.geometry()), options_(options) {
  if (path_safety.empty()) throw Error("volume rendering: the path safety volume is empty");
  geometry_.validate("volume rendering: path safety volume");
  validate_options(options_);
  if (region_state && !region_state->empty() &&
      !region_state->geometry().same_grid(geometry_, 1e-4)) {
    throw Error("volume rendering: the region states are not on the path safety grid");
  }
  if (region_state && region_state->empty()) region_state = nullptr;
  if (context) {
    if (!context->kinds.geometry().same_grid(geometry_, 1e-4)) {
      throw Error("volume rendering: the anatomy context is not on the path safety grid");
    }
    if (context->surfaces.empty() || context->surfaces.size() > size_t(kMaxAnatomyKinds)) {
      throw Error("volume rendering: the anatomy context has " +
                  std::to_string(context->surfaces.size()) + " kinds (expected 1 to " +
                  std::to_string(kMaxAnatomyKinds) + ")");
    }
    for (int64_t v = 0; v < context->kinds.voxel_count(); ++v) {
      if (context->kinds[v] >= context->surfaces.size()) {
        throw Error("volume rendering: anatomy kind " + std::to_string(context->kinds[v]) +
                    " has no surface");
      }
    }
    voxel_kinds_.assign(context->kinds.data(), context->kinds.data() + context->kinds.voxel_count());
    surfaces_ = context->surfaces;
  }
  voxel_classes_.resize(size_t(path_safety.voxel_count()));
  const auto& dims = geometry_.dims;
  // Per slice k: the box of its voxels with a class or a kind (combined below).
  std::vector<Eigen::Vector3i> slice_lo(size_t(dims[2]), Eigen::Vector3i::Constant(
                                                             std::numeric_limits<int>::max())),
      slice_hi(size_t(dims[2]), Eigen::Vector3i::Constant(-1));
#pragma omp parallel for schedule(dynamic, 4)
  for (int64_t k = 0; k < dims[2]; ++k) {
    Eigen::Vector3i& lo = slice_lo[size_t(k)];
    Eigen::Vector3i& hi = slice_hi[size_t(k)];
    for (int64_t j = 0; j < dims[1]; ++j) {
      for (int64_t i = 0; i < dims[0]; ++i) {
        const int64_t offset = geometry_.offset(i, j, k);
        const float value = path_safety[offset];
        uint8_t c = 0;
        const bool outside_body = !voxel_kinds_.empty() && voxel_kinds_[size_t(offset)] == 0;
        if (std::isfinite(value)) {
          c = outside_body ? 0 : uint8_t(1 + int(classes.classify(value)));
        } else if (region_state && (*region_state)[offset] == planning::kRegionUnknown) {
          c = kUnknownClass;
        }
        if (c != 0 || (!voxel_kinds_.empty() && voxel_kinds_[size_t(offset)] != 0)) {
          const Eigen::Vector3i index(static_cast<int>(i), static_cast<int>(j), static_cast<int>(k));
          lo = lo.cwiseMin(index);
          hi = hi.cwiseMax(index);
        }
        voxel_classes_[size_t(offset)] = c;
      }
    }
  }
  Eigen::Vector3i lo = Eigen::Vector3i::Constant(std::numeric_limits<int>::max());
  Eigen::Vector3i hi = Eigen::Vector3i::Constant(-1);
  for (int64_t k = 0; k < dims[2]; ++k) {
    lo = lo.cwiseMin(slice_lo[size_t(k)]);
    hi = hi.cwiseMax(slice_hi[size_t(k)]);
  }
  // Voxel centres are at integer indices: voxel (i,j,k) covers [i-0.5, i+0.5] etc.
  box_lo_ = lo.cast<float>() - Eigen::Vector3f::Constant(0.5f);
  box_hi_ = hi.cast<float>() + Eigen::Vector3f::Constant(0.5f);
}

SafetyVolumeRendering::~SafetyVolumeRendering() = default;

void SafetyVolumeRendering::set_options(const VolumeRenderingOptions& options) {
  validate_options(options);
  options_ = options;
}

void SafetyVolumeRendering::set_pose(const Eigen::Isometry3d& T_cam_ct) {
  if (!T_cam_ct.matrix().allFinite()) throw Error("volume rendering: pose T_cam_ct is not finite");
  T_cam_ct_ = T_cam_ct;
}

double SafetyVolumeRendering::step() const {
  return options_.step_mm > 0 ? options_.step_mm : 0.5 * geometry_.spacing.minCoeff();
}

SafetyVolumeRendering::RaySetup SafetyVolumeRendering::ray_setup() const {
  // index = A (p_ct - origin), p_ct = T_ct_cam (t d): index = A R_ct_cam d t + A (t_ct_cam - origin).
  const Eigen::Matrix3d A = geometry_.index_to_physical_matrix().inverse();
  const Eigen::Isometry3d T_ct_cam = T_cam_ct_.inverse();
  RaySetup s;
  s.M = (A * T_ct_cam.linear()).cast<float>();
  s.m0 = (A * (T_ct_cam.translation() - geometry_.origin)).cast<float>();
  return s;
}

Eigen::Vector4d SafetyVolumeRendering::reference_pixel(const calibration::CameraModel& camera,
                                                       double u, double v, bool* ambiguous) const {
  const Eigen::Vector4d none(0, 0, 0, 0);
  if (ambiguous) *ambiguous = false;
  const Eigen::Vector3f df = pixel_ray(camera, u, v);
  if (df.squaredNorm() < 0.5f || box_lo_.x() > box_hi_.x()) return none;
  const RaySetup s = ray_setup();
  const Eigen::Vector3d d = df.cast<double>();
  const Eigen::Vector3d m0 = s.m0.cast<double>();
  const Eigen::Vector3d D = s.M.cast<double>() * d;
  double t_in = 0.0, t_out = 1e30;
  for (int a = 0; a < 3; ++a) {
    if (std::abs(D[a]) < 1e-12) {
      if (m0[a] < box_lo_[a] || m0[a] > box_hi_[a]) return none;
    } else {
      const double t1 = (box_lo_[a] - m0[a]) / D[a];
      const double t2 = (box_hi_[a] - m0[a]) / D[a];
      t_in = std::max(t_in, std::min(t1, t2));
      t_out = std::min(t_out, std::max(t1, t2));
    }
  }
  if (!(t_out > t_in)) return none;
  const auto looks = class_looks(options_);
  const auto alphas = surface_alphas(surfaces_, options_.hidden_surfaces);
  const float step_f = float(step());
  const double step_mm = step_f;
  const int n = std::min(int(std::ceil((t_out - t_in) / step_mm)), kMaxSteps);
  const auto& dims = geometry_.dims;
  Eigen::Vector3d C = Eigen::Vector3d::Zero();
  double alpha = 0;
  const auto kind_at = [&](int64_t i, int64_t j, int64_t k) -> uint8_t {
    if (voxel_kinds_.empty()) return 0;
    i = std::clamp<int64_t>(i, 0, dims[0] - 1);
    j = std::clamp<int64_t>(j, 0, dims[1] - 1);
    k = std::clamp<int64_t>(k, 0, dims[2] - 1);
    return voxel_kinds_[size_t(geometry_.offset(i, j, k))];
  };
  int kind = -1;  // the first sample's kind shows no surface
  for (int i = 0; i < n; ++i) {
    const double t0 = t_in + i * step_mm;
    const double dt = i < n - 1 ? step_mm : t_out - t0;
    const double t = t0 + 0.5 * dt;
    const Eigen::Vector3d x = m0 + t * D;
    int64_t index[3];
    for (int a = 0; a < 3; ++a) {
      index[a] = std::clamp<int64_t>(int64_t(std::floor(x[a] + 0.5)), 0, dims[size_t(a)] - 1);
    }
    const int c = voxel_classes_[size_t(geometry_.offset(index[0], index[1], index[2]))];
    const uint8_t s = kind_at(index[0], index[1], index[2]);
    if (kind < 0) kind = s;
    if (s != kind) {
      kind = s;
      if (alphas[s] > 0) {
        Eigen::Vector3d g;
        for (int a = 0; a < 3; ++a) {
          int64_t up[3] = {index[0], index[1], index[2]}, down[3] = {index[0], index[1], index[2]};
          ++up[a];
          --down[a];
          g[a] = double(kind_at(up[0], up[1], up[2]) == s) - double(kind_at(down[0], down[1], down[2]) == s);
        }
        const Eigen::Vector3d spacing = geometry_.spacing;
        const double len = g.cwiseQuotient(spacing).norm() * D.cwiseProduct(spacing).norm();
        const double cosine = len > 0 ? std::abs(g.dot(D)) / len : 1.0;
        const double shade = kSurfaceAmbient + (1.0 - kSurfaceAmbient) * cosine;
        const double a = float(alphas[s]);
        const auto& rgb = surfaces_[s].colour;
        C += (1.0 - alpha) * a * shade * Eigen::Vector3d(rgb[0], rgb[1], rgb[2]) / 255.0;
        alpha += (1.0 - alpha) * a;
        if (alpha >= kVolumeRenderingOpaque) break;
      }
    }
    if (ambiguous && !*ambiguous) {
      for (int a = 0; a < 3; ++a) {
        const double f = x[a] + 0.5 - std::floor(x[a] + 0.5);  // position within the voxel, 0..1
        const int64_t side = f < kVolumeRenderingAmbiguity         ? -1
                             : f > 1.0 - kVolumeRenderingAmbiguity ? 1
                                                                   : 0;
        int64_t neighbour[3] = {index[0], index[1], index[2]};
        neighbour[a] += side;
        if (side == 0 || neighbour[a] < 0 || neighbour[a] >= dims[size_t(a)]) continue;
        if (voxel_classes_[size_t(geometry_.offset(neighbour[0], neighbour[1], neighbour[2]))] != c)
          *ambiguous = true;
      }
    }
    if (c == 0) continue;
    const double k = float(looks[size_t(c)].opacity);
    if (!(k > 0)) continue;
    const double a = 1.0 - std::exp(-k * dt);
    const auto& rgb = looks[size_t(c)].colour;
    C += (1.0 - alpha) * a * Eigen::Vector3d(rgb[0], rgb[1], rgb[2]) / 255.0;
    alpha += (1.0 - alpha) * a;
    if (alpha >= kVolumeRenderingOpaque) break;
  }
  return {C.x(), C.y(), C.z(), alpha};
}

void SafetyVolumeRendering::release_gl() {
  if (!gl_) return;
  glDeleteProgram(gl_->march_program);
  glDeleteProgram(gl_->composite_program);
  glDeleteVertexArrays(1, &gl_->vao);
  const GLuint textures[3] = {gl_->class_texture, gl_->ray_texture, gl_->low_texture};
  glDeleteTextures(3, textures);
  glDeleteFramebuffers(1, &gl_->low_fbo);
  gl_.reset();
}

void SafetyVolumeRendering::draw(const DrawContext& context) {
  // The objects are lost with their context (e.g. a renderer made anew): make them again.
  if (gl_ && (!glIsProgram(gl_->march_program) || !glIsTexture(gl_->class_texture))) gl_.reset();
  if (!gl_) {
    gl_ = Gl::create(geometry_.dims);
  }
  // The leap distances follow the classes shown.
  unsigned shown = 0;
  const auto looks = class_looks(options_);
  for (int c = 1; c < kClassCount; ++c) shown |= looks[size_t(c)].opacity > 0 ? 1u << c : 0u;
  if (gl_->uploaded_shown != shown) {
    gl_->upload(geometry_.dims, voxel_classes_, voxel_kinds_, shown);
    throw_on_gl_error("while filling the class texture");
  }
  if (box_lo_.x() > box_hi_.x()) return;  // nothing classified: nothing to draw

  const int width = cast_size(context.width, options_.resolution_scale);
  const int height = cast_size(context.height, options_.resolution_scale);
  gl_->update_rays(context, width, height);
  GLint target_fbo = 0;
  GLint viewport[4] = {0, 0, 0, 0};
  glGetIntegerv(GL_DRAW_FRAMEBUFFER_BINDING, &target_fbo);
  glGetIntegerv(GL_VIEWPORT, viewport);
  const bool reduced = width != context.width || height != context.height;
  if (reduced) gl_->update_low_target(width, height, target_fbo);

  // Ray casting, premultiplied output (at reduced resolution: composited bilinearly).
  const float step_mm = float(step());
  float surfaces[4 * kMaxAnatomyKinds] = {};
  const auto alphas = surface_alphas(surfaces_, options_.hidden_surfaces);
  for (size_t k = 0; k < surfaces_.size(); ++k) {
    for (size_t ch = 0; ch < 3; ++ch) surfaces[4 * k + ch] = float(surfaces_[k].colour[ch] / 255.0);
    surfaces[4 * k + 3] = float(alphas[k]);
  }
  // The reduced cast fills its own target from its corner; the full one the viewport.
  const GLint cast_viewport[4] = {reduced ? 0 : viewport[0], reduced ? 0 : viewport[1], width,
                                  height};
  gl_->bind_march(ray_setup(), box_lo_, box_hi_, geometry_, class_uniforms(options_, step_mm),
                  surfaces, step_mm, height, cast_viewport);
  if (reduced) gl_->cast_reduced(width, height, target_fbo, viewport, context);
  glEnable(GL_BLEND);
  glBlendFunc(GL_ONE, GL_ONE_MINUS_SRC_ALPHA);
  glDrawArrays(GL_TRIANGLES, 0, 3);
  glBlendFunc(GL_SRC_ALPHA, GL_ONE_MINUS_SRC_ALPHA);
  glActiveTexture(GL_TEXTURE0);
  throw_on_gl_error("while drawing");
}

}  // namespace crepuscular::overlay
