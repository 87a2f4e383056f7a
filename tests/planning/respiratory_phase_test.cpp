// The breathing phase from the patient board's motion: the skin's motion at a board on the
// breathing phantom's anterior wall against the phantom's own wall motion, and the phase
// estimated from a noisy board signal at 12, 15 and 20 breaths a minute against the true phase.
#include "planning/breathing/respiratory_phase.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "foundation/error.hpp"
#include "planning/simulation/phantom.hpp"

namespace crepuscular::planning {
namespace {

constexpr int kPhases = 6;

// The phantom's skin at the abdomen's anterior midline (x 0, z -30 mm) rises by 0.7 x 12 mm x
// inhale: the labels of six phases (3 mm voxels) give it to within half a voxel, phase 3
// end-inhale.
TEST(RespiratoryPhase, SkinMotionAtTheBoardFollowsThePhantomsWall) {
  std::vector<Volume<int32_t>> labels;
  std::vector<std::string> names;
  for (int k = 0; k < kPhases; ++k) {
    PhantomOptions o;
    o.spacing_mm = 3.0;
    o.inhale = breathing_inhale(k, kPhases);
    const Phantom ph = make_phantom(o);
    Volume<int32_t> l(ph.labels.geometry(), 0);
    for (int64_t n = 0; n < l.voxel_count(); ++n) l[n] = ph.labels[n];
    labels.push_back(std::move(l));
    names.push_back("phase0" + std::to_string(k));
  }
  std::vector<const Volume<int32_t>*> pointers;
  for (const auto& l : labels) pointers.push_back(&l);
  const Eigen::Vector3d board(0.0, -108.0, -30.0);
  const SkinMotion m = skin_motion(pointers, board, Eigen::Vector3d(0, -1, 0), names);
  ASSERT_EQ(m.displacement_mm.size(), size_t(kPhases));
  EXPECT_EQ(m.inhale_phase, 3);
  for (int k = 0; k < kPhases; ++k) {
    const double expected = -breathing_wall_displacement(board, breathing_inhale(k, kPhases), 12.0).y();
    EXPECT_NEAR(m.displacement_mm[size_t(k)], expected, 1.5) << "phase " << k;
  }
  EXPECT_NEAR(m.amplitude_mm(), 0.7 * 12.0, 0.8);
  // A board far from any skin is refused, naming the phase.
  try {
    skin_motion(pointers, Eigen::Vector3d(0, -300, -30), Eigen::Vector3d(0, -1, 0), names);
    FAIL() << "a board 200 mm off the skin was accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("phase00"), std::string::npos) << e.what();
  }
}

SkinMotion sine_motion(double amplitude) {
  SkinMotion m;
  m.direction = Eigen::Vector3d(0, -1, 0);
  for (int k = 0; k < kPhases; ++k) m.displacement_mm.push_back(amplitude * breathing_inhale(k, kPhases));
  m.inhale_phase = kPhases / 2;
  return m;
}

// A board on skin that rises 8.4 mm with each breath (sin^2 over the cycle, as the phases are
// spaced), tracked at 30 fps with 0.3 mm of noise, for 60 s: once a breath has been seen (within
// 2 breaths), the estimated phase is within one phase of the true one in at least 95 % of the
// frames, and the true phase in most.
TEST(RespiratoryPhase, EstimatedPhaseIsWithinOnePhaseOfTheTruth) {
  for (const double per_minute : {12.0, 15.0, 20.0}) {
    SCOPED_TRACE(std::to_string(per_minute) + " breaths a minute");
    const double period = 60.0 / per_minute;
    RespiratoryPhaseEstimator estimator(sine_motion(8.4));
    std::mt19937 rng(7);
    std::normal_distribution<double> noise(0.0, 0.3);
    int known = 0, within_one = 0, exact = 0;
    double first_known_s = -1;
    for (int i = 0; i < 60 * 30; ++i) {
      const double t = i / 30.0 + 0.37 * period;  // starts mid-breath
      const double cycle = t / period - std::floor(t / period);
      const double s = 40.0 + 8.4 * std::pow(std::sin(M_PI * cycle), 2) + noise(rng);
      const PhaseEstimate e = estimator.update(int64_t(std::llround(i / 30.0 * 1e9)), s);
      if (!e.known) {
        EXPECT_FALSE(e.reason.empty());
        EXPECT_LT(first_known_s, 0) << "the phase was lost again at frame " << i;
        continue;
      }
      if (first_known_s < 0) first_known_s = i / 30.0;
      const int truth = int(std::lround(cycle * kPhases)) % kPhases;
      ++known;
      within_one += phase_distance(e.phase, truth, kPhases) <= 1;
      exact += e.phase == truth;
    }
    std::printf("%.0f / min: known after %.1f s; within one phase %.3f, exact %.3f\n", per_minute,
                first_known_s, double(within_one) / known, double(exact) / known);
    ASSERT_GE(first_known_s, 0);
    EXPECT_LE(first_known_s, 2 * period + 1.0);
    EXPECT_GE(double(within_one) / known, 0.95);
    EXPECT_GE(double(exact) / known, 0.6);
  }
}

// A board on skin that does not move with breathing never gives a phase; a gap in tracking, or a
// board carried farther than breathing moves it, starts the wait for a breath again.
TEST(RespiratoryPhase, StillSkinOrATrackingGapGivesNoPhase) {
  RespiratoryPhaseEstimator still(sine_motion(0.2));
  const PhaseEstimate e = still.update(0, 10.0);
  EXPECT_FALSE(e.known);
  EXPECT_NE(e.reason.find("too little"), std::string::npos) << e.reason;

  RespiratoryPhaseEstimator estimator(sine_motion(8.4));
  PhaseEstimate last;
  for (int i = 0; i < 30 * 10; ++i) {
    last = estimator.update(int64_t(i) * 33'333'333, 8.4 * std::pow(std::sin(M_PI * i / 120.0), 2));
  }
  EXPECT_TRUE(last.known);
  const PhaseEstimate after_gap = estimator.update(int64_t(12e9), 0.0);
  EXPECT_FALSE(after_gap.known);
  // A board carried 30 mm (the patient moved): no phase, and the wait starts again.
  RespiratoryPhaseEstimator moved(sine_motion(8.4));
  for (int i = 0; i < 30 * 10; ++i) {
    last = moved.update(int64_t(i) * 33'333'333, 8.4 * std::pow(std::sin(M_PI * i / 120.0), 2));
  }
  EXPECT_TRUE(last.known);
  const PhaseEstimate carried = moved.update(int64_t(300) * 33'333'333, 40.0);
  EXPECT_FALSE(carried.known);
  EXPECT_NE(carried.reason.find("moved"), std::string::npos) << carried.reason;
  EXPECT_FALSE(moved.update(int64_t(301) * 33'333'333, 40.0).known);
  EXPECT_EQ(phase_distance(5, 0, 6), 1);
  EXPECT_EQ(phase_distance(1, 4, 6), 3);
}

}  // namespace
}  // namespace crepuscular::planning
