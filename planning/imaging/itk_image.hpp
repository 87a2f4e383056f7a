// ITK images on the grid of an ImageGeometry: the one place where our geometry becomes ITK's
// (origin, spacing, direction; both LPS). Internal to planning/.
#pragma once

#ifndef ITK_USE_SYSTEM_EIGEN
#define ITK_USE_SYSTEM_EIGEN  // one Eigen in every file: the system's, which volume.hpp includes
#endif
#include <itkImage.h>

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

}  // namespace crepuscular::planning
