// OpenIGTLink messages as Crepuscular sends them, packed by the reference library (header,
// body, CRC; protocol version 2): transforms in PLUS's ToolToReference naming (NeedleToCT,
// PatientToCT, NeedleTipToNeedle), the needle's safety as STRING, lost markers as STATUS, the
// target as POINT and the planned trajectory as TRAJ. Millimetres, LPS (the CT's frame).
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <string>

namespace crepuscular::igtlink {

struct Message {
  std::string type;   // "TRANSFORM", "STRING", ...
  std::string name;   // device name (at most 20 characters)
  std::string bytes;  // the packed message
};

// timestamp_ns: nanoseconds since the epoch of the source's clock (sec + nanosec on the wire).
Message transform_message(const std::string& name, const Eigen::Isometry3d& transform,
                          int64_t timestamp_ns);
Message string_message(const std::string& name, const std::string& text, int64_t timestamp_ns);
// code: igtl::StatusMessage codes (1 OK, 4 not found, 7 time out, ...).
Message status_message(const std::string& name, int code, const std::string& text,
                       int64_t timestamp_ns);
Message point_message(const std::string& name, const std::string& label,
                      const Eigen::Vector3d& position, int64_t timestamp_ns);
Message trajectory_message(const std::string& name, const std::string& label,
                           const Eigen::Vector3d& entry, const Eigen::Vector3d& target,
                           int64_t timestamp_ns);

constexpr int kStatusOk = 1;
constexpr int kStatusNotFound = 4;  // a marker not seen

}  // namespace crepuscular::igtlink
