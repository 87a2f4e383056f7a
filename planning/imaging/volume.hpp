// Volume<T>: a 3D grid of values with its physical geometry (origin, spacing, direction, LPS mm).
// Every index <-> physical conversion of the project goes through ImageGeometry.
#pragma once

#include <Eigen/Core>
#include <Eigen/LU>
#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "foundation/large_buffers.hpp"

#include "foundation/error.hpp"

namespace crepuscular::planning {

using Index3 = std::array<int64_t, 3>;

// Geometry of a voxel grid. origin = physical position (LPS, mm) of the centre of voxel (0,0,0);
// spacing in mm along each index axis; direction: columns are the unit vectors of the index axes in
// LPS. physical = origin + direction * diag(spacing) * index.
struct ImageGeometry {
  Index3 dims{0, 0, 0};
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  Eigen::Vector3d spacing = Eigen::Vector3d::Ones();
  Eigen::Matrix3d direction = Eigen::Matrix3d::Identity();

  int64_t voxel_count() const { return dims[0] * dims[1] * dims[2]; }
  double voxel_volume_mm3() const { return spacing.prod(); }

  // Linear offset of voxel (i, j, k); i runs fastest (ITK / NIfTI order).
  int64_t offset(int64_t i, int64_t j, int64_t k) const { return i + dims[0] * (j + dims[1] * k); }
  Index3 index_of_offset(int64_t offset) const {
    return {offset % dims[0], (offset / dims[0]) % dims[1], offset / (dims[0] * dims[1])};
  }
  bool contains(int64_t i, int64_t j, int64_t k) const {
    return i >= 0 && j >= 0 && k >= 0 && i < dims[0] && j < dims[1] && k < dims[2];
  }

  // Index (continuous) -> physical point (LPS mm), and the 3x3 linear part of that map.
  Eigen::Matrix3d index_to_physical_matrix() const { return direction * spacing.asDiagonal(); }
  Eigen::Vector3d index_to_physical(const Eigen::Vector3d& index) const {
    return origin + index_to_physical_matrix() * index;
  }
  Eigen::Vector3d index_to_physical(int64_t i, int64_t j, int64_t k) const {
    return index_to_physical(Eigen::Vector3d(double(i), double(j), double(k)));
  }
  // Physical point -> continuous index (voxel centres at integers).
  Eigen::Vector3d physical_to_index(const Eigen::Vector3d& p) const {
    return index_to_physical_matrix().inverse() * (p - origin);
  }
  // Nearest voxel of a physical point (may lie outside the grid; check with contains()).
  Index3 nearest_index(const Eigen::Vector3d& p) const;

  // Throws Error naming `what` when dims, spacing or direction are unusable.
  void validate(const std::string& what) const;
  // Same grid (dims, and origin/spacing/direction within tol_mm / tol).
  bool same_grid(const ImageGeometry& other, double tol = 1e-6) const;
};

template <typename T>
class Volume {
 public:
  using value_type = T;

  Volume() = default;
  // Large volumes on huge pages where the system offers them (foundation/large_buffers.hpp).
  explicit Volume(const ImageGeometry& geometry, T fill = T{}) : geometry_(geometry) {
    assign_large(data_, size_t(geometry.voxel_count()), fill);
  }

  const ImageGeometry& geometry() const { return geometry_; }
  const Index3& dims() const { return geometry_.dims; }
  int64_t voxel_count() const { return geometry_.voxel_count(); }
  bool empty() const { return data_.empty(); }

  T& operator()(int64_t i, int64_t j, int64_t k) { return data_[size_t(geometry_.offset(i, j, k))]; }
  const T& operator()(int64_t i, int64_t j, int64_t k) const {
    return data_[size_t(geometry_.offset(i, j, k))];
  }
  T& operator[](int64_t offset) { return data_[size_t(offset)]; }
  const T& operator[](int64_t offset) const { return data_[size_t(offset)]; }

  T* data() { return data_.data(); }
  const T* data() const { return data_.data(); }
  std::vector<T>& values() { return data_; }
  const std::vector<T>& values() const { return data_; }

  // Geometry helpers forwarded for convenience.
  Eigen::Vector3d index_to_physical(int64_t i, int64_t j, int64_t k) const {
    return geometry_.index_to_physical(i, j, k);
  }
  Eigen::Vector3d physical_to_index(const Eigen::Vector3d& p) const {
    return geometry_.physical_to_index(p);
  }

 private:
  ImageGeometry geometry_;
  std::vector<T> data_;
};

// The smallest box of voxels [lo, hi] (inclusive) holding every voxel of a mask that is not 0;
// empty (hi < lo) when there is none. Found on every core, a row 8 bytes at a time: a full-size
// mask of a small tumor is searched in its box instead of voxel by voxel.
struct VoxelBox {
  Index3 lo{0, 0, 0}, hi{-1, -1, -1};
  bool empty() const { return hi[0] < lo[0]; }
  Index3 dims() const { return {hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1}; }
};
VoxelBox nonzero_box(const Volume<uint8_t>& mask);

}  // namespace crepuscular::planning
