#include "planning/breathing/respiratory_phase.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>

#include <fmt/format.h>

#include "foundation/error.hpp"
#include "planning/imaging/sampling.hpp"

namespace crepuscular::planning {

double SkinMotion::amplitude_mm() const {
  double a = 0;
  for (double d : displacement_mm) a = std::max(a, d);
  return a;
}

SkinMotion skin_motion(const std::vector<const Volume<int32_t>*>& phase_labels,
                       const Eigen::Vector3d& board_ct, const Eigen::Vector3d& outward,
                       const std::vector<std::string>& phase_names) {
  if (phase_labels.empty() || !(outward.norm() > 0)) {
    throw Error("breathing: no phases, or no direction, to measure the skin's motion with");
  }
  SkinMotion m;
  m.direction = outward.normalized();
  const Eigen::Vector3d across1 = m.direction.unitOrthogonal(), across2 = m.direction.cross(across1);
  const double reach = 60.0, step = 0.1;
  // Where the body ends along one line, NaN where it does not cross the line.
  const auto surface_on = [&](const Volume<int32_t>& labels, const Eigen::Vector3d& through) {
    const auto body = [&](double s) {
      const Eigen::Vector3d q = labels.geometry().physical_to_index(through + s * m.direction);
      return trilinear(labels, q, [](int32_t v) { return v > 0 ? 1.0 : 0.0; });
    };
    // The outermost crossing of 0.5 going outward: inside before it, outside after it.
    double found = std::numeric_limits<double>::quiet_NaN();
    double previous = body(-reach);
    for (double s = -reach + step; s <= reach + 1e-9; s += step) {
      const double b = body(s);
      // Only where the scan goes on beyond: its edge is no skin.
      const Eigen::Vector3d beyond =
          labels.geometry().physical_to_index(through + (s + 2.0) * m.direction);
      const bool scanned = labels.geometry().contains(std::lround(beyond.x()), std::lround(beyond.y()),
                                                      std::lround(beyond.z()));
      if (previous >= 0.5 && b < 0.5 && scanned) {
        found = s - step + step * (previous - 0.5) / (previous - b);
      }
      previous = b;
    }
    return found;
  };
  // The skin's displacement is the mean over parallel lines through a disc of 30 mm radius around
  // the board (every 10 mm): a surface voxelised at a few millimetres moves in steps of a voxel
  // along each line, at other moments on each.
  std::vector<Eigen::Vector3d> lines;
  for (int a = -3; a <= 3; ++a)
    for (int b = -3; b <= 3; ++b)
      if (a * a + b * b <= 9) lines.push_back(board_ct + 10.0 * (a * across1 + b * across2));
  std::vector<std::vector<double>> surface(phase_labels.size());
  for (size_t k = 0; k < phase_labels.size(); ++k) {
    for (const Eigen::Vector3d& through : lines) surface[k].push_back(surface_on(*phase_labels[k], through));
    if (!std::isfinite(surface[k][lines.size() / 2])) {  // the board's own line
      const std::string name = k < phase_names.size() ? phase_names[k] : fmt::format("{}", k);
      throw Error(fmt::format("breathing: phase {}: no skin within {:.0f} mm of the patient board "
                              "along its normal ({:.1f}, {:.1f}, {:.1f} mm, LPS): the board is not "
                              "on the scanned skin",
                              name, reach, board_ct.x(), board_ct.y(), board_ct.z()));
    }
  }
  for (size_t k = 0; k < phase_labels.size(); ++k) {
    double sum = 0;
    int count = 0;
    for (size_t l = 0; l < lines.size(); ++l) {
      const double d = surface[k][l] - surface[0][l];
      if (std::isfinite(d)) sum += d, ++count;
    }
    m.displacement_mm.push_back(sum / count);
  }
  m.inhale_phase = int(std::max_element(m.displacement_mm.begin(), m.displacement_mm.end()) -
                       m.displacement_mm.begin());
  return m;
}

RespiratoryPhaseEstimator::RespiratoryPhaseEstimator(SkinMotion motion, double window_s)
    : motion_(std::move(motion)), window_s_(window_s) {}

PhaseEstimate RespiratoryPhaseEstimator::update(int64_t timestamp_ns, double position_mm) {
  const double t = double(timestamp_ns) * 1e-9;
  if (!history_.empty() && (t - history_.back().t > 1.0 || t < history_.back().t)) reset();
  history_.push_back({t, position_mm});
  while (history_.size() > 2 && t - history_.front().t > window_s_) history_.pop_front();

  PhaseEstimate e;
  const double amplitude = motion_.amplitude_mm();
  const int n = int(motion_.displacement_mm.size());
  if (n < 2 || amplitude < 0.5) {
    e.reason = fmt::format("the skin under the patient board moves {:.1f} mm over the phases: too "
                           "little to tell the phase",
                           amplitude);
    return e;
  }
  // The position now (mean of the last 0.15 s), the level of each moment alike, and the speed
  // (least squares over the last 0.4 s).
  const auto mean_before = [&](size_t end, double span) {
    double sum = 0;
    int count = 0;
    for (size_t i = end + 1; i-- > 0;) {
      if (history_[end].t - history_[i].t > span) break;
      sum += history_[i].s;
      ++count;
    }
    return sum / count;
  };
  double low = std::numeric_limits<double>::infinity(), high = -low;
  for (size_t i = 0; i < history_.size(); ++i) {
    const double level = mean_before(i, 0.15);
    low = std::min(low, level);
    high = std::max(high, level);
  }
  const double now = mean_before(history_.size() - 1, 0.15);
  double st = 0, ss = 0, stt = 0, sts = 0;
  int count = 0;
  for (size_t i = history_.size(); i-- > 0;) {
    if (t - history_[i].t > 0.4) break;
    const double dt = history_[i].t - t;
    st += dt, ss += history_[i].s, stt += dt * dt, sts += dt * history_[i].s;
    ++count;
  }
  const double denominator = count * stt - st * st;
  const double speed = count >= 3 && denominator > 0 ? (count * sts - st * ss) / denominator : 0.0;
  const double span_s = t - history_.front().t;
  e.displacement_mm = now - low;
  e.motion = speed > 0.15 * amplitude ? 1 : speed < -0.15 * amplitude ? -1 : 0;
  if (high - low > 1.5 * amplitude + 2.0) {
    // More than breathing moves the skin: the patient or the camera moved. Start again.
    e.reason = fmt::format("breathing phase: the patient board moved {:.0f} mm, more than breathing "
                           "moves the skin ({:.1f} mm): waiting for a still board",
                           high - low, amplitude);
    const Sample last = history_.back();
    history_.clear();
    history_.push_back(last);
    return e;
  }
  if (span_s < 3.0 || high - low < 0.5 * amplitude) {
    e.reason = fmt::format("breathing phase: waiting for a breath ({:.1f} of {:.1f} mm seen)",
                           high - low, amplitude);
    return e;
  }
  // Rising: phases 0 .. end-inhale; falling: end-inhale .. the last, then phase 0 again.
  std::vector<int> candidates;
  for (int k = 0; k < n; ++k) {
    const bool rising = k <= motion_.inhale_phase;
    const bool falling = k >= motion_.inhale_phase || k == 0;
    if (e.motion == 0 || (e.motion > 0 && rising) || (e.motion < 0 && falling)) candidates.push_back(k);
  }
  double best = std::numeric_limits<double>::infinity();
  for (int k : candidates) {
    const double d = std::abs(motion_.displacement_mm[size_t(k)] - e.displacement_mm);
    if (d < best) best = d, e.phase = k;
  }
  e.known = true;
  return e;
}

int phase_distance(int a, int b, int n) {
  const int d = std::abs(a - b) % n;
  return std::min(d, n - d);
}

}  // namespace crepuscular::planning
