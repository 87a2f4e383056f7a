// Bead detection in a CT and Slicer point markups (see fiducials.hpp).
#include "planning/imaging/fiducials.hpp"

#include <itkConnectedComponentImageFilter.h>
#include <spdlog/spdlog.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>

#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
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

}  // namespace

template <typename T>
std::vector<Fiducial> detect_fiducials(const Volume<T>& ct, const FiducialDetectionOptions& options) {
  const ImageGeometry& g = ct.geometry();
  g.validate("CT");
  using MaskImage = itk::Image<uint8_t, 3>;
  using LabelImage = itk::Image<uint32_t, 3>;
  auto mask = MaskImage::New();
  set_image_geometry(*mask, g);
  mask->Allocate();
  uint8_t* m = mask->GetBufferPointer();
  int64_t above = 0;
  for (int64_t o = 0; o < g.voxel_count(); ++o) {
    m[o] = double(ct[o]) >= options.threshold ? 1 : 0;
    above += m[o];
  }
  spdlog::debug("fiducials: {} voxels at or above {}", above, options.threshold);
  if (above == 0) return {};
  auto cc = itk::ConnectedComponentImageFilter<MaskImage, LabelImage>::New();
  cc->SetInput(mask);
  cc->SetFullyConnected(true);
  cc->Update();
  const uint32_t* labels = cc->GetOutput()->GetBufferPointer();
  const size_t count = size_t(cc->GetObjectCount());
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
  const double voxel_mm3 = g.voxel_volume_mm3();
  const Eigen::Matrix3d to_mm = g.index_to_physical_matrix();
  std::vector<Fiducial> found;
  for (size_t l = 1; l <= count; ++l) {
    const Component& c = comps[l];
    const double volume = double(c.voxels) * voxel_mm3;
    if (volume < options.min_volume_mm3 || volume > options.max_volume_mm3) {
      spdlog::debug("fiducials: component of {:.1f} mm3 skipped (outside {}..{} mm3)", volume,
                    options.min_volume_mm3, options.max_volume_mm3);
      continue;
    }
    Index3 lo, hi;
    for (size_t a = 0; a < 3; ++a) {
      lo[a] = std::max<int64_t>(0, c.lo[a] - options.margin_voxels);
      hi[a] = std::min<int64_t>(g.dims[a] - 1, c.hi[a] + options.margin_voxels);
    }
    // Local background: median of the window's border voxels.
    std::vector<double> border;
    for (int64_t k = lo[2]; k <= hi[2]; ++k) {
      for (int64_t j = lo[1]; j <= hi[1]; ++j) {
        for (int64_t i = lo[0]; i <= hi[0]; ++i) {
          if (i == lo[0] || i == hi[0] || j == lo[1] || j == hi[1] || k == lo[2] || k == hi[2]) {
            border.push_back(double(ct(i, j, k)));
          }
        }
      }
    }
    std::nth_element(border.begin(), border.begin() + long(border.size() / 2), border.end());
    const double background = std::min(border[border.size() / 2], options.threshold);
    // Intensity-weighted centroid (index space) and second moments (mm) over the window.
    double wsum = 0;
    Eigen::Vector3d first = Eigen::Vector3d::Zero();
    Eigen::Matrix3d second = Eigen::Matrix3d::Zero();
    const double floor = 0.05 * (c.peak - background);
    for (int64_t k = lo[2]; k <= hi[2]; ++k) {
      for (int64_t j = lo[1]; j <= hi[1]; ++j) {
        for (int64_t i = lo[0]; i <= hi[0]; ++i) {
          const double w = double(ct(i, j, k)) - background;
          if (w <= floor) continue;
          const Eigen::Vector3d x{double(i), double(j), double(k)};
          wsum += w;
          first += w * x;
          const Eigen::Vector3d xm = to_mm * x;
          second += w * xm * xm.transpose();
        }
      }
    }
    if (wsum <= 0) continue;
    const Eigen::Vector3d centroid_index = first / wsum;
    const Eigen::Vector3d mean_mm = to_mm * centroid_index;
    const Eigen::Matrix3d cov = second / wsum - mean_mm * mean_mm.transpose();
    const Eigen::Vector3d ev = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(cov).eigenvalues();
    // Extents of a single-voxel-thick component are bounded below by the voxel's own spread.
    const double smallest = std::sqrt(std::max(ev(0), g.spacing.minCoeff() * g.spacing.minCoeff() / 12.0));
    const double elongation = std::sqrt(std::max(ev(2), 0.0)) / smallest;
    if (elongation > options.max_elongation) {
      spdlog::debug("fiducials: component of {:.1f} mm3 skipped (elongation {:.1f})", volume,
                    elongation);
      continue;
    }
    Fiducial f;
    f.position = g.index_to_physical(centroid_index);
    f.volume_mm3 = volume;
    f.peak = c.peak;
    found.push_back(f);
  }
  std::sort(found.begin(), found.end(),
            [](const Fiducial& a, const Fiducial& b) { return a.peak > b.peak; });
  for (size_t i = 0; i < found.size(); ++i) found[i].label = "B-" + std::to_string(i + 1);
  spdlog::info("fiducials: {} bead(s) found above {} ({} bright component(s) in all)", found.size(),
               options.threshold, count);
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
