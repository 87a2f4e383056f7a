// `crepuscular register`: the patient marker board's frame in the CT (T_ct_patient) from the
// board's CT-visible fiducials, found in the CT or read from Slicer markups.
#include <spdlog/spdlog.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "apps/commands.hpp"
#include "calibration/calibration_files.hpp"
#include "calibration/camera_model.hpp"
#include "calibration/registration.hpp"
#include "kernels/error.hpp"
#include "planning/fiducials.hpp"
#include "planning/volume_io.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::apps {

namespace {

namespace fs = std::filesystem;

struct RegisterArgs {
  std::string ct;
  std::string boards;
  std::string board_name;
  std::string ct_fiducials;
  std::string recording;
  std::string points;
  std::string needle;
  std::string camera;
  std::string tumor;
  std::vector<double> target;
  std::string save_ct_fiducials;
  std::string out = "registration.yaml";
  double threshold = 2500.0;
  double tolerance_mm = 2.0;
  double fle_mm = 0.0;
  double still_mm = 1.0;
  int still_frames = 10;
  bool in_order = false;
};

// Points of a CSV file: rows "x,y,z" or "label,x,y,z" (mm); a header row and lines starting with
// '#' are skipped.
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

// Fiducial positions in the patient board frame, digitised with the calibrated needle tip: every
// stretch of at least `still_frames` frames in which the tip (seen in the patient board's frame)
// stays within `still_mm` of where it began gives one point.
std::vector<Eigen::Vector3d> digitise(const RegisterArgs& a, const std::vector<tracking::Board>& all,
                                      const tracking::Board& patient) {
  if (a.needle.empty()) {
    throw Error("register: --recording digitises fiducials with the needle tip and needs "
                "--needle needle.yaml (from `crepuscular calibrate pivot`)");
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
  calibration::CameraModel camera;
  if (!a.camera.empty()) {
    camera = calibration::CameraModel::read_yaml(a.camera);
  } else if (auto c = source->camera()) {
    camera = *c;
  } else {
    throw Error("register: --camera is required (the recording brings no camera.yaml)");
  }
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
        spdlog::info("register: fiducial digitised at ({:.2f}, {:.2f}, {:.2f}) in the patient frame "
                     "({} still frames)",
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
                a.recording + " (at least 3 needed): hold the needle tip still on each fiducial "
                "for half a second with both boards in view");
  }
  return points;
}

void run_register(const RegisterArgs& a) {
  int sources = int(!a.recording.empty()) + int(!a.points.empty());
  if (sources > 1) throw Error("register: give at most one of --recording and --points");
  std::string boards_path = a.boards;
  if (boards_path.empty() && !a.recording.empty() && fs::exists(a.recording + "/boards.json")) {
    boards_path = a.recording + "/boards.json";
  }
  if (boards_path.empty()) throw Error("register: --boards is required");
  const std::vector<tracking::Board> boards = tracking::read_boards(boards_path);
  const tracking::Board* patient = nullptr;
  for (const auto& b : boards) {
    if (!a.board_name.empty() ? b.name == a.board_name
                              : (b.name == "patient" || (!patient && !b.fiducials.empty()))) {
      patient = &b;
    }
  }
  if (!patient) {
    throw Error(boards_path + ": no patient board" +
                (a.board_name.empty() ? std::string(" (a board named \"patient\" or with fiducials)")
                                      : " named \"" + a.board_name + "\""));
  }

  // Fiducials in the board frame.
  std::vector<Eigen::Vector3d> board_points;
  std::vector<std::string> inputs = {a.ct, boards_path};
  if (!a.points.empty()) {
    board_points = read_points_csv(a.points);
    inputs.push_back(a.points);
  } else if (!a.recording.empty()) {
    board_points = digitise(a, boards, *patient);
    inputs.push_back(a.recording);
    inputs.push_back(a.needle);
  } else {
    board_points = patient->fiducials;
    if (board_points.size() < 3) {
      throw Error(boards_path + ": board \"" + patient->name + "\" lists " +
                  std::to_string(board_points.size()) +
                  " fiducials (at least 3 needed); add \"fiducials\" or digitise them with "
                  "--recording and --needle, or give --points");
    }
  }

  // Fiducials in the CT.
  std::vector<planning::Fiducial> ct_fiducials;
  if (!a.ct_fiducials.empty()) {
    ct_fiducials = planning::read_fiducial_markups(a.ct_fiducials);
    inputs.push_back(a.ct_fiducials);
  } else {
    spdlog::info("register: reading {}", a.ct);
    const planning::Volume<float> ct = planning::read_volume<float>(a.ct);
    planning::FiducialDetectionOptions o;
    o.threshold = a.threshold;
    ct_fiducials = planning::detect_fiducials(ct, o);
  }
  for (const auto& f : ct_fiducials) {
    spdlog::info("register: CT fiducial {} at ({:.2f}, {:.2f}, {:.2f}) LPS", f.label,
                 f.position.x(), f.position.y(), f.position.z());
  }
  if (!a.save_ct_fiducials.empty()) {
    planning::write_fiducial_markups(a.save_ct_fiducials, ct_fiducials);
    spdlog::info("register: CT fiducials written to {} (opens in 3D Slicer)", a.save_ct_fiducials);
  }
  std::vector<Eigen::Vector3d> ct_points;
  for (const auto& f : ct_fiducials) ct_points.push_back(f.position);

  calibration::RegistrationOptions ro;
  ro.distance_tolerance_mm = a.tolerance_mm;
  ro.inlier_mm = a.tolerance_mm;
  calibration::RegistrationResult r;
  if (a.in_order) {
    if (ct_points.size() != board_points.size()) {
      throw Error("register: --in-order needs as many CT fiducials (" +
                  std::to_string(ct_points.size()) + ") as board fiducials (" +
                  std::to_string(board_points.size()) + ")");
    }
    r = calibration::register_paired_points(board_points, ct_points, ro);
    r.matched = int(board_points.size());
  } else {
    r = calibration::register_fiducials(board_points, ct_points, ro);
  }

  calibration::RegistrationRecord rec;
  rec.date = calibration::utc_timestamp();
  rec.inputs = inputs;
  rec.board = patient->name;
  rec.T_ct_patient = r.T_ct_patient;
  rec.fiducials_in_board = int(board_points.size());
  rec.fiducials_in_ct = int(ct_points.size());
  rec.fre_rms_mm = r.fre_rms_mm;
  rec.fle_mm = r.fle_mm;
  std::vector<Eigen::Vector3d> matched_ct;
  for (size_t i = 0; i < board_points.size(); ++i) {
    if (r.match[i] < 0) {
      spdlog::warn("register: board fiducial {} at ({:.1f}, {:.1f}, {:.1f}) not found in the CT", i,
                   board_points[i].x(), board_points[i].y(), board_points[i].z());
      continue;
    }
    rec.board_fiducials.push_back(board_points[i]);
    rec.ct_fiducials.push_back(ct_points[size_t(r.match[i])]);
    matched_ct.push_back(ct_points[size_t(r.match[i])]);
    rec.fre_mm.push_back(r.fre_mm[i]);
    spdlog::info("register: board fiducial {} <-> CT {}: FRE {:.3f} mm", i,
                 ct_fiducials[size_t(r.match[i])].label, r.fre_mm[i]);
  }
  for (int j : r.unmatched_ct) {
    spdlog::warn("register: CT fiducial {} matches no board fiducial (ignored)",
                 ct_fiducials[size_t(j)].label);
  }
  if (!a.target.empty()) {
    rec.target_ct = Eigen::Vector3d(a.target[0], a.target[1], a.target[2]);
  } else if (!a.tumor.empty()) {
    const planning::Volume<uint8_t> mask = planning::read_mask(a.tumor);
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    int64_t count = 0;
    for (int64_t o = 0; o < mask.voxel_count(); ++o) {
      if (!mask[o]) continue;
      const planning::Index3 idx = mask.geometry().index_of_offset(o);
      sum += mask.index_to_physical(idx[0], idx[1], idx[2]);
      ++count;
    }
    if (count == 0) throw Error(a.tumor + ": tumor mask is empty (0 voxels > 0)");
    rec.target_ct = sum / double(count);
    inputs.push_back(a.tumor);
    rec.inputs = inputs;
  }
  if (rec.target_ct) {
    const double fle = a.fle_mm > 0 ? a.fle_mm : r.fle_mm;
    rec.expected_tre_mm = calibration::expected_tre_mm(matched_ct, *rec.target_ct, fle);
    spdlog::info("register: expected TRE {:.2f} mm at ({:.1f}, {:.1f}, {:.1f}) LPS (FLE {:.2f} mm {}, "
                 "Fitzpatrick 1998)",
                 rec.expected_tre_mm, rec.target_ct->x(), rec.target_ct->y(), rec.target_ct->z(),
                 fle, a.fle_mm > 0 ? "given" : "estimated from the FRE");
  } else {
    spdlog::info("register: give --tumor MASK or --target X,Y,Z for the expected TRE there");
  }
  calibration::write_registration(a.out, rec);
  spdlog::info("register: {} of {} fiducials paired, FRE RMS {:.3f} mm; {} written", r.matched,
               board_points.size(), r.fre_rms_mm, a.out);
}

}  // namespace

