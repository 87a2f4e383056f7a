// Recording a frame source, and rendering a synthetic scene, into a recording folder.
#include "pipelines/record.hpp"

#include <vector>

#include <algorithm>
#include <cmath>

#include <fmt/format.h>

#include "calibration/camera_model.hpp"
#include "foundation/output_files.hpp"
#include "foundation/log.hpp"
#include "tracking/board.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::pipelines {

tracking::RecordSummary run_record(const RecordRequest& r) {
  tracking::RecordOptions options;
  options.max_frames = r.frames;
  options.max_seconds = r.seconds;
  options.image_format = r.format;
  options.jpeg_quality = r.quality;
  options.plan = r.plan;
  options.stop = r.stop;
  if (!r.boards.empty()) {
    // Checked and normalised: grids expanded, as tracking reads them.
    options.boards_json = tracking::boards_json_text(tracking::read_boards(r.boards));
  }
  if (!r.camera.empty()) options.camera = calibration::CameraModel::read_yaml(r.camera);
  auto source = tracking::open_frame_source(r.source);
  if (r.frames < 0 && r.seconds < 0 && r.source.rfind("v4l2:", 0) == 0) {
    spdlog::info("record: no frame or time limit: recording until Ctrl-C");
  }
  if (r.format == "plus") {
    const tracking::RecordSummary s = tracking::record_to_plus_sequence(*source, r.out, options);
    spdlog::info("record: wrote {} frames to the sequence file {} in {:.1f} s ({} with a problem)",
                 s.frames, s.path, s.seconds, s.problems);
    return s;
  }
  const tracking::RecordSummary s = tracking::record_to_folder(*source, r.out, options);
  spdlog::info(
      "record: wrote {} frames to {} in {:.1f} s ({} without image data skipped, {} "
      "with a problem{})",
      s.frames, s.path, s.seconds, s.skipped, s.problems,
      s.truth_rows > 0 ? ", " + std::to_string(s.truth_rows) + " ground-truth rows" : "");
  return s;
}

tracking::RecordSummary run_synth(const SynthRequest& r) {
  tracking::SyntheticScene scene =
      r.scene.empty() ? tracking::builtin_scene() : tracking::read_scene(r.scene);
  if (r.breaths_per_minute > 0) {
    tracking::add_breathing(scene, r.breathing_board, r.breaths_per_minute, r.rise_mm);
  }
  const std::string description = r.scene.empty() ? "synthetic:builtin" : "synthetic:" + r.scene;
  std::vector<tracking::Board> boards;
  for (const tracking::SceneBoard& b : scene.boards) boards.push_back(b.board);
  spdlog::info("synth: {} frames of {}x{} at {} fps, {} boards, from {}", scene.frame_count,
               scene.camera.width, scene.camera.height, scene.fps, boards.size(), description);
  auto source = tracking::make_synthetic_source(scene, description);
  tracking::RecordOptions options;
  options.image_format = r.format;
  options.jpeg_quality = r.quality;
  options.max_frames = r.frames;
  options.boards_json = tracking::boards_json_text(boards);
  const tracking::RecordSummary s = tracking::record_to_folder(*source, r.out, options);
  if (r.breaths_per_minute > 0) {
    // The breathing's truth per frame: the breath's fraction (0 end-exhale, 0.5 end-inhale) and
    // the board's rise off the skin's end-exhale place.
    PendingTextFile truth(s.path + "/breathing.csv", "breathing ground truth",
                          "frame,timestamp_ns,cycle_fraction,rise_mm");
    const int64_t frames = r.frames > 0 ? std::min(r.frames, scene.frame_count) : scene.frame_count;
    for (int64_t f = 0; f < frames; ++f) {
      const double t = double(f) / scene.fps;
      truth.write(fmt::format("{},{},{:.4f},{:.3f}\n", f, int64_t(std::llround(t * 1e9)),
                              tracking::breathing_cycle_fraction(t, r.breaths_per_minute),
                              tracking::breathing_rise_mm(t, r.breaths_per_minute, r.rise_mm)));
    }
    truth.commit();
  }
  spdlog::info("synth: wrote {} frames and {} ground-truth rows to {} in {:.1f} s{}", s.frames,
               s.truth_rows, s.path, s.seconds,
               s.problems > 0 ? " (" + std::to_string(s.problems) + " corrupt on purpose)" : "");
  return s;
}

}  // namespace crepuscular::pipelines
