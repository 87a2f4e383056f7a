#include "pipelines/guide_breathing.hpp"

#include <chrono>
#include <cmath>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "planning/imaging/sampling.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/preprocessing/blocking.hpp"
#include "planning/safety/area_safety.hpp"

namespace crepuscular::pipelines {

namespace {

// The board's normal that points out of the body of `labels` (phase 0): 10 mm along it lies air
// in the scan (beyond the scan's edge nothing is known), 10 mm against it the body.
Eigen::Vector3d outward_normal(const planning::Volume<int32_t>& labels,
                               const Eigen::Isometry3d& T_ct_patient, const std::string& where) {
  const Eigen::Vector3d origin = T_ct_patient.translation();
  const Eigen::Vector3d normal = T_ct_patient.linear().col(2);
  for (const Eigen::Vector3d& d : {Eigen::Vector3d(-normal), normal}) {
    if (planning::nearest_voxel(labels, origin + 10.0 * d) == std::optional<int32_t>(0) &&
        planning::nearest_voxel_or<int32_t>(labels, origin - 10.0 * d, 0) > 0) {
      return d;
    }
  }
  throw Error(where + ": the registered patient board (at " +
              std::to_string(origin.x()) + ", " + std::to_string(origin.y()) + ", " +
              std::to_string(origin.z()) +
              " mm, LPS) does not lie on the skin of phase 0: its phase cannot be told from its "
              "motion");
}

}  // namespace

std::unique_ptr<overlay::BreathingPhases> load_breathing_phases(const planning::PlanData& plan,
                                                                const Eigen::Isometry3d& T_ct_patient) {
  if (plan.phases.empty()) return nullptr;
  if (plan.phase_path_safety.empty()) {
    spdlog::info("guide: {} was made over {} breathing phases without per-phase volumes (plan "
                 "--per-phase): guidance shows their combination, safe only where every phase is",
                 plan.dir, plan.phases.size());
    return nullptr;
  }
  if (!plan.table) {
    throw Error(plan.dir + "/plan.json: the breathing plan records no vulnerability table to "
                "compute each phase's blocking with");
  }
  const auto start = std::chrono::steady_clock::now();
  planning::MarginOptions margin;
  margin.fwhm_mm = plan.json.at("preprocessing").value("margin_fwhm_mm", margin.fwhm_mm);
  const nlohmann::json& listed = plan.json.at("breathing").at("phases");
  auto phases = std::make_unique<overlay::BreathingPhases>();
  std::vector<const planning::Volume<int32_t>*> labels;
  for (size_t k = 0; k < plan.phases.size(); ++k) {
    auto p = std::make_unique<planning::PlanData>();
    p->dir = plan.dir;
    p->json = plan.json;
    p->grid = plan.grid;
    p->gamma_mm = plan.gamma_mm;
    p->radius_mm = plan.radius_mm;
    p->values = plan.values;
    p->region = plan.region;
    p->classes = plan.classes;
    p->table = plan.table;
    const auto& c = listed.at(k).at("tumor_centroid_lps_mm");
    p->tumor_centre = Eigen::Vector3d(c.at(0).get<double>(), c.at(1).get<double>(), c.at(2).get<double>());
    for (const auto& [value, volumes] : plan.phase_path_safety) p->path_safety[value] = volumes.at(k);
    p->labels_path = planning::plan_phase_input_path(plan, k, "labels");
    p->labels = planning::read_label_map(p->labels_path);
    const std::string tumor = planning::plan_phase_input_path(plan, k, "tumor");
    if (!tumor.empty()) p->tumor = planning::read_mask(tumor);
    p->blocking = planning::blocking_from_labels(p->labels, *plan.table, margin, p->labels_path);
    if (plan.area && !p->tumor.empty()) {
      // The phase's own safe regions, by the plan's criterion (its value and threshold).
      const std::string value = plan.json.at("area_safety").value("value", plan.values.front());
      planning::AreaSafetyOptions o;
      o.spacing_mm = plan.grid.spacing[0];
      o.max_distance_mm = plan.area->max_distance_mm > 0 ? plan.area->max_distance_mm : plan.radius_mm;
      planning::AreaSafetyGeometry g = planning::compute_area_safety(
          planning::fit_tumor_ellipsoid(p->tumor, tumor),
          planning::path_safety_test(p->path_safety.at(value),
                                     plan.classes.at(value).higher_is_safer, plan.area->threshold,
                                     plan.radius_mm, plan.region.empty() ? nullptr : &plan.region),
          o);
      g.criterion = plan.area->criterion;
      g.threshold = plan.area->threshold;
      p->area = std::move(g);
    }
    phases->names.push_back(plan.phases[k]);
    phases->plans.push_back(std::move(p));
  }
  for (const auto& p : phases->plans) labels.push_back(&p->labels);
  const Eigen::Vector3d outward = outward_normal(*labels.front(), T_ct_patient, phases->plans.front()->labels_path);
  phases->skin = planning::skin_motion(labels, T_ct_patient.translation(), outward, phases->names);
  std::string curve;
  for (double d : phases->skin.displacement_mm) curve += fmt::format(" {:.1f}", d);
  spdlog::info("guide: breathing over {} phases (read in {:.1f} s); the skin under the patient "
               "board moves{} mm (from phase 0, outward); the phase is estimated from the board's "
               "motion",
               phases->names.size(),
               std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(),
               curve);
  return phases;
}

}  // namespace crepuscular::pipelines
