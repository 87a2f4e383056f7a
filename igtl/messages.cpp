#include "igtl/messages.hpp"

#include <igtlPointMessage.h>
#include <igtlStatusMessage.h>
#include <igtlStringMessage.h>
#include <igtlTrajectoryMessage.h>
#include <igtlTransformMessage.h>

#include "foundation/error.hpp"

namespace crepuscular::igtlink {
namespace {

template <typename M>
void stamp(M& message, const std::string& name, int64_t timestamp_ns) {
  if (name.empty() || name.size() > 20) {
    throw Error("OpenIGTLink: device name \"" + name + "\" must have 1 to 20 characters");
  }
  message->SetDeviceName(name.c_str());
  igtl::TimeStamp::Pointer ts = igtl::TimeStamp::New();
  const int64_t ns = std::max<int64_t>(timestamp_ns, 0);
  ts->SetTime(igtlUint32(ns / 1000000000), igtlUint32(ns % 1000000000));
  message->SetTimeStamp(ts);
}

template <typename M>
Message packed(M& message) {
  message->Pack();
  return {message->GetDeviceType(), message->GetDeviceName(),
          std::string(static_cast<const char*>(message->GetPackPointer()),
                      size_t(message->GetPackSize()))};
}

}  // namespace

Message transform_message(const std::string& name, const Eigen::Isometry3d& transform,
                          int64_t timestamp_ns) {
  igtl::TransformMessage::Pointer m = igtl::TransformMessage::New();
  stamp(m, name, timestamp_ns);
  igtl::Matrix4x4 matrix;
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) matrix[r][c] = float(transform.matrix()(r, c));
  }
  m->SetMatrix(matrix);
  return packed(m);
}

Message string_message(const std::string& name, const std::string& text, int64_t timestamp_ns) {
  igtl::StringMessage::Pointer m = igtl::StringMessage::New();
  stamp(m, name, timestamp_ns);
  m->SetString(text.c_str());
  return packed(m);
}

Message status_message(const std::string& name, int code, const std::string& text,
                       int64_t timestamp_ns) {
  igtl::StatusMessage::Pointer m = igtl::StatusMessage::New();
  stamp(m, name, timestamp_ns);
  m->SetCode(code);
  m->SetSubCode(0);
  m->SetErrorName(code == kStatusOk ? "" : "marker lost");
  m->SetStatusString(text.c_str());
  return packed(m);
}

Message point_message(const std::string& name, const std::string& label,
                      const Eigen::Vector3d& position, int64_t timestamp_ns) {
  igtl::PointMessage::Pointer m = igtl::PointMessage::New();
  stamp(m, name, timestamp_ns);
  igtl::PointElement::Pointer e = igtl::PointElement::New();
  e->SetName(label.substr(0, 63).c_str());
  e->SetGroupName("Target");
  e->SetRGBA(255, 0, 255, 255);
  e->SetPosition(float(position.x()), float(position.y()), float(position.z()));
  e->SetRadius(2.0f);
  m->AddPointElement(e);
  return packed(m);
}

Message trajectory_message(const std::string& name, const std::string& label,
                           const Eigen::Vector3d& entry, const Eigen::Vector3d& target,
                           int64_t timestamp_ns) {
  igtl::TrajectoryMessage::Pointer m = igtl::TrajectoryMessage::New();
  stamp(m, name, timestamp_ns);
  igtl::TrajectoryElement::Pointer e = igtl::TrajectoryElement::New();
  e->SetName(label.substr(0, 63).c_str());
  e->SetGroupName("Planned");
  e->SetType(igtl::TrajectoryElement::TYPE_ENTRY_TARGET);
  e->SetRGBA(0, 200, 0, 255);
  e->SetEntryPosition(float(entry.x()), float(entry.y()), float(entry.z()));
  e->SetTargetPosition(float(target.x()), float(target.y()), float(target.z()));
  e->SetRadius(1.0f);
  m->AddTrajectoryElement(e);
  return packed(m);
}

}  // namespace crepuscular::igtlink
