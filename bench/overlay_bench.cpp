// Overlay renderer frame time with the content of a live guidance frame: 300 safe-ray polylines of
// 20 points (opacity 0.6), 20 entry-area contours of 100 points, the needle line and a status text
// image, all re-added every frame from a moving camera pose (as the live view does).
//
// Two measurements per image size:
// - "frame": set_frame + re-adding all layers + render() (draw and readback of the BGR image), what
//   the headless output (video file, PNG snapshots) pays;
// - "draw": set_frame + re-adding all layers + draw() + glFinish, what the live window pays before
//   present() (no readback).
// Prints the OpenGL implementation, median and p95 per phase, and one JSON line per size.
#include <GL/gl.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <random>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <spdlog/spdlog.h>

#include "foundation/error.hpp"
#include "overlay/renderer.hpp"

namespace {

using crepuscular::overlay::OverlayRenderer;
using crepuscular::overlay::Polyline;
using crepuscular::overlay::RendererBackend;
using crepuscular::overlay::RendererOptions;
using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

struct Stats {
  double median = 0, p95 = 0;
};

Stats stats(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  Stats s;
  if (v.empty()) return s;
  s.median = v[v.size() / 2];
  s.p95 = v[std::min(v.size() - 1, static_cast<size_t>(std::ceil(0.95 * v.size())) - 1)];
  return s;
}

crepuscular::calibration::CameraModel camera(int width, int height) {
  crepuscular::calibration::CameraModel cam;
  cam.width = width;
  cam.height = height;
  cam.fx = cam.fy = 0.9 * width;
  cam.cx = width / 2.0;
  cam.cy = height / 2.0;
  cam.distortion = {-0.12, 0.05, 0.0005, -0.0004, 0.0};
  return cam;
}

// The scene in the patient (model) frame, mm; the tumor at the origin, the skin at z = -60.
struct Scene {
  std::vector<Polyline> rays, contours;
  Polyline needle;
};

Scene make_scene() {
  Scene scene;
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int i = 0; i < 300; ++i) {
    Eigen::Vector3d dir(0.6 * u(rng), 0.6 * u(rng), -1);
    dir.normalize();
    Polyline ray;
    for (int k = 0; k < 20; ++k) ray.points_cam.push_back(dir * (5.0 + 60.0 * k / 19.0));
    ray.colour = i % 3 ? cv::Scalar(80, 200, 60) : cv::Scalar(0, 200, 255);  // safe / medium
    ray.width_px = 2;
    ray.opacity = 0.6;
    scene.rays.push_back(ray);
  }
  for (int i = 0; i < 20; ++i) {
    Polyline contour;
    const Eigen::Vector3d centre(30 * u(rng), 30 * u(rng), -60);
    const double radius = 4 + 6 * (u(rng) + 1);
    for (int k = 0; k < 100; ++k) {
      const double a = 2 * M_PI * k / 100;
      contour.points_cam.push_back(centre + Eigen::Vector3d(radius * std::cos(a),
                                                            radius * std::sin(a),
                                                            1.5 * std::sin(3 * a)));
    }
    contour.closed = true;
    contour.width_px = 2 + i % 5;
    contour.colour = cv::Scalar(255, 160, 0);
    scene.contours.push_back(contour);
  }
  scene.needle.points_cam = {{25, 10, -120}, {0, 0, 0}};
  scene.needle.width_px = 3;
  scene.needle.colour = cv::Scalar(0, 0, 255);
  return scene;
}

Polyline moved(const Polyline& p, const Eigen::Isometry3d& T_cam_model) {
  Polyline out = p;
  for (auto& q : out.points_cam) q = T_cam_model * q;
  return out;
}

// Camera pose of frame i: the tumor 300 mm in front of the camera, the skin between them,
// swaying a little from frame to frame.
Eigen::Isometry3d pose(int i) {
  const double a = 0.02 * std::sin(0.1 * i), b = 0.02 * std::cos(0.13 * i);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = (Eigen::AngleAxisd(a, Eigen::Vector3d::UnitX()) *
                Eigen::AngleAxisd(b, Eigen::Vector3d::UnitY()))
                   .toRotationMatrix();
  T.translation() = Eigen::Vector3d(2 * a, 2 * b, 300);
  return T;
}

