// The AprilTag families libapriltag knows, by name.
#include "tracking/tag_family.hpp"

#include <tag16h5.h>
#include <tag25h9.h>
#include <tag36h10.h>
#include <tag36h11.h>
#include <tagCircle21h7.h>
#include <tagCircle49h12.h>
#include <tagCustom48h12.h>
#include <tagStandard41h12.h>
#include <tagStandard52h13.h>

#include <vector>

#include "calibration/aruco.hpp"
#include "foundation/error.hpp"
#include "tracking/detector.hpp"

namespace crepuscular::tracking {

namespace {

// Kalibr's aprilgrid targets print tag36h11 with a black border 2 cells wide: the same codes,
// a detected square of 10 cells (6 data cells and two border cells on each side) in a white ring
// of 12. The data cells move one cell inward.
apriltag_family_t* tag36h11b2_create() {
  apriltag_family_t* f = tag36h11_create();
  f->width_at_border = 10;
  f->total_width = 12;
  for (uint32_t i = 0; i < f->nbits; ++i) {
    f->bit_x[i] += 1;
    f->bit_y[i] += 1;
  }
  return f;
}

struct FamilyEntry {
  const char* name;
  apriltag_family_t* (*create)();
  void (*destroy)(apriltag_family_t*);
};

constexpr FamilyEntry kFamilies[] = {
    {"tag36h11", tag36h11_create, tag36h11_destroy},
    {"tag36h11b2", tag36h11b2_create, tag36h11_destroy},  // Kalibr aprilgrid (2-cell border)
    {"tag36h10", tag36h10_create, tag36h10_destroy},
    {"tag25h9", tag25h9_create, tag25h9_destroy},
    {"tag16h5", tag16h5_create, tag16h5_destroy},
    {"tagCircle21h7", tagCircle21h7_create, tagCircle21h7_destroy},
    {"tagCircle49h12", tagCircle49h12_create, tagCircle49h12_destroy},
    {"tagStandard41h12", tagStandard41h12_create, tagStandard41h12_destroy},
    {"tagStandard52h13", tagStandard52h13_create, tagStandard52h13_destroy},
    {"tagCustom48h12", tagCustom48h12_create, tagCustom48h12_destroy},
};

}  // namespace

std::vector<std::string> tag_family_names() {
  std::vector<std::string> names;
  for (const FamilyEntry& f : kFamilies) names.emplace_back(f.name);
  for (const std::string& d : calibration::aruco_dictionary_names()) names.push_back(d);
  return names;
}

TagFamilyPtr open_tag_family(const std::string& name) {
  for (const FamilyEntry& f : kFamilies) {
    if (name == f.name) return TagFamilyPtr(f.create(), f.destroy);
  }
  std::string names;
  for (const std::string& f : tag_family_names()) names += " " + f;
  throw Error("tag family '" + name + "' is unknown; expected one of" + names);
}

}  // namespace crepuscular::tracking
