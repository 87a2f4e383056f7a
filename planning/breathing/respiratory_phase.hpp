// The breathing phase during guidance (docs/ARCHITECTURE.md §10): the patient board lies on the
// skin, so its motion is the respiratory signal. A breathing plan's phases tell how far the skin
// under the board lies from its end-exhale place in each phase; a board displacement is matched
// against those, and the direction of its motion tells inhale from exhale.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <deque>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// The skin's motion at the board over a breathing cycle.
struct SkinMotion {
  Eigen::Vector3d direction = Eigen::Vector3d::UnitY();  // CT, unit: outward from the body
  // Per phase (cycle order), how far the skin lies along `direction` from where it lies in phase
  // 0 (mm); phase 0 is end-exhale, so these are >= 0 up to the end-inhale phase and back.
  std::vector<double> displacement_mm;
  int inhale_phase = 0;  // the phase of the largest displacement
  double amplitude_mm() const;
};

// From the phases' label maps (cycle order, phase 0 end-exhale): where the body (label > 0) ends
// along lines in `outward` (unit, CT) within 60 mm of the board (the 0.5 crossing of the
// trilinearly interpolated body indicator), against phase 0, averaged over the lines through a
// disc of 30 mm radius around `board_ct`. Throws Error naming the phase when its skin does not
// cross the board's own line.
SkinMotion skin_motion(const std::vector<const Volume<int32_t>*>& phase_labels,
                       const Eigen::Vector3d& board_ct, const Eigen::Vector3d& outward,
                       const std::vector<std::string>& phase_names);

struct PhaseEstimate {
  bool known = false;      // false until a breath has been seen (reason says why)
  int phase = -1;          // the plan's phase (cycle order)
  double displacement_mm = 0;  // the board's, from the end-exhale level of the last breaths
  int motion = 0;          // +1 inhaling, -1 exhaling, 0 at rest
  std::string reason;
};

// Per tracked frame: the board's position along the skin's motion direction (mm, larger = more
// outward; any origin). The end-exhale level is the lowest position of the last `window_s`
// seconds; the phase is known once that window has held a breath (half the skin's amplitude seen
// over at least 3 s). Inhaling: phases 0 .. end-inhale; exhaling: end-inhale .. the last; at
// rest: the phase of the nearest displacement. A board that moves more than 1.5 times the skin's
// amplitude plus 2 mm (the patient or the camera moved) gives no phase until it has breathed again.
class RespiratoryPhaseEstimator {
 public:
  explicit RespiratoryPhaseEstimator(SkinMotion motion, double window_s = 12.0);
  PhaseEstimate update(int64_t timestamp_ns, double position_mm);
  // A gap in tracking (board lost): the history restarts.
  void reset() { history_.clear(); }
  const SkinMotion& motion() const { return motion_; }

 private:
  SkinMotion motion_;
  double window_s_;
  struct Sample {
    double t = 0, s = 0;
  };
  std::deque<Sample> history_;
};

// Cyclic distance between two phases of n.
int phase_distance(int a, int b, int n);

}  // namespace crepuscular::planning
