// Bead detection in a CT and Slicer point markups (see fiducials.hpp).
#include "planning/imaging/fiducials.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <optional>
#include <sstream>

#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/log.hpp"
#include "planning/imaging/itk_image.hpp"
#include "foundation/output_files.hpp"

namespace crepuscular::planning {
namespace {

struct Component {
  int64_t voxels = 0;
  Index3 lo{std::numeric_limits<int64_t>::max(), std::numeric_limits<int64_t>::max(),
            std::numeric_limits<int64_t>::max()};
  Index3 hi{-1, -1, -1};
  double peak = -std::numeric_limits<double>::infinity();
};

using MaskImage = itk::Image<uint8_t, 3>;

// 1 where the CT is at or above `threshold`, on the CT's grid; `above` counts those voxels.
template <typename T>
MaskImage::Pointer threshold_mask(const Volume<T>& ct, double threshold, int64_t& above) {
  const ImageGeometry& g = ct.geometry();
  auto mask = MaskImage::New();
  set_image_geometry(*mask, g);
  mask->Allocate();
  uint8_t* m = mask->GetBufferPointer();
  above = 0;
  for (int64_t o = 0; o < g.voxel_count(); ++o) {
    m[o] = double(ct[o]) >= threshold ? 1 : 0;
    above += m[o];
  }
  return mask;
}

// Voxel count, index bounding box and peak CT value of each fully connected component of `mask`,
// indexed by component label (entry 0, the background, stays empty).
template <typename T>
std::vector<Component> connected_components(const Volume<T>& ct, const MaskImage::Pointer& mask) {
  const ImageGeometry& g = ct.geometry();
  const ComponentLabels components = label_components(mask, true);
  const uint32_t* labels = components.image->GetBufferPointer();
  const size_t count = components.count;
  std::vector<Component> comps(count + 1);
  for (int64_t o = 0; o < g.voxel_count(); ++o) {
    const uint32_t l = labels[o];
    if (l == 0) continue;
    Component& c = comps[l];
    const Index3 idx = g.index_of_offset(o);
    ++c.voxels;
    for (int a = 0; a < 3; ++a) {
      c.lo[size_t(a)] = std::min(c.lo[size_t(a)], idx[size_t(a)]);
      c.hi[size_t(a)] = std::max(c.hi[size_t(a)], idx[size_t(a)]);
    }
    c.peak = std::max(c.peak, double(ct[o]));
  }
  return comps;
}

// Index box [lo, hi] (inclusive) around a component: its bounding box grown by the margin,
// clipped to the grid.
struct Window {
  Index3 lo, hi;
};

Window component_window(const Component& c, const ImageGeometry& g, int margin_voxels) {
  Window w;
  for (size_t a = 0; a < 3; ++a) {
    w.lo[a] = std::max<int64_t>(0, c.lo[a] - margin_voxels);
    w.hi[a] = std::min<int64_t>(g.dims[a] - 1, c.hi[a] + margin_voxels);
  }
  return w;
}

// Local background: median of the window's border voxels, at most `threshold`.
template <typename T>
double local_background(const Volume<T>& ct, const Window& w, double threshold) {
  std::vector<double> border;
  for (int64_t k = w.lo[2]; k <= w.hi[2]; ++k) {
    for (int64_t j = w.lo[1]; j <= w.hi[1]; ++j) {
      for (int64_t i = w.lo[0]; i <= w.hi[0]; ++i) {
        if (i == w.lo[0] || i == w.hi[0] || j == w.lo[1] || j == w.hi[1] || k == w.lo[2] ||
            k == w.hi[2]) {
          border.push_back(double(ct(i, j, k)));
        }
      }
    }
  }
  std::nth_element(border.begin(), border.begin() + long(border.size() / 2), border.end());
  return std::min(border[border.size() / 2], threshold);
}

// Sums over the window of the weights w = CT - background (voxels with w <= floor left out), of
// w x index and of w x (mm position)(mm position)^T.
struct Moments {
  double wsum = 0;
  Eigen::Vector3d first = Eigen::Vector3d::Zero();
  Eigen::Matrix3d second = Eigen::Matrix3d::Zero();
};

template <typename T>
Moments window_moments(const Volume<T>& ct, const Window& win, double background, double floor) {
  const Eigen::Matrix3d to_mm = ct.geometry().index_to_physical_matrix();
  Moments m;
  for (int64_t k = win.lo[2]; k <= win.hi[2]; ++k) {
    for (int64_t j = win.lo[1]; j <= win.hi[1]; ++j) {
      for (int64_t i = win.lo[0]; i <= win.hi[0]; ++i) {
        const double w = double(ct(i, j, k)) - background;
        if (w <= floor) continue;
        const Eigen::Vector3d x{double(i), double(j), double(k)};
        m.wsum += w;
        m.first += w * x;
        const Eigen::Vector3d xm = to_mm * x;
        m.second += w * xm * xm.transpose();
      }
    }
  }
  return m;
}

// Longest / shortest principal extent of the moments' spread about the centroid (mm). Extents of
// a single-voxel-thick component are bounded below by the voxel's own spread.
double elongation(const Moments& m, const ImageGeometry& g) {
  const Eigen::Matrix3d to_mm = g.index_to_physical_matrix();
  const Eigen::Vector3d mean_mm = to_mm * (m.first / m.wsum);
  const Eigen::Matrix3d cov = m.second / m.wsum - mean_mm * mean_mm.transpose();
  const Eigen::Vector3d ev = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(cov).eigenvalues();
  const double smallest =
      std::sqrt(std::max(ev(0), g.spacing.minCoeff() * g.spacing.minCoeff() / 12.0));
  return std::sqrt(std::max(ev(2), 0.0)) / smallest;
}

// The bead of one component: its intensity-weighted centroid (index space, over the window above
// the local background); nothing when its volume or its elongation rules it out.
template <typename T>
std::optional<Fiducial> measure_bead(const Volume<T>& ct, const Component& c,
                                     const FiducialDetectionOptions& options) {
  const ImageGeometry& g = ct.geometry();
  const double volume = double(c.voxels) * g.voxel_volume_mm3();
  if (volume < options.min_volume_mm3 || volume > options.max_volume_mm3) {
    spdlog::debug("fiducials: component of {:.1f} mm3 skipped (outside {}..{} mm3)", volume,
                  options.min_volume_mm3, options.max_volume_mm3);
    return std::nullopt;
  }
  const Window window = component_window(c, g, options.margin_voxels);
  const double background = local_background(ct, window, options.threshold);
  // Voxels of less than a fifth of the peak above the background are left out: a bead on the
  // skin has tissue beside it that the border median (air, mostly) would weigh in.
  const Moments m = window_moments(ct, window, background, 0.2 * (c.peak - background));
  if (m.wsum <= 0) return std::nullopt;
  const double stretch = elongation(m, g);
  if (stretch > options.max_elongation) {
    spdlog::debug("fiducials: component of {:.1f} mm3 skipped (elongation {:.1f})", volume,
                  stretch);
    return std::nullopt;
  }
  Fiducial f;
  f.position = g.index_to_physical(Eigen::Vector3d(m.first / m.wsum));
  f.volume_mm3 = volume;
  f.peak = c.peak;
  return f;
}

}  // namespace

template <typename T>
std::vector<Fiducial> detect_fiducials(const Volume<T>& ct,
                                       const FiducialDetectionOptions& options) {
  ct.geometry().validate("CT");
  int64_t above = 0;
  const MaskImage::Pointer mask = threshold_mask(ct, options.threshold, above);
  spdlog::debug("fiducials: {} voxels at or above {}", above, options.threshold);
  if (above == 0) return {};
  const std::vector<Component> comps = connected_components(ct, mask);
  std::vector<Fiducial> found;
  for (size_t l = 1; l < comps.size(); ++l) {
    if (const std::optional<Fiducial> f = measure_bead(ct, comps[l], options)) found.push_back(*f);
  }
  std::sort(found.begin(), found.end(),
            [](const Fiducial& a, const Fiducial& b) { return a.peak > b.peak; });
  for (size_t i = 0; i < found.size(); ++i) found[i].label = "B-" + std::to_string(i + 1);
  spdlog::info("fiducials: {} bead(s) found above {} ({} bright component(s) in all)", found.size(),
               options.threshold, comps.size() - 1);
  return found;
}

template std::vector<Fiducial> detect_fiducials(const Volume<int16_t>&,
                                                const FiducialDetectionOptions&);
template std::vector<Fiducial> detect_fiducials(const Volume<float>&,
                                                const FiducialDetectionOptions&);

std::vector<Fiducial> read_fiducial_markups(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) throw Error(path + ": cannot be opened");
  const nlohmann::json doc = read_json_file(path, "markups file");
  if (!doc.is_object() || !doc.contains("markups") || !doc["markups"].is_array()) {
    throw Error(path + ": field 'markups' is missing (expected a 3D Slicer .mrk.json file)");
  }
  std::vector<Fiducial> out;
  int point_lists = 0;
  for (size_t m = 0; m < doc["markups"].size(); ++m) {
    const nlohmann::json& markup = doc["markups"][m];
    const JsonPath where = JsonPath(path, "markups").index(m);
    if (!markup.is_object() || optional_string(markup, "type", where, "") != "Fiducial") continue;
    ++point_lists;
    const std::string cs = optional_string(markup, "coordinateSystem", where, "LPS");
    if (cs != "LPS" && cs != "RAS") {
      where.key("coordinateSystem").fail("is \"" + cs + "\" (expected \"LPS\" or \"RAS\")");
    }
    if (optional_string(markup, "coordinateUnits", where, "mm") != "mm") {
      where.key("coordinateUnits").fail("must be \"mm\"");
    }
    if (!markup.contains("controlPoints")) continue;
    const nlohmann::json& points = as_array(markup["controlPoints"], where.key("controlPoints"));
    for (size_t p = 0; p < points.size(); ++p) {
      const JsonPath pw = where.key("controlPoints").index(p);
      const std::vector<double> v = as_numbers(required_field(points[p], "position", pw),
                                               pw.key("position"), 3, 3, "three numbers (mm)");
      Fiducial f;
      f.position = Eigen::Vector3d(v[0], v[1], v[2]);
      if (cs == "RAS") {
        f.position.x() = -f.position.x();
        f.position.y() = -f.position.y();
      }
      f.label = optional_string(points[p], "label", pw, "F-" + std::to_string(out.size() + 1));
      out.push_back(f);
    }
  }
  if (point_lists == 0) {
    throw Error(path + ": no point list (markup of type \"Fiducial\") in field 'markups'");
  }
  return out;
}

void write_fiducial_markups(const std::string& path, const std::vector<Fiducial>& fiducials,
                            const std::string& coordinate_system) {
  if (coordinate_system != "LPS" && coordinate_system != "RAS") {
    throw Error("markups coordinate system \"" + coordinate_system + "\" (expected LPS or RAS)");
  }
  nlohmann::json points = nlohmann::json::array();
  for (size_t i = 0; i < fiducials.size(); ++i) {
    Eigen::Vector3d p = fiducials[i].position;
    if (coordinate_system == "RAS") {
      p.x() = -p.x();
      p.y() = -p.y();
    }
    points.push_back({{"id", std::to_string(i + 1)},
                      {"label", fiducials[i].label},
                      {"position", {p.x(), p.y(), p.z()}},
                      {"positionStatus", "defined"}});
  }
  const nlohmann::json doc = {
      {"@schema",
       "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
       "Schema/markups-schema-v1.0.0.json#"},
      {"markups",
       {{{"type", "Fiducial"},
         {"coordinateSystem", coordinate_system},
         {"coordinateUnits", "mm"},
         {"controlPoints", points}}}}};
  write_text_file(path, doc.dump(2) + "\n");
}

}  // namespace crepuscular::planning
