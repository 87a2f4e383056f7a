// ImageGeometry: validation and nearest-voxel lookup.
#include "planning/imaging/volume.hpp"

#include <Eigen/LU>
#include <cmath>
#include <sstream>

namespace crepuscular::planning {

Index3 ImageGeometry::nearest_index(const Eigen::Vector3d& p) const {
  const Eigen::Vector3d idx = physical_to_index(p);
  return {int64_t(std::llround(idx.x())), int64_t(std::llround(idx.y())),
          int64_t(std::llround(idx.z()))};
}

void ImageGeometry::validate(const std::string& what) const {
  for (int a = 0; a < 3; ++a) {
    if (dims[a] <= 0) {
      std::ostringstream m;
      m << what << ": dimension " << a << " is " << dims[a] << " (expected > 0)";
      throw Error(m.str());
    }
    if (!std::isfinite(spacing[a]) || spacing[a] <= 0.0) {
      std::ostringstream m;
      m << what << ": spacing along axis " << a << " is " << spacing[a] << " mm (expected > 0)";
      throw Error(m.str());
    }
    if (!std::isfinite(origin[a])) {
      throw Error(what + ": origin is not finite");
    }
  }
  const double det = direction.determinant();
  if (!std::isfinite(det) || std::abs(std::abs(det) - 1.0) > 1e-3) {
    std::ostringstream m;
    m << what << ": direction matrix has determinant " << det << " (expected +-1, orthonormal)";
    throw Error(m.str());
  }
}

bool ImageGeometry::same_grid(const ImageGeometry& other, double tol) const {
  return dims == other.dims && (origin - other.origin).cwiseAbs().maxCoeff() <= tol &&
         (spacing - other.spacing).cwiseAbs().maxCoeff() <= tol &&
         (direction - other.direction).cwiseAbs().maxCoeff() <= tol;
}

}  // namespace crepuscular::planning
