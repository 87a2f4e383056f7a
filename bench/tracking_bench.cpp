// Tracking benchmark: detection + board poses per frame while tracking, beside libapriltag's own
// full-frame detection on the same frames, at 1280x720 and 1920x1080. Frames are rendered first
// (tracking/synthetic.hpp) and kept in memory; only detection and poses are timed. Prints one JSON
// line per resolution.
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <numeric>
#include <ctime>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>

#include "tracking/detector.hpp"
#include "tracking/synthetic.hpp"
#include "tracking/tracker.hpp"

using namespace crepuscular;
using namespace crepuscular::tracking;

namespace {

using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// CPU time of the whole process (all threads), ms: less sensitive than wall time to other work on
// a shared machine.
double cpu_ms() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// The patient board (6 tags of 40 mm) at about 50 cm, moving 60 mm and turning 12 degrees over the
// sequence (a radiologist's slow hand on the field), seen by a camera scaled to the resolution.
SyntheticScene bench_scene(int width, int height, int frames, bool with_needle) {
  SyntheticScene s;
  const double scale = width / 1280.0;
  s.camera.width = width;
  s.camera.height = height;
  s.camera.fx = s.camera.fy = 1000.0 * scale;
  s.camera.cx = 0.5 * (width - 1);
  s.camera.cy = 0.5 * (height - 1);
  s.camera.distortion = {-0.1, 0.03, 0.0, 0.0, 0.0};
  s.fps = 60;
  s.frame_count = frames;
  s.noise_sigma = 2.0;
  s.background = "noise";
  SceneBoard patient;
  patient.board = make_grid_board("patient", 2, 3, 40.0, 10.0, 0);
  const double T_end = double(frames - 1) / s.fps;
  auto pose = [](double x, double y, double z, double rx, double ry, double rz) {
    const double d = 3.14159265358979323846 / 180.0;
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = (Eigen::AngleAxisd(rz * d, Eigen::Vector3d::UnitZ()) *
                  Eigen::AngleAxisd(ry * d, Eigen::Vector3d::UnitY()) *
                  Eigen::AngleAxisd(rx * d, Eigen::Vector3d::UnitX()))
                     .toRotationMatrix();
    T.translation() = Eigen::Vector3d(x, y, z);
    return T;
  };
  patient.keyframes = {{0.0, pose(-40, 10, 500, 20, -10, 0)}, {T_end, pose(20, -20, 520, 15, 0, 12)}};
  s.boards.push_back(patient);
  if (with_needle) {
    SceneBoard needle;
    needle.board = make_grid_board("needle", 2, 2, 20.0, 6.0, 10);
    needle.keyframes = {{0.0, pose(120, 60, 450, -20, 15, 0)}, {T_end, pose(60, 30, 470, -10, 10, 20)}};
    s.boards.push_back(needle);
  }
  return s;
}

nlohmann::json run(int width, int height, int frames, int repeats, const DetectorOptions& det,
                   int full_every, bool with_needle) {
  const SyntheticScene scene = bench_scene(width, height, frames, with_needle);
  SyntheticRenderer renderer(scene);
  std::vector<Frame> seq;
  std::vector<cv::Mat> grey;
  const auto t_render = Clock::now();
  for (int i = 0; i < frames; ++i) {
    Frame f;
    f.index = i;
    f.timestamp_ns = renderer.timestamp_ns_of(i);
    f.image = renderer.render(i, &f.truth);
    cv::Mat g;
    cv::cvtColor(f.image, g, cv::COLOR_BGR2GRAY);
    grey.push_back(g);
    seq.push_back(std::move(f));
  }
  spdlog::info("{}x{}: rendered {} frames in {:.1f} s", width, height, frames,
               ms_since(t_render) / 1e3);
  std::vector<Board> boards;
  for (const SceneBoard& b : scene.boards) boards.push_back(b.board);

  // libapriltag alone, whole frame, on the grey image (no colour conversion counted), and its
  // corners against the projection of the true corners.
  TagDetector detector(det);
  std::vector<double> full_ms, full_cpu, corner_px;
  std::vector<size_t> full_count(frames);
  for (int r = 0; r < repeats; ++r) {
    const auto t0 = Clock::now();
    const double c0 = cpu_ms();
    for (int i = 0; i < frames; ++i) full_count[i] = detector.detect(grey[i]).size();
    full_ms.push_back(ms_since(t0) / frames);
    full_cpu.push_back((cpu_ms() - c0) / frames);
  }
  for (int i = 0; i < frames; ++i) {
    for (const Detection& d : detector.detect(grey[i])) {
      for (size_t b = 0; b < boards.size(); ++b) {
        const BoardTag* tag = boards[b].find(d.id);
        if (!tag) continue;
        for (int k = 0; k < 4; ++k) {
          const Eigen::Vector2d truth =
              scene.camera.project(seq[size_t(i)].truth[b].T_cam_board * tag->corners[size_t(k)]);
          corner_px.push_back((d.corners[size_t(k)] - truth).norm());
        }
      }
    }
  }

  // Tracking (colour frames in: conversion, detection, poses, filter), and full-frame tracking.
  auto track = [&](int interval, std::vector<size_t>* counts, double* err_mm, int64_t* fulls,
                   std::vector<double>* region_ms, std::vector<double>* frame_ms,
                   double* cpu_per_frame) {
    std::vector<double> per, cpu;
    for (int r = 0; r < repeats; ++r) {
      TrackerOptions o;
      o.detector = det;
      o.full_search_interval = interval;
      Tracker tracker(scene.camera, boards, o);
      std::vector<double> errs;
      const auto t0 = Clock::now();
      const double c0 = cpu_ms();
      for (int i = 0; i < frames; ++i) {
        const auto tf = Clock::now();
        const TrackResult res = tracker.process(seq[i]);
        const double ms = ms_since(tf);
        frame_ms->push_back(ms);
        if (!res.full_search) region_ms->push_back(ms);
        if (r == 0) {
          (*counts)[i] = res.detections.size();
          for (size_t b = 0; b < res.boards.size(); ++b) {
            if (!res.boards[b].tracked) {
              errs.push_back(1e9);
              continue;
            }
            errs.push_back((res.boards[b].T_cam_board.translation() -
                            seq[i].truth[b].T_cam_board.translation())
                               .norm());
          }
        }
      }
      per.push_back(ms_since(t0) / frames);
      cpu.push_back((cpu_ms() - c0) / frames);
      if (r == 0) {
        *err_mm = median(errs);
        *fulls = tracker.full_searches();
      }
    }
    *cpu_per_frame = median(cpu);
    return median(per);
  };
  std::vector<size_t> roi_count(frames), fullt_count(frames);
  double roi_err = 0, fullt_err = 0;
  int64_t roi_fulls = 0, fullt_fulls = 0;
  std::vector<double> region_ms, roi_frame_ms, unused1, unused2;
  double roi_cpu = 0, fullt_cpu = 0;
  const double roi_ms =
      track(full_every, &roi_count, &roi_err, &roi_fulls, &region_ms, &roi_frame_ms, &roi_cpu);
  const double fullt_ms =
      track(0, &fullt_count, &fullt_err, &fullt_fulls, &unused1, &unused2, &fullt_cpu);

  int64_t fewer = 0, det_full = 0, det_roi = 0;
  for (int i = 0; i < frames; ++i) {
    det_full += int64_t(full_count[i]);
    det_roi += int64_t(roi_count[i]);
    if (roi_count[i] < full_count[i]) ++fewer;
  }
  const double full_med = median(full_ms);
  nlohmann::json j;
  j["resolution"] = std::to_string(width) + "x" + std::to_string(height);
  j["frames"] = frames;
  j["tags_per_frame"] = with_needle ? 10 : 6;
  j["threads"] = det.threads;
  j["decimate"] = det.decimate;
  j["libapriltag_full_frame_ms"] = full_med;
  j["libapriltag_full_frame_fps"] = 1e3 / full_med;
  j["tracking_ms"] = roi_ms;
  j["tracking_fps"] = 1e3 / roi_ms;
  j["tracking_full_searches"] = roi_fulls;
  j["tracking_region_frame_median_ms"] = region_ms.empty() ? 0.0 : median(region_ms);
  j["tracking_slowest_frame_ms"] = *std::max_element(roi_frame_ms.begin(), roi_frame_ms.end());
  j["full_frame_tracking_ms"] = fullt_ms;
  j["speedup_vs_libapriltag_full_frame"] = full_med / roi_ms;
  j["libapriltag_full_frame_cpu_ms"] = median(full_cpu);
  j["tracking_cpu_ms"] = roi_cpu;
  j["full_frame_tracking_cpu_ms"] = fullt_cpu;
  j["detections_full_frame"] = det_full;
  j["detections_tracking"] = det_roi;
  j["frames_with_fewer_detections_than_full_frame"] = fewer;
  j["median_translation_error_mm"] = roi_err;
  j["refine_edges"] = det.refine_edges;
  j["corner_error_mean_px"] = corner_px.empty() ? 0.0 : std::accumulate(corner_px.begin(), corner_px.end(), 0.0) / double(corner_px.size());
  j["corner_error_max_px"] = corner_px.empty() ? 0.0 : *std::max_element(corner_px.begin(), corner_px.end());
  return j;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Tracking benchmark: detection + board poses per frame vs libapriltag full frame"};
  int frames = 60, repeats = 3, threads = 2, full_every = 15;
  DetectorOptions det;
  bool needle = false;
  std::vector<std::string> sizes = {"1280x720", "1920x1080"};
  app.add_option("--frames", frames, "Frames per resolution")->capture_default_str();
  app.add_option("--repeats", repeats, "Timed passes (median reported)")->capture_default_str();
  app.add_option("--threads", threads, "libapriltag threads")->capture_default_str();
  app.add_option("--decimate", det.decimate, "libapriltag quad decimation")->capture_default_str();
  app.add_option("--refine-edges", det.refine_edges, "libapriltag edge refinement (0 or 1)")
      ->capture_default_str();
  app.add_option("--blur", det.blur_sigma, "libapriltag quad_sigma")->capture_default_str();
  app.add_option("--full-search-every", full_every, "Tracker's full-frame search interval")
      ->capture_default_str();
  app.add_option("--sizes", sizes, "Resolutions WxH")->capture_default_str();
  app.add_flag("--needle", needle, "Add the needle board (4 more tags)");
  CLI11_PARSE(app, argc, argv);
  det.threads = threads;
  for (const std::string& s : sizes) {
    int w = 0, h = 0;
    if (std::sscanf(s.c_str(), "%dx%d", &w, &h) != 2 || w <= 0 || h <= 0) {
      std::fprintf(stderr, "error: --sizes: '%s' is not WxH\n", s.c_str());
      return 1;
    }
    std::printf("%s\n", run(w, h, frames, repeats, det, full_every, needle).dump().c_str());
    std::fflush(stdout);
  }
  return 0;
}
