// The demo's report.md: the plan's class shares and safe regions, the needle along the
// recording, the files.
#include "pipelines/demo_report.hpp"

#include <array>
#include <nlohmann/json.hpp>
#include <cmath>
#include <fmt/format.h>
#include <sstream>

#include "overlay/guidance.hpp"
#include "planning/trajectories/evaluate.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::pipelines {

namespace {

std::string fmt3(const Eigen::Vector3d& v) {
  return fmt::format("({:.1f}, {:.1f}, {:.1f})", v.x(), v.y(), v.z());
}

// Share of region-of-interest voxels in each class (%).
std::array<double, 3> class_shares(const planning::Volume<float>& v,
                                   const planning::SafetyClasses& c) {
  std::array<double, 3> n{0, 0, 0};
  double total = 0;
  for (float x : v.values()) {
    if (!std::isfinite(x)) continue;
    n[size_t(c.classify(x))] += 1;
    total += 1;
  }
  for (double& s : n) s = total > 0 ? 100.0 * s / total : 0.0;
  return n;
}

std::string approach_text(const GuidanceApproach& a) {
  std::ostringstream o;
  const auto& s = a.state;
  o << fmt::format(
      "- **{} path**: entry {} mm (LPS), {:.0f} deg from straight anterior; line integral "
      "{:.2f} (insignificant <= {:.2f}), path safety at the entry: {}; tip to target {:.1f} mm.\n",
      a.name, fmt3(a.entry_ct), a.angle_from_anterior_deg, s.evaluation.line_integral, s.eps,
      s.tip_class, s.tip_to_centroid_mm);
  const auto lines = overlay::needle_text(s);
  if (lines.empty()) {
    o << "  It crosses no structure that carries risk.\n";
  } else {
    o << "  It crosses:";
    for (const auto& l : lines) o << " " << l << ";";
    o << "\n";
  }
  return o.str();
}

// Needle safety over the frames of one approach.
struct Phase {
  const GuidanceApproach* approach;
  int64_t safe = 0, medium = 0, dangerous = 0, unknown = 0, lost = 0;
  double first_dangerous_s = -1;
};

void count_phase(Phase& p, const overlay::GuidanceFrameInfo& info, double time_s) {
  if (time_s < p.approach->start_s || time_s > p.approach->end_s) return;
  if (!info.needle) {
    ++p.lost;
    return;
  }
  switch (info.needle->state.safety) {
    case planning::NeedleSafety::kSafe:
      ++p.safe;
      break;
    case planning::NeedleSafety::kMedium:
      ++p.medium;
      break;
    case planning::NeedleSafety::kDangerous:
      ++p.dangerous;
      if (p.first_dangerous_s < 0) p.first_dangerous_s = time_s;
      break;
    case planning::NeedleSafety::kUnknown:
      ++p.unknown;
      break;
  }
}

}  // namespace

std::string demo_plan_report(const planning::PlanData& plan, double spacing_mm,
                             const std::string& mode, double plan_s) {
  std::ostringstream report;
  report << "# Crepuscular demo report\n\n"
         << "Built-in phantom abdomen (" << spacing_mm << " mm voxels) with a liver tumor.\n\n";
  report << "## Plan\n\n"
         << "Tumor centre " << fmt3(plan.tumor_centre) << " mm (LPS); region of interest "
         << plan.radius_mm << " mm around it; " << mode << " mode, computed in " << plan_s
         << " s.\n\n"
         << "| value | safe | medium | dangerous | (share of the region's voxels) |\n"
         << "|---|---|---|---|---|\n";
  for (const auto& v : plan.values) {
    const auto s = class_shares(plan.path_safety.at(v), plan.classes.at(v));
    report << fmt::format("| {} | {:.1f} % | {:.1f} % | {:.1f} % | |\n", v, s[0], s[1], s[2]);
  }
  if (plan.area) {
    report << "\nArea safety: " << plan.area->regions.size() << " safe region(s)";
    if (!plan.area->regions.empty()) {
      report << fmt::format("; the largest is {:.1f} cm3 around {} mm",
                            plan.area->regions[0].size_mm3 / 1000.0,
                            fmt3(plan.area->regions[0].centre));
    }
    report << ".\n";
  }
  return report.str();
}

