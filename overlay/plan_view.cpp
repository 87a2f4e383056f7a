#include "overlay/plan_view.hpp"

#define GL_GLEXT_PROTOTYPES 1
#include <GL/glcorearb.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <optional>
#include <set>

#include "foundation/error.hpp"
#include "planning/views/palette.hpp"

namespace crepuscular::overlay {

namespace {

constexpr double kPi = 3.14159265358979323846;
double radians(double deg) { return deg * kPi / 180.0; }

// Surfaces of the fixed kinds, then the structures' colours (none green, yellow, red or grey, the
// colours of the classes and of unknown).
const AnatomySurface kSkinSurface{"skin", {225, 185, 160}, 0.12};
const AnatomySurface kBoneSurface{"bone", {240, 235, 215}, 0.45};
const AnatomySurface kTumorSurface{"tumor", {160, 70, 230}, 0.7};
constexpr double kStructureOpacity = 0.35;
const planning::Rgb kStructureColours[] = {{70, 110, 235},  {60, 195, 225},  {215, 90, 210},
                                           {150, 100, 60},  {245, 160, 205}, {45, 65, 160},
                                           {40, 150, 150},  {175, 150, 235}, {120, 60, 120},
                                           {100, 170, 255}, {200, 140, 100}, {90, 90, 200}};

bool bone_name(const std::string& name) {
  std::string n = name;
  std::transform(n.begin(), n.end(), n.begin(), [](unsigned char c) { return std::tolower(c); });
  for (const char* word : {"bone", "rib", "vertebra", "sternum", "skull", "pelvis", "femur",
                           "scapula", "clavicul", "sacrum", "hip", "humerus", "spine"}) {
    if (n.find(word) != std::string::npos) return true;
  }
  return false;
}

double grid_diagonal(const planning::ImageGeometry& g) {
  return Eigen::Vector3d(g.spacing.x() * double(g.dims[0]), g.spacing.y() * double(g.dims[1]),
                         g.spacing.z() * double(g.dims[2]))
      .norm();
}

}  // namespace

ViewAngles parse_view_angles(const std::string& text) {
  std::string t = text;
  std::transform(t.begin(), t.end(), t.begin(), [](unsigned char c) { return std::tolower(c); });
  if (t == "anterior") return {0, 0};
  if (t == "left") return {90, 0};
  if (t == "posterior") return {180, 0};
  if (t == "right") return {-90, 0};
  if (t == "superior") return {0, 90};
  if (t == "inferior") return {0, -90};
  const auto comma = t.find(',');
  if (comma != std::string::npos) {
    try {
      size_t used_az = 0, used_el = 0;
      const std::string az = t.substr(0, comma), el = t.substr(comma + 1);
      const double a = std::stod(az, &used_az), e = std::stod(el, &used_el);
      if (used_az == az.size() && used_el == el.size() && std::isfinite(a) && std::isfinite(e) &&
          e >= -90 && e <= 90) {
        return {a, e};
      }
    } catch (const std::exception&) {
    }
  }
  throw Error("view '" + text +
              "': expected anterior, posterior, left, right, superior, inferior or AZ,EL in "
              "degrees (azimuth from anterior toward the patient's left, elevation -90 to 90 "
              "toward superior), e.g. 30,20");
}

Eigen::Isometry3d OrbitCamera::pose() const {
  const double az = radians(angles.azimuth_deg), el = radians(angles.elevation_deg);
  // Direction from the centre to the camera (LPS): anterior is -y, the patient's left +x.
  const Eigen::Vector3d out(std::sin(az) * std::cos(el), -std::cos(az) * std::cos(el),
                            std::sin(el));
  const Eigen::Vector3d z = -out;  // forward
  // Up: superior, or, looking along the superior axis, the side the azimuth names (anterior at
  // azimuth 0: from the feet the image is then an axial slice in the radiological convention).
  Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  if (std::abs(out.z()) > 0.999) up = Eigen::Vector3d(std::sin(az), -std::cos(az), 0);
  const Eigen::Vector3d x = z.cross(up).normalized();  // image right
  const Eigen::Vector3d y = z.cross(x);                  // image down
  Eigen::Isometry3d T_ct_cam = Eigen::Isometry3d::Identity();
  T_ct_cam.linear().col(0) = x;
  T_ct_cam.linear().col(1) = y;
  T_ct_cam.linear().col(2) = z;
  T_ct_cam.translation() = centre + distance_mm * out;
  return T_ct_cam.inverse();
}

calibration::CameraModel OrbitCamera::camera(int width, int height) const {
  calibration::CameraModel cam;
  cam.width = width;
  cam.height = height;
  cam.fy = 0.5 * height / std::tan(0.5 * radians(fov_deg));
  cam.fx = cam.fy;
  cam.cx = 0.5 * (width - 1);
  cam.cy = 0.5 * (height - 1);
  cam.distortion = {0, 0, 0, 0, 0};
  return cam;
}

double OrbitCamera::fitting_distance(double radius_mm, double fov_deg, double aspect) {
  // The smaller half-angle: vertical, or horizontal when the image is taller than wide.
  double half = 0.5 * radians(fov_deg);
  if (aspect < 1) half = std::atan(std::tan(half) * aspect);
  return 1.05 * radius_mm / std::sin(half);
}

AnatomyContext make_anatomy_context(const planning::PlanData& plan,
                                    const planning::Volume<float>* ct) {
  AnatomyContext context;
  const auto& grid = plan.grid;
  context.kinds = planning::Volume<uint8_t>(grid, 0);
  context.surfaces = {AnatomySurface{"outside", {0, 0, 0}, 0.0}, kSkinSurface, kBoneSurface,
                      kTumorSurface};
  // Bones by name (without a CT), structures by level.
  std::map<int, uint8_t> label_kind;
  std::set<int> bone_labels;
  if (plan.table && !plan.labels.empty()) {
    // Structures: the table's third level ("medium" in the presets) and above.
    std::vector<int> levels;
    for (const auto& l : plan.table->levels) levels.push_back(l.level);
    std::sort(levels.begin(), levels.end());
    const int lowest = levels.size() > 2 ? levels[2] - 1 : levels.empty() ? 0 : levels.front();
    std::vector<const planning::LabelClass*> structures;
    for (const auto& l : plan.table->labels) {
      if (l.value == 0) continue;
      if (bone_name(l.name)) {
        bone_labels.insert(l.value);
      } else if (l.level > lowest) {
        structures.push_back(&l);
      }
    }
    // The most vulnerable first, so that they get their own kinds.
    std::stable_sort(structures.begin(), structures.end(),
                     [](const auto* a, const auto* b) { return a->level > b->level; });
    const int available = kMaxAnatomyKinds - kStructureKind;
    for (size_t s = 0; s < structures.size(); ++s) {
      const int kind = kStructureKind + int(s % size_t(available));
      label_kind[structures[s]->value] = uint8_t(kind);
      if (int(s) < available) {
        const planning::Rgb colour = kStructureColours[s % std::size(kStructureColours)];
        context.surfaces.push_back({structures[s]->name, colour, kStructureOpacity});
      }
    }
  }
  const bool have_labels = !plan.labels.empty();
  const bool have_tumor = !plan.tumor.empty();
  const bool have_ct = ct && !ct->empty();
#pragma omp parallel for schedule(dynamic, 4)
  for (int64_t k = 0; k < grid.dims[2]; ++k) {
    for (int64_t j = 0; j < grid.dims[1]; ++j) {
      for (int64_t i = 0; i < grid.dims[0]; ++i) {
        const Eigen::Vector3d p = grid.index_to_physical(i, j, k);
        // Without a label map or a CT nothing says where the body ends: all of it is body.
        uint8_t kind = have_labels || have_ct ? kOutside : kSkin;
        int label = 0;
        if (have_labels) {
          const auto n = plan.labels.geometry().nearest_index(p);
          if (plan.labels.geometry().contains(n[0], n[1], n[2])) label = plan.labels(n[0], n[1], n[2]);
          if (label > 0) kind = kSkin;
        } else if (have_ct) {
          const auto n = ct->geometry().nearest_index(p);
          if (ct->geometry().contains(n[0], n[1], n[2]) && (*ct)(n[0], n[1], n[2]) > -400)
            kind = kSkin;
        }
        if (kind == kSkin) {
          if (have_ct) {
            const auto n = ct->geometry().nearest_index(p);
            if (ct->geometry().contains(n[0], n[1], n[2]) && (*ct)(n[0], n[1], n[2]) >= kBoneHu)
              kind = kBone;
          } else if (bone_labels.count(label)) {
            kind = kBone;
          }
          const auto s = label_kind.find(label);
          if (s != label_kind.end()) kind = s->second;
        }
        if (have_tumor) {
          const auto n = plan.tumor.geometry().nearest_index(p);
          if (plan.tumor.geometry().contains(n[0], n[1], n[2]) && plan.tumor(n[0], n[1], n[2]))
            kind = kTumor;
        }
        context.kinds(i, j, k) = kind;
      }
    }
  }
  return context;
}

PlanView3D::PlanView3D(const planning::PlanData& plan, const planning::Volume<float>* ct,
                       PlanViewOptions options)
    : plan_(plan), ct_(ct), options_(std::move(options)) {
  if (plan_.values.empty() || plan_.path_safety.empty()) {
    throw Error(plan_.dir + ": the plan holds no path safety volume to show");
  }
  value_ = options_.value;
  if (value_.empty()) {
    value_ = std::find(plan_.values.begin(), plan_.values.end(), "svv") != plan_.values.end()
                 ? "svv"
                 : plan_.values.front();
  }
  add_values(plan_);
  if (!values_.count(value_)) {
    std::string have;
    for (const auto& v : plan_.values) have += (have.empty() ? "" : ", ") + v;
    throw Error(plan_.dir + ": no path safety value '" + value_ + "' (the plan has " + have + ")");
  }
  context_ = make_anatomy_context(plan_, ct_);
}

PlanView3D::~PlanView3D() = default;

void PlanView3D::set_options(const PlanViewOptions& options) {
  options_ = options;
  options_.value = value_;
}

void PlanView3D::add_values(const planning::PlanData& plan) {
  for (const auto& [name, volume] : plan.path_safety) {
    if (values_.count(name) || !plan.classes.count(name)) continue;
    if (!values_.empty() && !volume.geometry().same_grid(plan_.grid, 1e-4)) {
      throw Error(plan.dir + ": path_safety_" + name + " is not on the plan's grid");
    }
    values_[name] = {&volume, plan.classes.at(name)};
  }
}

void PlanView3D::set_ct(const planning::Volume<float>* ct) {
  ct_ = ct;
  context_ = make_anatomy_context(plan_, ct_);
  for (auto& [value, r] : renderings_) retired_.push_back(std::move(r));
  renderings_.clear();
}

void PlanView3D::next_value() {
  std::vector<std::string> shown;
  for (const auto& v : plan_.values)
    if (values_.count(v)) shown.push_back(v);
  const auto it = std::find(shown.begin(), shown.end(), value_);
  value_ = (it == shown.end() || it + 1 == shown.end()) ? shown.front() : *(it + 1);
}

OrbitCamera PlanView3D::default_camera(ViewAngles angles, double aspect) const {
  OrbitCamera camera;
  camera.centre = plan_.tumor_centre;
  camera.angles = angles;
  // The region of interest's radius, else the grid's half diagonal.
  double radius = plan_.radius_mm;
  if (!(radius > 0)) {
    radius = 0.5 * grid_diagonal(plan_.grid);
  }
  camera.distance_mm = OrbitCamera::fitting_distance(radius, camera.fov_deg, aspect);
  return camera;
}

VolumeRenderingOptions PlanView3D::rendering_options(bool software, bool moving) const {
  VolumeRenderingOptions o;
  o.palette = options_.palette;
  o.show_safe = !options_.hidden[0];
  o.show_medium = !options_.hidden[1];
  o.show_dangerous = !options_.hidden[2];
  o.show_unknown = !options_.hidden[3];
  for (double& k : o.opacity_per_mm) k *= options_.opacity_scale;
  o.unknown_opacity_per_mm *= options_.opacity_scale;
  o.resolution_scale = options_.resolution_scale > 0 ? options_.resolution_scale
                       : !software                    ? 1.0
                       : moving                       ? 0.25
                                                      : 0.5;
  o.hidden_surfaces = options_.context ? options_.hidden_surfaces : ~0u;
  // One sample per voxel along the ray (nearest voxel): half a voxel doubles the work for the
  // same classes.
  o.step_mm = plan_.grid.spacing.minCoeff();
  return o;
}

SafetyVolumeRendering& PlanView3D::rendering() {
  auto& r = renderings_[value_];
  if (!r) {
    r = std::make_unique<SafetyVolumeRendering>(volume(), classes(),
                                                rendering_options(false, false),
                                                plan_.region.empty() ? nullptr : &plan_.region,
                                                &context_);
  }
  return *r;
}

void PlanView3D::draw(const DrawContext& frame, const cv::Rect& panel,
                      const calibration::CameraModel& camera, const Eigen::Isometry3d& T_cam_ct,
                      bool software, bool moving) {
  for (auto& old : retired_) old->release_gl();
  retired_.clear();
  SafetyVolumeRendering& r = rendering();
  r.set_options(rendering_options(software, moving));
  r.set_pose(T_cam_ct);
  // OpenGL's viewport counts rows from the bottom.
  glViewport(panel.x, frame.height - panel.y - panel.height, panel.width, panel.height);
  r.draw(DrawContext{camera, panel.width, panel.height});
  glViewport(0, 0, frame.width, frame.height);
}

std::vector<std::pair<Eigen::Vector3d, cv::Scalar>> PlanView3D::mesh_points(
    const Eigen::Isometry3d& T_cam_ct) const {
  std::vector<std::pair<Eigen::Vector3d, cv::Scalar>> points;
  if (!options_.area_mesh || !plan_.area) return points;
  const auto& g = *plan_.area;
  points.reserve(g.vertices.size());
  for (size_t v = 0; v < g.vertices.size(); ++v) {
    const double leeway = v < g.leeway.size() ? g.leeway[v] : 0.0;
    const bool safe = v < g.safe.size() && g.safe[v];
    const planning::Rgb c =
        safe ? planning::leeway_colour(options_.palette, leeway)
             : planning::class_colours(options_.palette)[size_t(planning::SafetyClass::kDangerous)];
    points.emplace_back(T_cam_ct * g.vertices[v], cv::Scalar(c[2], c[1], c[0]));
  }
  return points;
}

std::optional<Eigen::Vector3d> PlanView3D::pick_skin(const calibration::CameraModel& camera,
                                                     const Eigen::Isometry3d& T_cam_ct, double u,
                                                     double v) const {
  const Eigen::Vector3f d = pixel_ray(camera, u, v);
  if (d.squaredNorm() < 0.5f) return std::nullopt;
  const Eigen::Isometry3d T_ct_cam = T_cam_ct.inverse();
  const Eigen::Vector3d origin = T_ct_cam.translation();
  const Eigen::Vector3d dir = T_ct_cam.linear() * d.cast<double>();
  const auto& grid = plan_.grid;
  const double step = 0.25 * grid.spacing.minCoeff();
  // From the camera to beyond the grid's far side.
  const double far = (origin - plan_.tumor_centre).norm() +
                     grid_diagonal(grid);
  for (double t = 0; t < far; t += step) {
    const Eigen::Vector3d p = origin + t * dir;
    const auto n = grid.nearest_index(p);
    if (!grid.contains(n[0], n[1], n[2])) continue;
    if (context_.kinds(n[0], n[1], n[2]) != kOutside) return p;
  }
  return std::nullopt;
}

void PlanView3D::release_gl() {
  for (auto& old : retired_) old->release_gl();
  retired_.clear();
  for (auto& [value, r] : renderings_) r->release_gl();
}

}  // namespace crepuscular::overlay
