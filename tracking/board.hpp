// Marker boards: rigid sets of AprilTags with known corner positions (board frame, mm).
#pragma once

#include <Eigen/Core>
#include <array>
#include <string>
#include <vector>

namespace crepuscular::tracking {

struct BoardTag {
  int id = 0;
  // Corners in the board frame (mm), in libapriltag's order of apriltag_detection_t::p.
  std::array<Eigen::Vector3d, 4> corners;
};

struct Board {
  std::string name;                       // e.g. "patient", "needle"
  std::string family = "tag36h11";
  std::vector<BoardTag> tags;
  std::vector<Eigen::Vector3d> fiducials;  // CT-visible fiducials (patient board), board frame mm
};

// A planar grid of rows x cols tags of side tag_size_mm with gap_mm between them, ids from first_id,
// in the z = 0 plane of the board frame.
Board make_grid_board(const std::string& name, int rows, int cols, double tag_size_mm,
                      double gap_mm, int first_id);

// boards.json: {"boards": [ {...}, ... ]}. Errors name the file and the field.
std::vector<Board> read_boards(const std::string& path);
void write_boards(const std::string& path, const std::vector<Board>& boards);

}  // namespace crepuscular::tracking