std::string demo_guidance_report(const GuidanceScenario& scenario, const GuideSummary& g) {
  Phase phases[2] = {{&scenario.safe}, {&scenario.dangerous}};
  for (const auto& info : g.frame_infos) {
    const double time_s = double(info.frame) / scenario.scene.fps;
    for (Phase& p : phases) count_phase(p, info, time_s);
  }
  std::ostringstream report;
  report << "\n## The needle along the recording\n\n"
         << "A synthetic camera recording (" << g.frames << " frames at " << scenario.scene.fps
         << " fps, 1280x720) of the patient board on the skin and a tracked needle, guided "
            "headless with the calibration files in setup/.\n\n";
  report << approach_text(scenario.safe) << approach_text(scenario.dangerous) << "\n";
  report << "| approach | time | frames safe | medium | dangerous | "
            "unknown (no line to the tumor inside the scan) | needle not tracked |\n"
         << "|---|---|---|---|---|---|---|\n";
  for (const Phase& p : phases) {
    report << fmt::format("| {} | {:.1f}-{:.1f} s | {} | {} | {} | {} | {} |\n", p.approach->name,
                          p.approach->start_s, p.approach->end_s, p.safe, p.medium, p.dangerous,
                          p.unknown, p.lost);
  }
  report << fmt::format(
      "\nAnatomy shown in {} of {} frames (patient board tracked); needle evaluated in {}. "
      "Latency from frame arrival to finished overlay: median {:.1f} ms, p95 {:.1f} ms (tracking "
      "{:.1f} ms, overlay {:.1f} ms, rendering {:.1f} ms; {}).\n",
      g.patient_tracked, g.frames, g.needle_evaluated, g.latency_median_ms, g.latency_p95_ms,
      g.track_median_ms, g.overlay_median_ms, g.render_median_ms, g.gl);
  // The needle line's uncertainty against the truth of the recording: the true line inside the
  // predicted 95 % region, and the spread of the crossing at the tumor against the predicted one.
  int with_line = 0, inside = 0, uncertain = 0;
  double measured2 = 0, predicted2 = 0;
  for (const auto& info : g.frame_infos) {
    if (!info.needle || !info.needle->uncertainty.valid || info.needle->state.points_away) continue;
    const planning::LineUncertainty& u = info.needle->uncertainty;
    const Eigen::Isometry3d T = scenario.T_ct_needle_at(double(info.frame) / scenario.scene.fps);
    const Eigen::Vector3d tip = T * tracking::kNeedleTipInNeedle, axis = T.linear().col(2);
    ++with_line;
    inside += u.inside95(tip, axis);
    uncertain += info.needle->region.uncertain();
    const double along = axis.dot(u.axis);
    if (std::abs(along) > 1e-6) {
      const double depth = (u.tumor_crossing - tip).dot(u.axis) / along;
      measured2 += (tip + depth * axis - u.tumor_crossing).squaredNorm();
      predicted2 += u.at_tumor.trace();
    }
  }
  if (with_line > 0 && predicted2 > 0) {
    report << fmt::format(
        "\nThe needle line's 95 % uncertainty (the boards' pose covariances, the needle "
        "calibration's and the registration's expected errors) held the true line in {:.1f} % "
        "of the {} frames with a line; the crossing at the tumor was off by {:.2f} mm RMS where "
        "{:.2f} mm was predicted; UNCERTAIN (a line of the region less safe than the needle's own) "
        "in {} of them.\n",
        100.0 * inside / with_line, with_line, std::sqrt(measured2 / with_line),
        std::sqrt(predicted2 / with_line), uncertain);
  }
  report << "\nSnapshots: snapshots/safe_path.png and snapshots/dangerous_path.png (end of each "
            "approach), and midway through each.\n";
  return report.str();
}

std::string demo_files_report(bool guidance, double total_s) {
  std::ostringstream report;
  report << "\n## Files\n\n"
         << "- phantom/: ct.nii.gz, labels.nii.gz, tumor.nii.gz, vulnerability.json\n"
         << "- plan/: path_safety_*.nii.gz (NaN outside the region), blocking.nii.gz, "
            "area_safety.vtk, plan.json: open with the CT in 3D Slicer\n"
         << "- slices/: axial, coronal, sagittal and oblique views through the largest safe "
            "region\n"
         << "- 3d/: the 3D planning view from anterior, anterior-left, left and the feet "
            "(`crepuscular view --plan plan` shows it in a window)\n";
  if (guidance) {
    report << "- setup/: camera.yaml, registration.yaml, needle.yaml, boards.json, scene.json\n"
           << "- recording/: the synthetic camera recording with its ground truth\n"
           << "- overlay.mp4, overlay.csv (per frame: tracking, needle safety, latency), "
              "snapshots/\n";
  }
  report << fmt::format("\nThe demo took {:.0f} s.\n", total_s);
  return report.str();
}