void add_register_command(CLI::App& app) {
  auto a = std::make_shared<RegisterArgs>();
  CLI::App* cmd = app.add_subcommand(
      "register",
      "Register the patient marker board to the CT (T_ct_patient) by its CT-visible fiducials.\n"
      "Fiducials are paired by the board's known layout (any order; missing and extra ones are\n"
      "tolerated), fitted rigidly (closed form, then a robust refinement); reports the FRE per\n"
      "fiducial and the expected TRE at the tumor. Mirrored, collinear and symmetric\n"
      "configurations are refused.");
  cmd->add_option("--ct", a->ct, "The CT (NIfTI, NRRD, MetaImage or a DICOM folder), LPS mm")
      ->required();
  cmd->add_option("--boards", a->boards,
                  "Marker boards (boards.json) with the patient board's fiducials; default: the "
                  "recording's boards.json");
  cmd->add_option("--board-name", a->board_name,
                  "The patient board (default: the board named \"patient\", else the first with "
                  "fiducials)");
  cmd->add_option("--ct-fiducials", a->ct_fiducials,
                  "Fiducials placed in 3D Slicer (.mrk.json, LPS or RAS); default: beads found "
                  "automatically in the CT");
  cmd->add_option("--points", a->points,
                  "Fiducial positions in the patient board frame (CSV x,y,z or label,x,y,z, mm); "
                  "default: the board definition's");
  cmd->add_option("--recording", a->recording,
                  "A recording in which the calibrated needle tip rests on each fiducial in turn "
                  "(digitises their board-frame positions; needs --needle)");
  cmd->add_option("--needle", a->needle, "Needle calibration (needle.yaml) for --recording");
  cmd->add_option("--camera", a->camera,
                  "Camera model for --recording (default: the recording's camera.yaml)");
  cmd->add_option("--tumor", a->tumor, "Tumor mask: the expected TRE is given at its centroid");
  cmd->add_option("--target", a->target, "Or a point (LPS mm) for the expected TRE: --target=X,Y,Z")
      ->expected(3)
      ->delimiter(',');
  cmd->add_option("--fle-mm", a->fle_mm,
                  "Fiducial localisation error for the expected TRE (0: estimated from the FRE)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--threshold", a->threshold,
                  "Automatic bead detection: beads are brighter than this (HU)")
      ->capture_default_str();
  cmd->add_option("--tolerance-mm", a->tolerance_mm,
                  "Pairing tolerance: fiducial distances and fitted positions agree this well")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  cmd->add_option("--still-mm", a->still_mm,
                  "Digitising: the tip counts as resting while it stays within this distance")
      ->capture_default_str();
  cmd->add_option("--still-frames", a->still_frames,
                  "Digitising: frames the tip must rest to record a fiducial")
      ->capture_default_str();
  cmd->add_flag("--in-order", a->in_order,
                "Pair fiducials by their order (the CT list in the board's order) instead of by "
                "the layout: for symmetric layouts");
  cmd->add_option("--save-ct-fiducials", a->save_ct_fiducials,
                  "Also write the CT fiducials as a Slicer .mrk.json (to check them)");
  cmd->add_option("--out", a->out, "Registration file to write (YAML)")->capture_default_str();
  cmd->callback([a] { run_register(*a); });
}

}  // namespace crepuscular::apps
