// The slices job: the plan and the CT -> one view per plane through the tumor (or a safe
// region) -> OUT/<plane>.png and OUT/slices.json, written as one folder.
#include "pipelines/slices.hpp"

#include <fmt/format.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <optional>
#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "planning/imaging/scan_coverage.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/plan_folder/plan_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {

using namespace planning;  // NOLINT: the job drives the planning modules throughout

namespace {

// The scan the plan was made from (its label map, else its CT) when its grid is known, and a
// warning when the CT given lies on another grid: it may be another patient's or another day's
// scan, whose anatomy the plan's colours would be drawn over. "" when they agree or nothing is
// known to compare with.
std::string other_scan_warning(const PlanData& plan, const ImageGeometry& ct,
                               const std::string& ct_path) {
  std::optional<ImageGeometry> planned;
  std::string planned_from;
  if (!plan.labels.empty()) {
    planned = plan.labels.geometry();
    planned_from = "the plan's label map " + plan.labels_path;
  } else if (plan.json.contains("inputs") && plan.json["inputs"].is_object() &&
             plan.json["inputs"].contains("ct") && plan.json["inputs"]["ct"].is_object() &&
             plan.json["inputs"]["ct"].contains("path")) {
    const std::string path = plan.json["inputs"]["ct"]["path"].get<std::string>();
    std::error_code ec;
    if (!fs::exists(path, ec) || fs::equivalent(path, ct_path, ec)) return {};
    planned = read_volume_geometry(path);
    planned_from = "the plan's CT " + path;
  }
  if (!planned || ct.same_grid(*planned, 1e-3)) return {};
  const auto grid_text = [](const ImageGeometry& g) {
    return fmt::format("{} x {} x {} voxels of {:.3g} x {:.3g} x {:.3g} mm from ({:.1f}, {:.1f}, "
                       "{:.1f})",
                       g.dims[0], g.dims[1], g.dims[2], g.spacing[0], g.spacing[1], g.spacing[2],
                       g.origin[0], g.origin[1], g.origin[2]);
  };
  return fmt::format(
      "{}: the CT is not on the grid of {} ({} against {}): it may be another scan; the plan is "
      "drawn over it where they overlap in LPS, check that it is the scan planned on",
      ct_path, planned_from, grid_text(ct), grid_text(*planned));
}

// Where the planes pass and which way the oblique one runs.
struct Placement {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  Eigen::Vector3d axis = Eigen::Vector3d::Zero();
  const AreaRegion* region = nullptr;
};

Placement place_planes(const SlicesRequest& req, const PlanData& plan) {
  Placement p;
  p.centre = req.have_at ? req.at : plan.tumor_centre;
  if (req.region >= 0) {
    const std::string which = "region " + std::to_string(req.region);
    if (!plan.area) {
      throw Error(which + ": " + req.plan_dir + " has no area safety geometry (area_safety.vtk)");
    }
    for (const auto& r : plan.area->regions) {
      if (r.id == req.region) p.region = &r;
    }
    if (!p.region) {
      throw Error(which + ": no such region (the plan has " +
                  std::to_string(plan.area->regions.size()) + ", numbered from 0)");
    }
    if (!req.have_at) p.centre = p.region->centre;
    p.axis = p.region->main_axis;
  }
  const bool want_oblique =
      std::find(req.planes.begin(), req.planes.end(), SlicePlaneKind::kOblique) != req.planes.end();
  if (want_oblique && !p.region) {
    if (!plan.area || plan.area->regions.empty()) {
      throw Error("oblique plane: the plane follows a safe region's main axis, but " +
                  req.plan_dir + " has no area safety regions (area_safety.vtk)");
    }
    p.region = &plan.area->regions[0];
    p.axis = p.region->main_axis;
    spdlog::info("oblique plane along the main axis of region {} (the largest)", p.region->id);
  }
  return p;
}

// One pixel size for every view of the run, so that the images compare at a glance: the finest
// spacing of the CT and the plan, divided so that the CT's largest extent spans at least
// min_view_pixels.
double common_pixel_mm(const ImageGeometry& g, const ImageGeometry& plan_grid,
                       int min_view_pixels) {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
  for (int c = 0; c < 8; ++c) {
    const Eigen::Vector3d p = g.index_to_physical(
        Eigen::Vector3d((c & 1) ? g.dims[0] - 0.5 : -0.5, (c & 2) ? g.dims[1] - 0.5 : -0.5,
                        (c & 4) ? g.dims[2] - 0.5 : -0.5));
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  const double finest = std::min(g.spacing.minCoeff(), plan_grid.spacing.minCoeff());
  const double extent = (hi - lo).maxCoeff();
  const int factor = std::max(1, int(std::ceil(min_view_pixels / (extent / finest))));
  return finest / factor;
}

nlohmann::json vec_json(const Eigen::Vector3d& p) { return nlohmann::json{p.x(), p.y(), p.z()}; }

nlohmann::json view_json(const std::string& file, SlicePlaneKind kind, const SlicePlane& plane,
                         const SliceView& view) {
  return {{"file", file},
          {"plane", plane_name(kind)},
          {"centre_lps_mm", vec_json(plane.centre)},
          {"right_lps", vec_json(plane.right)},
          {"down_lps", vec_json(plane.down)},
          {"pixel_0_0_lps_mm", vec_json(view.origin)},
          {"pixel_mm", view.pixel_mm},
          {"view_width", view.view_width},
          {"view_height", view.view_height},
          {"image_width", view.image.width},
          {"image_height", view.image.height},
          {"structures", view.structures},
          {"contour_segments", view.contour_segments},
          {"unknown_pixels", view.unknown_pixels}};
}


}  // namespace

nlohmann::json run_slices(const SlicesRequest& req) {
  const auto t0 = std::chrono::steady_clock::now();
  if (req.plan_dir.empty()) throw Error("slices: a plan folder is required");
  if (req.ct.empty()) throw Error("slices: the CT is required");
  if (req.out_dir.empty()) throw Error("slices: an output folder is required");
  if (req.planes.empty()) throw Error("slices: no plane given");

  const std::string value = req.value.empty() ? plan_default_value(req.plan_dir) : req.value;
  PlanLoadOptions load;
  load.blocking = false;
  load.only_value = value;
  load.labels_override = req.labels;
  load.series = req.series;
  spdlog::info("reading plan {}", req.plan_dir);
  const PlanData plan = load_plan(req.plan_dir, load);
  spdlog::info("reading CT {}", req.ct);
  const Volume<float> ct = read_volume<float>(req.ct, {req.series});
  require_overlap_with_plan(ct.geometry(), plan.grid, req.ct, "the CT");
  const std::string other_scan = other_scan_warning(plan, ct.geometry(), req.ct);
  if (!other_scan.empty()) spdlog::warn("slices: {}", other_scan);
  const Placement place = place_planes(req, plan);

  SliceScene scene;
  scene.ct = &ct;
  scene.path_safety = &plan.path_safety.at(value);
  scene.region_state = plan.region.empty() ? nullptr : &plan.region;
  scene.value_name = value;
  scene.classes = plan.classes.at(value);
  scene.labels = plan.labels.empty() ? nullptr : &plan.labels;
  scene.table = plan.table ? &*plan.table : nullptr;
  scene.tumor = plan.tumor.empty() ? nullptr : &plan.tumor;
  scene.area = plan.area ? &*plan.area : nullptr;
  scene.region = place.region;
  if (!scene.area) {
    spdlog::info("{}: no area_safety.vtk; slices show no leeway contour", req.plan_dir);
  }
  SliceOptions options = req.options;
  if (!(options.pixel_mm > 0)) {
    options.pixel_mm = common_pixel_mm(ct.geometry(), plan.grid, options.min_view_pixels);
  }

  StagedDirectory out(req.out_dir);
  nlohmann::json views = nlohmann::json::array();
  std::vector<SlicePlaneKind> done;  // a plane named twice is drawn once
  for (const auto kind : req.planes) {
    if (std::find(done.begin(), done.end(), kind) != done.end()) continue;
    done.push_back(kind);
    const SlicePlane plane = make_slice_plane(kind, place.centre, place.axis);
    const SliceView view = render_slice(scene, plane, options);
    const std::string file = std::string(plane_name(kind)) + ".png";
    write_png(view.image, out.file(file));
    spdlog::info("{}: {} x {} pixels of {:.2f} mm, {} structures, {} contour segments", file,
                 view.view_width, view.view_height, view.pixel_mm, view.structures.size(),
                 view.contour_segments);
    if (view.unknown_pixels > 0) {
      spdlog::warn("{}: {} pixels show the region of interest outside the scan (unknown, hatched)",
                   file, view.unknown_pixels);
    }
    views.push_back(view_json(file, kind, plane, view));
  }
  nlohmann::json j = {
      {"plan", fs::absolute(final_path_of(req.plan_dir)).string()},
      {"ct", fs::absolute(final_path_of(req.ct)).string()},
      {"value", value},
      {"palette", req.options.palette == Palette::kColorblind ? "colorblind" : "default"},
      {"window_hu", {{"width", req.options.window_width}, {"level", req.options.window_level}}},
      {"region", place.region ? nlohmann::json(place.region->id) : nlohmann::json(nullptr)},
      {"pixel_convention",
       "pixel (x, y) shows pixel_0_0 + x pixel_mm right + y pixel_mm down; the "
       "view occupies columns [0, view_width), the legend the rest"},
      {"views", views}};
  if (!other_scan.empty()) j["warnings"] = {other_scan};
  j["changed_inputs"] = nlohmann::json::array();
  for (const auto& c : plan.changed_inputs) j["changed_inputs"].push_back(c.message);
  write_text_file(out.file("slices.json"), j.dump(2) + "\n");
  out.commit();
  spdlog::info("slices written to {} ({:.2f} s)", req.out_dir,
               std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  return j;
}

}  // namespace crepuscular::pipelines
