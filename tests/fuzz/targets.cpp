#include "tests/fuzz/targets.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <thread>

#include "calibration/calibration_files.hpp"
#include "calibration/camera_model.hpp"
#include "foundation/error.hpp"
#include "igtl/pose_receiver.hpp"
#include "planning/imaging/fiducials.hpp"
#include "planning/imaging/segmentation.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "planning/preprocessing/vulnerability.hpp"
#include "planning/safety/area_safety.hpp"
#include "planning/trajectories/evaluate.hpp"
#include "planning/trajectories/markups.hpp"
#include "recordings/plus_sequence.hpp"
#include "recordings/recording.hpp"
#include "tracking/board.hpp"
#include "tracking/poses_csv.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::fuzz {
namespace {

namespace fs = std::filesystem;

void read_float_volume(const std::string& path) { planning::read_volume<float>(path); }
void read_label_map(const std::string& path) { planning::read_label_map(path); }

// A volume or, for a 4D file, its phases split into 3D files beside it (at most 8).
void read_volume_or_phases(const std::string& path) {
  const int frames = planning::volume_frames(path);
  if (frames == 1) {
    planning::read_volume<float>(path);
    return;
  }
  if (frames > 8) throw Error(path + ": more than 8 phases (not fuzzed)");
  std::vector<std::string> phases;
  for (int t = 0; t < frames; ++t) {
    phases.push_back((fs::path(path).parent_path() / ("phase" + std::to_string(t) + ".nii")).string());
  }
  planning::split_volume_frames(path, phases);
}

// The input's parts between kSliceMark (tests/fuzz/make_seeds.py) become the slice files of a
// DICOM folder beside it (at most 16), read with series 2.25.99001 chosen.
void read_dicom_folder(const std::string& path) {
  static const std::string kSliceMark = "#SLICE#\n";
  std::ifstream in(path, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const fs::path folder = fs::path(path).parent_path() / "series";
  fs::create_directory(folder);
  size_t start = 0;
  for (int k = 0; k < 16; ++k) {
    const size_t mark = bytes.find(kSliceMark, start);
    std::ofstream out(folder / ("slice" + std::to_string(k) + ".dcm"), std::ios::binary);
    out << bytes.substr(start, mark == std::string::npos ? std::string::npos : mark - start);
    if (mark == std::string::npos) break;
    start = mark + kSliceMark.size();
  }
  planning::read_volume<float>(folder.string(), {{"2.25.99001"}});
}

void read_recording(const std::string& path) {
  recordings::RecordingReader reader(fs::path(path).parent_path().string());
  const size_t n = std::min<size_t>(reader.entries().size(), 4);
  for (size_t i = 0; i < n; ++i) reader.load(i);
  if (reader.has_ground_truth() && !reader.entries().empty()) {
    reader.ground_truth(reader.entries().front().frame);
  }
}

using PoseReceiverStats = igtlink::PoseReceiver::Stats;

// An OpenIGTLink stream from a tracking server: the file's bytes sent to a receiver listening on
// a local port, then the connection closed; returns once the receiver is done with it.
void read_igtl_stream(const std::string& path) {
  static igtlink::PoseReceiver receiver("igtl-server:0");
  std::ifstream in(path, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const int64_t before = receiver.stats().ended, dropped = receiver.stats().dropped;
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(uint16_t(receiver.port()));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0) {
    ::close(fd);
    throw Error("igtl stream: cannot connect to the receiver");
  }
  size_t sent = 0;
  while (sent < bytes.size()) {
    const ssize_t n = ::send(fd, bytes.data() + sent, bytes.size() - sent, MSG_NOSIGNAL);
    if (n <= 0) break;  // the receiver dropped the connection: a malformed message
    sent += size_t(n);
  }
  ::close(fd);
  while (receiver.stats().ended == before) std::this_thread::sleep_for(std::chrono::microseconds(50));
  // A malformed message dropped the connection: the stream was refused, with its reason.
  const PoseReceiverStats after = receiver.stats();
  if (after.dropped != dropped) throw Error(path + ": " + after.last_problem);
}

void read_plan_json(const std::string& path) {
  planning::PlanLoadOptions only_the_json;
  only_the_json.blocking = false;
  only_the_json.path_safety = false;
  only_the_json.labels = false;
  only_the_json.tumor = false;
  only_the_json.area_safety = false;
  planning::load_plan(fs::path(path).parent_path().string(), only_the_json);
}

// The scratch folder of this process, emptied of what an earlier input left (frames, ...), and
// removed when the process exits. The path is never destroyed: a static path object would be
// destroyed before the exit handler that removes the folder runs (it is registered while the
// object is made, so it runs after the object's destructor), and that handler would then hand
// freed memory to remove_all as a path.
const fs::path& scratch_folder() {
  static const fs::path* const folder = [] {
    auto* p = new fs::path(fs::temp_directory_path() /
                           ("crepuscular-fuzz-" + std::to_string(getpid())));
    fs::remove_all(*p);
    fs::create_directories(*p);
    std::atexit([] { std::error_code ignored; fs::remove_all(*folder, ignored); });
    return p;
  }();
  return *folder;
}

}  // namespace

const std::vector<FuzzTarget>& fuzz_targets() {
  static const std::vector<FuzzTarget> targets = {
      {"nifti", "image.nii", read_float_volume},
      {"nifti_gz", "image.nii.gz", read_volume_or_phases},
      {"dicom_series", "slices.bin", read_dicom_folder},
      {"nrrd", "image.nrrd", read_float_volume},
      {"metaimage", "image.mha", read_label_map},
      {"segmentation", "segmentation.seg.nrrd",
       [](const std::string& path) { planning::read_segmentation(path); }},
      {"vulnerability", "vulnerability.json",
       [](const std::string& path) { planning::VulnerabilityTable::load(path); }},
      {"boards", "boards.json", [](const std::string& path) { tracking::read_boards(path); }},
      {"scene", "scene.json", [](const std::string& path) { tracking::read_scene(path); }},
      {"camera_yaml", "camera.yaml",
       [](const std::string& path) { calibration::CameraModel::read_yaml(path); }},
      {"needle_yaml", "needle.yaml",
       [](const std::string& path) { calibration::read_needle_calibration(path); }},
      {"registration_yaml", "registration.yaml",
       [](const std::string& path) { calibration::read_registration(path); }},
      {"frames_csv", "frames.csv", read_recording},
      {"truth_csv", "truth.csv", [](const std::string& path) { recordings::read_pose_csv(path); }},
      {"poses_csv", "poses.csv", [](const std::string& path) { tracking::read_poses_csv(path); }},
      {"line_markup", "line.mrk.json",
       [](const std::string& path) { planning::read_line_markup(path); }},
      {"fiducial_markups", "fiducials.mrk.json",
       [](const std::string& path) { planning::read_fiducial_markups(path); }},
      {"batch_csv", "trajectories.csv",
       [](const std::string& path) { planning::read_trajectories_csv(path); }},
      {"plan_json", "plan.json", read_plan_json},
      {"area_mesh", "area_safety.vtk",
       [](const std::string& path) { planning::read_area_safety_vtk(path); }},
      {"igtl_stream", "stream.igtl", read_igtl_stream},
      {"plus_sequence", "sequence.igs.mha",
       [](const std::string& path) { recordings::read_plus_sequence(path); }},
  };
  return targets;
}

const FuzzTarget* find_fuzz_target(const std::string& name) {
  for (const FuzzTarget& target : fuzz_targets()) {
    if (name == target.name) return &target;
  }
  return nullptr;
}

std::string run_fuzz_input(const FuzzTarget& target, const uint8_t* data, size_t size) {
  const fs::path& folder = scratch_folder();
  for (const auto& entry : fs::directory_iterator(folder)) fs::remove_all(entry.path());
  const fs::path path = folder / target.file_name;
  {
    std::ofstream out(path, std::ios::binary);
    out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
  }
  try {
    target.read(path.string());
    return "";
  } catch (const Error& e) {
    return e.what();  // refused with a message naming the file: what bad input must get
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz %s: not a crepuscular::Error escaped the reader: %s\n", target.name,
                 e.what());
    std::abort();
  } catch (...) {
    std::fprintf(stderr, "fuzz %s: an unknown exception escaped the reader\n", target.name);
    std::abort();
  }
}

}  // namespace crepuscular::fuzz
