// The registration job: fiducials on the board side and in the CT -> pairing and rigid fit ->
// registration.yaml with the FRE per fiducial and the expected TRE at the tumor.
#include "pipelines/registration.hpp"

#include <fstream>
#include <sstream>

#include "calibration/camera_model.hpp"
#include "calibration/registration.hpp"
#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "pipelines/session_inputs.hpp"
#include "planning/imaging/fiducials.hpp"
#include "planning/imaging/volume_io.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::pipelines {

namespace {

const tracking::Board& patient_board(const std::vector<tracking::Board>& boards,
                                     const std::string& name, const std::string& boards_path) {
  const tracking::Board* patient = nullptr;
  for (const auto& b : boards) {
    if (!name.empty() ? b.name == name
                      : (b.name == "patient" || (!patient && !b.fiducials.empty()))) {
      patient = &b;
    }
  }
  if (!patient) {
    throw Error(boards_path + ": no patient board" +
                (name.empty() ? std::string(" (a board named \"patient\" or with fiducials)")
                              : " named \"" + name + "\""));
  }
  return *patient;
}

// The fiducials in the board frame: a points file, digitised in a recording, or the board's own.
std::vector<Eigen::Vector3d> board_fiducials(const RegistrationRequest& a,
                                             const std::vector<tracking::Board>& boards,
                                             const tracking::Board& patient,
                                             const std::string& boards_path,
                                             std::vector<std::string>& inputs) {
  if (!a.points.empty()) {
    inputs.push_back(a.points);
    return read_points_csv(a.points);
  }
  if (!a.recording.empty()) {
    std::vector<Eigen::Vector3d> points = digitise_fiducials(a, boards, patient);
    inputs.push_back(a.recording);
    inputs.push_back(a.needle);
    return points;
  }
  if (patient.fiducials.size() < 3) {
    throw Error(boards_path + ": board \"" + patient.name + "\" lists " +
                std::to_string(patient.fiducials.size()) +
                " fiducials (at least 3 needed); add \"fiducials\", digitise them with the "
                "calibrated needle in a recording, or give their positions in a points file");
  }
  return patient.fiducials;
}

// The fiducials in the CT: Slicer markups, or beads found in the CT.
std::vector<planning::Fiducial> ct_fiducials(const RegistrationRequest& a,
                                             std::vector<std::string>& inputs) {
  std::vector<planning::Fiducial> found;
  if (!a.ct_fiducials.empty()) {
    found = planning::read_fiducial_markups(a.ct_fiducials);
    inputs.push_back(a.ct_fiducials);
  } else {
    spdlog::info("register: reading {}", a.ct);
    const planning::Volume<float> ct = planning::read_volume<float>(a.ct, {a.series});
    planning::FiducialDetectionOptions o;
    o.threshold = a.threshold_hu;
    found = planning::detect_fiducials(ct, o);
  }
  for (const auto& f : found) {
    spdlog::info("register: CT fiducial {} at ({:.2f}, {:.2f}, {:.2f}) LPS", f.label,
                 f.position.x(), f.position.y(), f.position.z());
  }
  if (!a.save_ct_fiducials.empty()) {
    planning::write_fiducial_markups(a.save_ct_fiducials, found);
    spdlog::info("register: CT fiducials written to {} (opens in 3D Slicer)", a.save_ct_fiducials);
  }
  return found;
}

calibration::RegistrationResult fit(const RegistrationRequest& a,
                                    const std::vector<Eigen::Vector3d>& board_points,
                                    const std::vector<Eigen::Vector3d>& ct_points) {
  calibration::RegistrationOptions ro;
  ro.distance_tolerance_mm = a.tolerance_mm;
  ro.inlier_mm = a.tolerance_mm;
  if (!a.in_order) return calibration::register_fiducials(board_points, ct_points, ro);
  if (ct_points.size() != board_points.size()) {
    throw Error("register: pairing in order needs as many CT fiducials (" +
                std::to_string(ct_points.size()) + ") as board fiducials (" +
                std::to_string(board_points.size()) + ")");
  }
  calibration::RegistrationResult r =
      calibration::register_paired_points(board_points, ct_points, ro);
  r.matched = int(board_points.size());
  return r;
}

// The pairs into the record, logged with their FRE; unmatched fiducials warned about.
void record_pairs(const calibration::RegistrationResult& r,
                  const std::vector<Eigen::Vector3d>& board_points,
                  const std::vector<planning::Fiducial>& ct, calibration::RegistrationRecord& rec) {
  for (size_t i = 0; i < board_points.size(); ++i) {
    if (r.match[i] < 0) {
      spdlog::warn("register: board fiducial {} at ({:.1f}, {:.1f}, {:.1f}) not found in the CT", i,
                   board_points[i].x(), board_points[i].y(), board_points[i].z());
      continue;
    }
    rec.board_fiducials.push_back(board_points[i]);
    rec.ct_fiducials.push_back(ct[size_t(r.match[i])].position);
    rec.fre_mm.push_back(r.fre_mm[i]);
    spdlog::info("register: board fiducial {} <-> CT {}: FRE {:.3f} mm", i,
                 ct[size_t(r.match[i])].label, r.fre_mm[i]);
  }
  for (int j : r.unmatched_ct) {
    spdlog::warn("register: CT fiducial {} matches no board fiducial (ignored)",
                 ct[size_t(j)].label);
  }
}

Eigen::Vector3d mask_centroid(const std::string& path, const std::vector<std::string>& series) {
  const planning::Volume<uint8_t> mask = planning::read_mask(path, {series});
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  int64_t count = 0;
  for (int64_t o = 0; o < mask.voxel_count(); ++o) {
    if (!mask[o]) continue;
    const planning::Index3 idx = mask.geometry().index_of_offset(o);
    sum += mask.index_to_physical(idx[0], idx[1], idx[2]);
    ++count;
  }
  if (count == 0) throw Error(path + ": tumor mask is empty (0 voxels > 0)");
  return sum / double(count);
}

// The expected TRE at the target (the point given, or the tumor's centroid).
void expected_tre(const RegistrationRequest& a, const calibration::RegistrationResult& r,
                  calibration::RegistrationRecord& rec) {
  if (a.target) {
    rec.target_ct = *a.target;
  } else if (!a.tumor.empty()) {
    rec.target_ct = mask_centroid(a.tumor, a.series);
    rec.inputs.push_back(a.tumor);
  }
  if (!rec.target_ct) {
    spdlog::info("register: give a tumor mask or a target point for the expected TRE there");
    return;
  }
  const double fle = a.fle_mm > 0 ? a.fle_mm : r.fle_mm;
  rec.expected_tre_mm = calibration::expected_tre_mm(rec.ct_fiducials, *rec.target_ct, fle);
  spdlog::info(
      "register: expected TRE {:.2f} mm at ({:.1f}, {:.1f}, {:.1f}) LPS (FLE {:.2f} mm "
      "{}, Fitzpatrick 1998)",
      rec.expected_tre_mm, rec.target_ct->x(), rec.target_ct->y(), rec.target_ct->z(), fle,
      a.fle_mm > 0 ? "given" : "estimated from the FRE");
}

}  // namespace

