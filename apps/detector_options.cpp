// The tag detector's settings as command-line options, shared by every command that finds marker
// boards in images.
#include "apps/commands.hpp"

namespace crepuscular::apps {

void add_detector_options(CLI::App* cmd, tracking::DetectorOptions& o) {
  const char* group = "Tag detection";
  cmd->add_option("--decimate", o.decimate,
                  "Find tag outlines on the image shrunk by this factor. 1 finds every tag of "
                  "apriltag's test photos (47 of 47, corners within 0.02 px of the reference); 2 "
                  "is about 3x faster but misses tags under about 25 px (34 of 47)")
      ->capture_default_str()
      ->check(in_range(1.0, 8.0))
      ->group(group);
  cmd->add_flag("--refine-edges,!--no-refine-edges", o.refine_edges,
                "Snap tag edges to the strongest nearby gradient. Worth it with --decimate 2 or "
                "more; at full resolution it moves the corners of very oblique tags by up to 2 px")
      ->capture_default_str()
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
