// The tag detector's settings as command-line options, shared by every command that finds marker
// boards in images.
#include "apps/commands.hpp"

namespace crepuscular::apps {

void add_detector_options(CLI::App* cmd, tracking::DetectorOptions& o) {
  const char* group = "Tag detection";
  cmd->add_option(
         "--decimate", o.decimate,
         "Find tag outlines on the image shrunk by this factor. 1 finds small and oblique "
         "tags (46 of the 47 tags of apriltag's test photos, 34 at 2); 2 is 3.6 times faster "
         "per 720p frame (bench/RESULTS.md) and suits tags of 25 px or more")
      ->capture_default_str()
      ->check(in_range(1.0, 8.0))
      ->group(group);
  cmd->add_flag("--refine-edges,!--no-refine-edges", o.refine_edges,
                "Snap tag edges to the strongest nearby gradient (on by default): corners nearer "
                "the truth at every decimation (rendered tags: 0.07-0.17 px on average against "
                "0.14-0.24 px). --no-refine-edges with --decimate 1 are apriltag's reference "
                "settings (all 47 test-photo tags, 0.004 px from its reference corners)")
      ->group(group);
  cmd->add_option("--sharpening", o.sharpening,
                  "Sharpening of the tag image before its bits are read (0 = none); helps "
                  "small, soft tags decode")
      ->capture_default_str()
      ->check(in_range(0.0, 2.0))
      ->group(group);
  cmd->add_option("--blur", o.blur_sigma,
                  "Gaussian blur (sigma, px) before tag outlines are found: for noisy images; "
                  "negative values sharpen. 0 = none")
      ->capture_default_str()
      ->check(in_range(-5.0, 5.0))
      ->group(group);
  cmd->add_option("--max-hamming", o.max_hamming,
                  "Bit errors corrected per tag (0 to 2): fewer give fewer false tags and miss "
                  "more damaged ones")
      ->capture_default_str()
      ->check(in_range(0, 2, true))
      ->group(group);
  cmd->add_option("--detector-threads", o.threads, "Worker threads of the tag detector")
      ->capture_default_str()
      ->check(in_range(1, 64, true))
      ->group(group);
}

}  // namespace crepuscular::apps
