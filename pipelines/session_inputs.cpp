// Boards and camera default to the source's own.
#include "pipelines/session_inputs.hpp"

#include <filesystem>

#include "foundation/error.hpp"

namespace crepuscular::pipelines {

std::string session_boards_file(const std::string& boards_file, const std::string& source_uri,
                                const std::string& job) {
  if (!boards_file.empty()) return boards_file;
  if (source_uri.rfind("recording:", 0) == 0) {
    const std::string beside = tracking::parse_source_uri(source_uri).path + "/boards.json";
    std::error_code ec;
    if (std::filesystem::exists(beside, ec)) return beside;
  }
  if (source_uri.empty()) throw Error(job + ": the marker boards (boards.json) are required");
  throw Error(job + ": the marker boards (boards.json) are required: the source " + source_uri +
              " brings none");
}

calibration::CameraModel session_camera(const std::string& camera_file,
                                        const tracking::FrameSource& source,
                                        const std::string& job) {
  if (!camera_file.empty()) return calibration::CameraModel::read_yaml(camera_file);
  if (auto c = source.camera()) return *c;
  throw Error(job + ": the camera model (camera.yaml) is required: the source " +
              source.describe() + " brings none");
}

}  // namespace crepuscular::pipelines