std::vector<Eigen::Vector3d> read_points_csv(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(path + ": cannot be opened");
  std::vector<Eigen::Vector3d> points;
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (line.empty() || line[0] == '#') continue;
    std::vector<std::string> fields;
    std::stringstream ss(line);
    std::string f;
    while (std::getline(ss, f, ',')) fields.push_back(f);
    if (fields.size() != 3 && fields.size() != 4) {
      throw Error(path + ":" + std::to_string(number) +
                  ": expected x,y,z or label,x,y,z (mm), found " + std::to_string(fields.size()) +
                  " fields");
    }
    const size_t first = fields.size() - 3;
    double v[3];
    bool numeric = true;
    for (int k = 0; k < 3; ++k) {
      try {
        size_t used = 0;
        v[k] = std::stod(fields[first + size_t(k)], &used);
      } catch (const std::exception&) {
        numeric = false;
      }
    }
    if (!numeric) {
      if (points.empty() && number == 1) continue;  // header
      throw Error(path + ":" + std::to_string(number) + ": coordinates are not numbers");
    }
    points.emplace_back(v[0], v[1], v[2]);
  }
  if (points.size() < 3) {
    throw Error(path + ": " + std::to_string(points.size()) +
                " point(s); at least 3 fiducial positions are needed");
  }
  return points;
}

