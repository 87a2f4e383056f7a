// The AprilTag families libapriltag knows, by name: one table for the renderer's tag patterns and
// the detector. Internal to the tracking library (it includes libapriltag's header).
#pragma once

#include <apriltag.h>

#include <memory>
#include <string>

namespace crepuscular::tracking {

// A libapriltag family, destroyed with its own function.
using TagFamilyPtr = std::unique_ptr<apriltag_family_t, void (*)(apriltag_family_t*)>;

// Throws crepuscular::Error naming the known families and ArUco dictionaries when `name` is not
// a libapriltag family (ArUco dictionaries go through calibration/aruco.hpp).
TagFamilyPtr open_tag_family(const std::string& name);

}  // namespace crepuscular::tracking
