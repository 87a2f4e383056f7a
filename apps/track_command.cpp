// `crepuscular track`: marker-board poses for every frame of a camera, recording or synthetic
// scene, written as a poses CSV.
#include "apps/commands.hpp"
#include "pipelines/track.hpp"

namespace crepuscular::apps {

void add_track_command(CLI::App& app) {
  auto a = std::make_shared<pipelines::TrackRequest>();
  CLI::App* cmd = app.add_subcommand(
      "track",
      "Find the marker boards in every frame and write their poses (T_cam_board, mm) as CSV:\n"
      "frame,timestamp_ns,board,state,tx,ty,tz,qw,qx,qy,qz,rms_px, state tracked or lost.\n"
      "A board not seen for longer than --max-age-ms is reported lost, never held longer.\n"
      "Each board is searched in its own tag family (boards.json \"family\"); why a board is\n"
      "not found is logged, and with --details written per frame.");
  cmd->add_option("--source", a->source,
                  "Frames: recording:DIR, synthetic:SCENE.json, synthetic:builtin, "
                  "plus:FILE.igs.mha (a PLUS sequence file's image frames) or "
                  "v4l2:/dev/video0?width=1280&height=720&fps=60")
      ->required();
  cmd->add_option("--boards", a->boards,
                  "Marker boards (boards.json, or Kalibr's aprilgrid target yaml); default: "
                  "the recording's boards.json");
  cmd->add_option("--camera", a->camera,
                  "Camera model (OpenCV YAML); default: the source's own (a recording's "
                  "camera.yaml, a synthetic scene's camera)");
  cmd->add_option("--out", a->out, "Poses CSV to write (complete or not at all)")
      ->capture_default_str();
  cmd->add_option("--max-age-ms", a->max_age_ms,
                  "Longest time a board's last pose is still reported while the board is not "
                  "seen; older poses are reported lost")
      ->capture_default_str()
      ->check(in_range(1, 10000));
  cmd->add_option("--full-search-every", a->full_search_interval,
                  "Search the whole frame at least every this many frames while all boards are "
                  "tracked (in between only where their poses predict the tags); 0 = every frame")
      ->capture_default_str()
      ->check(in_range(0, 1e9, true));
  cmd->add_option("--details", a->details,
                  "Also write what the detector found, per frame and board: the tags seen (family, "
                  "id, corners in pixels), the pose's reprojection RMS, and why a board was not "
                  "measured (no tag of its family, tags not on the board, a layout that does not "
                  "fit, an unreadable image). CSV; open it in a spreadsheet");
  add_detector_options(cmd, a->detector);
  cmd->add_flag("!--no-smoothing", a->smoothing,
                "Report each frame's measured pose without the temporal filter");
  cmd->callback([a] {
    claim_run_paths({"track",
                     {{"--source", source_path(a->source)},
                      {"--boards", a->boards},
                      {"--camera", a->camera}},
                     {{"--out", a->out}, {"--details", a->details}}});
    pipelines::run_track(*a);
  });
}

}  // namespace crepuscular::apps