// Re-adds every layer for frame i; returns the milliseconds spent.
double add_layers(OverlayRenderer& r, const Scene& scene, int i, cv::Mat& text) {
  const auto t0 = Clock::now();
  const Eigen::Isometry3d T = pose(i);
  for (const char* layer : {"rays", "entry areas", "needle", "status"}) r.clear_layer(layer);
  for (const auto& p : scene.rays) r.add_polyline("rays", moved(p, T));
  for (const auto& p : scene.contours) r.add_polyline("entry areas", moved(p, T));
  r.add_polyline("needle", moved(scene.needle, T));
  text.setTo(cv::Scalar(0, 0, 0, 0));
  char line[128];
  std::snprintf(line, sizeof(line), "tracking OK  frame %d  latency %.1f ms", i, 10 + 0.1 * (i % 7));
  cv::putText(text, line, cv::Point(20, 40), cv::FONT_HERSHEY_SIMPLEX, 1.0,
              cv::Scalar(255, 255, 255, 255), 2, cv::LINE_AA);
  cv::putText(text, "needle: safe  tip-target 23.4 mm  angle 2.1 deg", cv::Point(20, 80),
              cv::FONT_HERSHEY_SIMPLEX, 0.8, cv::Scalar(80, 255, 80, 255), 2, cv::LINE_AA);
  r.set_layer_image("status", text);
  return ms_since(t0);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Overlay renderer frame time at 1280x720 and 1920x1080 with live-guidance content"};
  int frames = 200;
  std::string backend = "auto";
  std::vector<std::string> sizes = {"1280x720", "1920x1080"};
  app.add_option("--frames", frames, "Timed frames per size and measurement (after 10 warm-up frames)")
      ->default_val(200)
      ->check(CLI::PositiveNumber);
  app.add_option("--backend", backend,
                 "OpenGL context: auto (EGL, else a hidden GLFW window), egl (no display needed), "
                 "glfw (hidden GLFW window; needs an X display)")
      ->default_val("auto")
      ->check(CLI::IsMember({"auto", "egl", "glfw"}));
  app.add_option("--size", sizes, "Image sizes WIDTHxHEIGHT")->default_val(sizes);
  CLI11_PARSE(app, argc, argv);

  RendererOptions options;
  options.backend = backend == "egl"    ? RendererBackend::kEgl
                    : backend == "glfw" ? RendererBackend::kGlfw
                                        : RendererBackend::kAuto;
  const Scene scene = make_scene();
  try {
    for (const auto& size : sizes) {
      int width = 0, height = 0;
      if (std::sscanf(size.c_str(), "%dx%d", &width, &height) != 2 || width < 16 || height < 16) {
        throw crepuscular::Error("--size: expected WIDTHxHEIGHT such as 1920x1080, got '" + size +
                                 "'");
      }
      OverlayRenderer renderer(camera(width, height), options);
      cv::Mat frame(height, width, CV_8UC3);
      cv::randu(frame, cv::Scalar::all(0), cv::Scalar::all(256));
      cv::Mat text(height, width, CV_8UC4);
      std::vector<double> upload, layers, render, frame_total, draw, draw_total;
      // The two measurements alternate frame by frame so that both see the same machine load.
      for (int i = 0; i < 2 * (frames + 10); ++i) {
        const bool timed = i >= 20;
        const auto t0 = Clock::now();
        renderer.set_frame(frame);
        const double t_upload = ms_since(t0);
        const double t_layers = add_layers(renderer, scene, i / 2, text);
        const auto t1 = Clock::now();
        if (i % 2 == 0) {
          const cv::Mat image = renderer.render();
          const double t_render = ms_since(t1);
          if (image.cols != width) throw crepuscular::Error("render() returned a wrong size");
          if (timed) {
            upload.push_back(t_upload);
            layers.push_back(t_layers);
            render.push_back(t_render);
            frame_total.push_back(ms_since(t0));
          }
        } else {
          renderer.draw();
          glFinish();  // the renderer's context is current after draw()
          if (timed) {
            draw.push_back(ms_since(t1));
            draw_total.push_back(ms_since(t0));
          }
        }
      }
      const std::string gl = renderer.gl_description();
      const auto line = [](const char* what, const Stats& s) {
        std::printf("  %-44s median %7.2f ms   p95 %7.2f ms\n", what, s.median, s.p95);
      };
      std::printf("%dx%d on %s, %d frames\n", width, height, gl.c_str(), frames);
      line("set_frame (upload)", stats(upload));
      line("re-add layers (projection, text image)", stats(layers));
      line("render() (draw + readback)", stats(render));
      line("frame: set_frame + layers + render()", stats(frame_total));
      line("draw() + glFinish", stats(draw));
      line("live: set_frame + layers + draw() + glFinish", stats(draw_total));
      nlohmann::json j = {{"bench", "overlay"},
                          {"width", width},
                          {"height", height},
                          {"gl", gl},
                          {"frames", frames},
                          {"upload_ms", stats(upload).median},
                          {"layers_ms", stats(layers).median},
                          {"render_ms", stats(render).median},
                          {"frame_ms", stats(frame_total).median},
                          {"frame_p95_ms", stats(frame_total).p95},
                          {"draw_finish_ms", stats(draw).median},
                          {"draw_finish_p95_ms", stats(draw).p95},
                          {"live_ms", stats(draw_total).median},
                          {"live_p95_ms", stats(draw_total).p95}};
      std::cout << j.dump() << std::endl;
    }
  } catch (const crepuscular::Error& e) {
    spdlog::error("{}", e.what());
    return 1;
  }
  return 0;
}
