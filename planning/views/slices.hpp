// 2D slice views of a plan (paper section 3.4, "area safety visualization"): the CT with a
// soft-tissue window, the path safety classes over it, outlines of labelled structures and of the
// tumor, and the area safety contour drawn as lines whose width and colour show the leeway;
// orientation letters, a scale bar and a legend. Images are plain RGB buffers written as PNG.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "planning/safety/area_safety.hpp"
#include "planning/safety/safety_classes.hpp"
#include "planning/imaging/volume.hpp"
#include "planning/views/palette.hpp"
#include "planning/preprocessing/vulnerability.hpp"

namespace crepuscular::planning {

enum class SlicePlaneKind { kAxial, kCoronal, kSagittal, kOblique };

const char* plane_name(SlicePlaneKind kind);
// "axial,coronal,sagittal,oblique" (any subset, any order); throws Error on an unknown name.
std::vector<SlicePlaneKind> parse_planes(const std::string& text);
// "safe,medium,dangerous" (any subset, or empty) -> hidden flags indexed by SafetyClass.
std::array<bool, 3> parse_hidden_classes(const std::string& text);

// An image plane in the patient. Pixel (x, y) of the view shows the point
// origin + x * pixel_mm * right + y * pixel_mm * down (LPS mm): x grows to the image right,
// y to the image bottom. Radiological convention: axial and coronal views show the patient's left
// (+L, LPS +x) on the image right; axial views have anterior at the top, coronal and sagittal views
// superior at the top; sagittal views have anterior on the left.
struct SlicePlane {
  SlicePlaneKind kind = SlicePlaneKind::kAxial;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();  // a point of the plane, LPS mm
  Eigen::Vector3d right = Eigen::Vector3d::UnitX();  // unit, image +x
  Eigen::Vector3d down = Eigen::Vector3d::UnitY();   // unit, image +y
  Eigen::Vector3d normal() const { return right.cross(down); }
};

// The plane of `kind` through `centre`. Oblique: the plane that contains `main_axis` (unit, e.g.
// a safe region's main axis, paper Fig. 9) and is closest to the standard plane in which that
// axis lies most: its image axes are those of that standard plane tilted to contain the axis.
SlicePlane make_slice_plane(SlicePlaneKind kind, const Eigen::Vector3d& centre,
                            const Eigen::Vector3d& main_axis = Eigen::Vector3d::Zero());

// Orientation letter(s) of a direction: L/R (x), P/A (y), S/I (z) in LPS; for oblique directions
// the letters of every component above 0.3, largest first (e.g. "LS").
std::string orientation_letters(const Eigen::Vector3d& direction);

// What a slice shows; pointers may be null (that layer is left out).
struct SliceScene {
  const Volume<float>* ct = nullptr;           // HU, required
  const Volume<float>* path_safety = nullptr;  // NaN outside the region of interest
  // Voxel states of the plan (planning/safety/unknown.hpp RegionState, roi.nii.gz): voxels in the
  // unknown state (2: outside the scan) are drawn as grey hatching, never in a class colour, and
  // the view grows to show them where they lie beyond the CT.
  const Volume<uint8_t>* region_state = nullptr;
  std::string value_name;                      // "svv", ... (legend)
  SafetyClasses classes;
  const Volume<int32_t>* labels = nullptr;
  const VulnerabilityTable* table = nullptr;  // names and levels for the legend
  const Volume<uint8_t>* tumor = nullptr;
  const AreaSafetyGeometry* area = nullptr;
  // A selected safe region: its main axis is drawn from the ellipsoid centre (dashed, white)
  // where it runs within 15 degrees of the view plane.
  const AreaRegion* region = nullptr;
};

struct SliceOptions {
  double window_width = 400;  // HU, soft tissue
  double window_level = 40;   // HU
  Palette palette = Palette::kDefault;
  std::array<bool, 3> hidden{false, false, false};  // by SafetyClass
  double overlay_opacity = 0.4;                     // path safety over the CT
  // Pixel size in mm; 0: the finest spacing of the CT and the path safety grid, divided by the
  // smallest integer that makes the view at least min_view_pixels wide (text stays legible).
  double pixel_mm = 0;
  int min_view_pixels = 512;
  double max_line_width_mm = 10;  // area safety line width at leeway 1 (paper: 1 cm)
  int legend_width = 300;         // pixels of the legend panel right of the view
};

// RGB image, row-major, 3 bytes per pixel.
struct RgbImage {
  int width = 0, height = 0;
  std::vector<uint8_t> rgb;
  std::array<uint8_t, 3> at(int x, int y) const {
    const size_t o = (size_t(y) * size_t(width) + size_t(x)) * 3;
    return {rgb[o], rgb[o + 1], rgb[o + 2]};
  }
};

struct SliceView {
  SlicePlane plane;
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();  // centre of view pixel (0, 0), LPS mm
  double pixel_mm = 1;
  int view_width = 0, view_height = 0;  // the view occupies image columns [0, view_width)
  RgbImage image;                       // view + legend panel
  std::vector<std::string> structures;  // names of the structures outlined in this view
  int contour_segments = 0;             // area safety contour segments drawn
  int64_t unknown_pixels = 0;           // view pixels drawn as unknown (hatched)

  // View pixel (continuous; pixel centres at integers) of a point projected onto the plane.
  Eigen::Vector2d pixel_of(const Eigen::Vector3d& p) const;
  Eigen::Vector3d point_of(double x, double y) const;
};

// Unknown voxels (outside the scan): diagonal lines of kUnknownHatchGrey, kUnknownHatchWidth
// pixels wide every kUnknownHatchPeriod pixels (pixels with (x + y) % period < width), over the CT
// (over black where the CT does not reach).
constexpr uint8_t kUnknownHatchGrey = 190;
constexpr int kUnknownHatchPeriod = 8;
constexpr int kUnknownHatchWidth = 2;
inline bool unknown_hatch_pixel(int x, int y) {
  return (x + y) % kUnknownHatchPeriod < kUnknownHatchWidth;
}

// Grey level of a CT value in the window (0..255).
uint8_t window_grey(double hu, double width, double level);

// Renders one view. The view covers the CT's extent projected onto the plane.
SliceView render_slice(const SliceScene& scene, const SlicePlane& plane,
                       const SliceOptions& options);

// Writes an RGB image as PNG through a temporary sibling; throws Error naming the path.
void write_png(const RgbImage& image, const std::string& path);

}  // namespace crepuscular::planning
