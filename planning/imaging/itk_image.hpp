// ITK images and image files on the grid of an ImageGeometry: the one place where our geometry
// becomes ITK's and back (origin, spacing, direction; both LPS). Internal to planning/.
#pragma once

#ifndef ITK_USE_SYSTEM_EIGEN
#define ITK_USE_SYSTEM_EIGEN  // one Eigen in every file: the system's, which volume.hpp includes
#endif
#include <itkImage.h>
#include <itkImageIOBase.h>

#include <Eigen/Core>
#include <sstream>
#include <string>
#include <vector>

#include "foundation/error.hpp"
#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// Gives `image` the region, spacing, origin and direction of `g`; allocates nothing.
template <typename Image>
void set_image_geometry(Image& image, const ImageGeometry& g) {
  typename Image::SizeType size;
  typename Image::SpacingType spacing;
  typename Image::PointType origin;
  typename Image::DirectionType direction;
  for (unsigned a = 0; a < 3; ++a) {
    size[a] = itk::SizeValueType(g.dims[a]);
    spacing[a] = g.spacing[a];
    origin[a] = g.origin[a];
    for (unsigned r = 0; r < 3; ++r) direction[r][a] = g.direction(r, a);
  }
  image.SetRegions(typename Image::RegionType(size));
  image.SetSpacing(spacing);
  image.SetOrigin(origin);
  image.SetDirection(direction);
}

// Geometry checks beyond ImageGeometry::validate: the direction must be orthonormal (validate only
// looks at the determinant). Tolerance 1e-3 because NIfTI stores the direction in float32. Throws
// Error naming `path`.
inline void check_geometry(const ImageGeometry& g, const std::string& path) {
  g.validate(path);
  const double deviation =
      (g.direction.transpose() * g.direction - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (deviation > 1e-3) {
    std::ostringstream m;
    m.precision(10);
    m << path << ": direction cosines are not orthonormal (|D^T D - I| = " << deviation
      << ", expected < 0.001)";
    throw Error(m.str());
  }
}

// The grid of a file's first three axes as its ImageIO reports them (after ReadImageInformation),
// checked with check_geometry. The direction is read from the IO itself: for files with more than
// 3 axes ImageFileReader replaces it with the identity.
inline ImageGeometry geometry_of_image_io(const itk::ImageIOBase& io, const std::string& path) {
  ImageGeometry g;
  for (unsigned a = 0; a < 3; ++a) {
    g.dims[a] = int64_t(io.GetDimensions(a));
    g.spacing[a] = io.GetSpacing(a);
    g.origin[a] = io.GetOrigin(a);
    const std::vector<double> axis = io.GetDirection(a);
    for (unsigned r = 0; r < 3; ++r) g.direction(r, a) = r < axis.size() ? axis[r] : 0.0;
  }
  check_geometry(g, path);
  return g;
}

// The connected components of the nonzero voxels of `mask` (ITK's ConnectedComponentImageFilter):
// labels 1..count on the components, 0 elsewhere; 26-connected when `fully_connected`, else
// 6-connected. Throws itk::ExceptionObject. Defined in itk_image.cpp, so that the filter's template
// code is compiled once for every caller.
struct ComponentLabels {
  itk::Image<uint32_t, 3>::Pointer image;
  size_t count = 0;
};
ComponentLabels label_components(const itk::Image<uint8_t, 3>* mask, bool fully_connected);

}  // namespace crepuscular::planning