std::vector<Eigen::Vector3d> digitise_fiducials(const RegistrationRequest& a,
                                                const std::vector<tracking::Board>& all,
                                                const tracking::Board& patient) {
  if (a.needle.empty()) {
    throw Error(
        "register: digitising fiducials in a recording needs the needle calibration "
        "(needle.yaml from `crepuscular calibrate pivot`)");
  }
  const calibration::NeedleCalibration needle = calibration::read_needle_calibration(a.needle);
  const std::string needle_board = needle.board.empty() ? "needle" : needle.board;
  std::vector<tracking::Board> boards = {patient};
  for (const auto& b : all) {
    if (b.name == needle_board) boards.push_back(b);
  }
  if (boards.size() < 2) {
    throw Error("register: the boards lack the needle board \"" + needle_board + "\" named in " +
                a.needle);
  }
  auto source = tracking::open_frame_source("recording:" + a.recording);
  const calibration::CameraModel camera = session_camera(a.camera, *source, "register");
  tracking::TrackerOptions o;
  o.detector.family = patient.family;
  o.smoothing = false;
  tracking::Tracker tracker(camera, boards, o);
  std::vector<Eigen::Vector3d> points, stretch;
  auto close_stretch = [&] {
    if (int(stretch.size()) >= a.still_frames) {
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      for (const auto& p : stretch) mean += p;
      mean /= double(stretch.size());
      bool repeat = false;
      for (const auto& q : points) repeat = repeat || (q - mean).norm() < 3.0 * a.still_mm;
      if (!repeat) {
        points.push_back(mean);
        spdlog::info(
            "register: fiducial digitised at ({:.2f}, {:.2f}, {:.2f}) in the patient "
            "frame ({} still frames)",
            mean.x(), mean.y(), mean.z(), stretch.size());
      }
    }
    stretch.clear();
  };
  while (auto frame = source->next()) {
    const tracking::TrackResult r = tracker.process(*frame);
    const tracking::BoardStatus* p = nullptr;
    const tracking::BoardStatus* n = nullptr;
    for (const auto& s : r.boards) {
      if (s.board == patient.name && s.measured) p = &s;
      if (s.board == needle_board && s.measured) n = &s;
    }
    if (!p || !n) {
      close_stretch();
      continue;
    }
    const Eigen::Vector3d tip = p->T_measured.inverse() * (n->T_measured * needle.tip_needle);
    if (!stretch.empty() && (tip - stretch.front()).norm() > a.still_mm) close_stretch();
    stretch.push_back(tip);
  }
  close_stretch();
  if (points.size() < 3) {
    throw Error("register: " + std::to_string(points.size()) + " fiducial(s) digitised in " +
                a.recording +
                " (at least 3 needed): hold the needle tip still on each fiducial "
                "for half a second with both boards in view");
  }
  return points;
}

calibration::RegistrationRecord run_registration(const RegistrationRequest& a) {
  if (!a.recording.empty() && !a.points.empty()) {
    throw Error("register: give at most one of a recording and a points file");
  }
  const std::string boards_path = session_boards_file(
      a.boards, a.recording.empty() ? std::string() : "recording:" + a.recording, "register");
  const std::vector<tracking::Board> boards = tracking::read_boards(boards_path);
  const tracking::Board& patient = patient_board(boards, a.board_name, boards_path);

  std::vector<std::string> inputs = {a.ct, boards_path};
  const std::vector<Eigen::Vector3d> board_points =
      board_fiducials(a, boards, patient, boards_path, inputs);
  const std::vector<planning::Fiducial> ct = ct_fiducials(a, inputs);
  std::vector<Eigen::Vector3d> ct_points;
  for (const auto& f : ct) ct_points.push_back(f.position);
  const calibration::RegistrationResult r = fit(a, board_points, ct_points);

  calibration::RegistrationRecord rec;
  rec.date = calibration::utc_timestamp();
  rec.inputs = inputs;
  rec.board = patient.name;
  rec.T_ct_patient = r.T_ct_patient;
  rec.fiducials_in_board = int(board_points.size());
  rec.fiducials_in_ct = int(ct_points.size());
  rec.fre_rms_mm = r.fre_rms_mm;
  rec.fle_mm = r.fle_mm;
  record_pairs(r, board_points, ct, rec);
  expected_tre(a, r, rec);
  calibration::write_registration(a.out, rec);
  spdlog::info("register: {} of {} fiducials paired, FRE RMS {:.3f} mm; {} written", r.matched,
               board_points.size(), r.fre_rms_mm, a.out);
  return rec;
}

}  // namespace crepuscular::pipelines
