// The marker boards and camera model of a tracking session: the files given, else the ones the
// frame source brings (a recording folder's boards.json and camera.yaml, a synthetic scene's
// camera). One rule for calibration, registration, tracking and guidance.
#pragma once

#include <string>

#include "calibration/camera_model.hpp"
#include "tracking/frame_source.hpp"

namespace crepuscular::pipelines {

// The boards file: `boards_file` when given, else the boards.json of a "recording:DIR" source
// when it has one. Throws Error (starting with `job`) when neither exists.
std::string session_boards_file(const std::string& boards_file, const std::string& source_uri,
                                const std::string& job);

// The camera model: read from `camera_file` when given, else the source's own. Throws Error
// (starting with `job`) when neither exists.
calibration::CameraModel session_camera(const std::string& camera_file,
                                        const tracking::FrameSource& source,
                                        const std::string& job);

}  // namespace crepuscular::pipelines