std::string demo_breathing_report(const planning::PlanData& plan,
                                  const GuidanceScenario& scenario, const GuideSummary& guide) {
  std::ostringstream o;
  o << "\n## Breathing\n\n";
  const nlohmann::json& b = plan.json.at("breathing");
  o << fmt::format(
      "The phantom breathes: {} phases of one cycle (phase 00 end-exhale, the middle one "
      "end-inhale). Path safety was computed per phase on one grid and combined: a voxel is safe "
      "only if it is safe in every phase (svv the minimum over the phases, the others the "
      "maximum). Share of the known region whose class changes over the cycle:",
      plan.phases.size());
  for (const auto& [value, share] : b.at("class_change_share").items()) {
    o << fmt::format(" {} {:.1f} %", value, 100.0 * share.get<double>());
  }
  o << ".\n\n";
  const planning::TrajectoryEvaluator evaluator(plan);
  const std::array<const GuidanceApproach*, 2> approaches = {&scenario.safe, &scenario.dangerous};
  for (const std::string& value : plan.values) {
    if (!plan.phase_path_safety.count(value)) continue;
    const planning::SafetyClasses& classes = plan.classes.at(value);
    o << "Path safety (" << value << ") at each approach's entry, per phase (class by the "
      << "combined plan's thresholds):\n\n| phase |";
    for (const auto* a : approaches) o << " " << a->name << " path |";
    o << "\n|---|";
    for (size_t i = 0; i < approaches.size(); ++i) o << "---|";
    o << "\n";
    std::vector<planning::TrajectoryEvaluation> evals;
    for (const auto* a : approaches) {
      evals.push_back(evaluator.evaluate({a->name, a->entry_ct, scenario.target_ct}));
    }
    const auto cell = [&](double x) {
      static const char* const kNames[] = {"safe", "medium", "dangerous", "unknown"};
      return std::isfinite(x) ? fmt::format("{:.3g} {}", x, kNames[int(classes.classify(x))])
                              : std::string("unknown");
    };
    for (size_t k = 0; k < plan.phases.size(); ++k) {
      o << "| " << plan.phases[k] << " |";
      for (const auto& e : evals) {
        for (const auto& v : e.values) {
          if (v.value != value) continue;
          o << " " << cell(k < v.per_phase.size() ? v.per_phase[k] : NAN) << " |";
        }
      }
      o << "\n";
    }
    o << "| **combined** |";
    for (const auto& e : evals) {
      for (const auto& v : e.values) {
        if (v.value == value) o << " **" << cell(v.at_entry) << "** |";
      }
    }
    o << "\n| worst phase |";
    for (const auto& e : evals) {
      for (const auto& v : e.values) {
        if (v.value == value) o << " " << (v.worst_phase.empty() ? "-" : v.worst_phase) << " |";
      }
    }
    o << "\n\n";
  }
  // The guidance run: the phase estimated from the patient board's motion against the truth.
  const int n = int(plan.phases.size());
  int known = 0, within_one = 0, exact = 0;
  double first_known_s = -1;
  for (const auto& info : guide.frame_infos) {
    if (!info.breathing || !info.breathing->estimate.known) continue;
    const double t = double(info.frame) / scenario.scene.fps;
    const int truth = scenario.breathing_phase_at(t);
    if (first_known_s < 0) first_known_s = t;
    ++known;
    within_one += planning::phase_distance(info.breathing->estimate.phase, truth, n) <= 1;
    exact += info.breathing->estimate.phase == truth;
  }
  o << fmt::format(
      "Guidance on the breathing recording ({:.0f} breaths a minute; the patient board rises with "
      "the skin, the camera and the needle stay in the room): the phase is estimated from the "
      "board's motion against the skin's motion under it over the plan's phases, and the needle "
      "is evaluated in the current phase and in every phase.\n\n",
      60.0 / scenario.breathing_period_s);
  if (known > 0) {
    o << fmt::format("- Phase known from {:.1f} s on, in {} frames: within one phase of the true "
                     "phase in {:.1f} % of them, the true phase in {:.1f} %.\n",
                     first_known_s, known, 100.0 * within_one / known, 100.0 * exact / known);
  } else {
    o << "- The phase was never known during the recording.\n";
  }
  for (const GuidanceApproach* a : approaches) {
    const int64_t end = std::min<int64_t>(scenario.scene.frame_count - 1,
                                          int64_t(std::floor(a->end_s * scenario.scene.fps)));
    for (const auto& info : guide.frame_infos) {
      if (info.frame != end || !info.breathing || !info.needle) continue;
      std::string safe;
      for (size_t k = 0; k < info.breathing->phase_safety.size(); ++k) {
        if (info.breathing->phase_safety[k] == planning::NeedleSafety::kSafe) {
          safe += (safe.empty() ? "" : ", ") + plan.phases[k];
        }
      }
      o << fmt::format("- The {} approach at its end (frame {}): the line is safe in {}.\n",
                       a->name, end, safe.empty() ? std::string("no phase") : safe);
    }
  }
  o << "\n";
  o << "Files: phantom/phases.json and phantom/phaseKK/ (CT, labels, tumor per phase; the slices, "
       "registration and guidance use phase00, end-exhale), plan/path_safety_<value>_phaseKK.nii.gz "
       "(each phase), plan/path_safety_<value>.nii.gz (the combination, which the overlay "
       "draws).\n";
  return o.str();
}

}  // namespace crepuscular::pipelines
