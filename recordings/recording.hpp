// Recordings (docs/ARCHITECTURE.md §8): a folder of frames, their capture timestamps, camera.yaml
// and session.json. Written frame by frame so that a killed recorder leaves a replayable folder.
//
// Layout of a recording folder:
//   frames/000000.jpg ...   one image file per frame (JPEG or PNG), named by frame number
//   frames.csv              frame,timestamp_ns,file      (one row per complete frame)
//   camera.yaml             the camera model (OpenCV FileStorage YAML), written by the caller
//   session.json            {"format": "crepuscular-recording", "version": 1, "created", "source",
//                            "plan", "boards", "frame_count", "complete", ...}
//   ground_truth.csv        synthetic recordings only: frame,timestamp_ns,board,state,tx,ty,tz,
//                           qw,qx,qy,qz,rms_px (T_cam_board, mm; the pose CSV format)
//   boards.json             the marker boards seen (synthetic recordings), as tracking reads them
//
// Order of writing one frame: the image file (through a temporary name and a rename), then its
// ground-truth rows, then its frames.csv row, each flushed. A frames.csv row therefore always has
// its image and its truth; a killed writer leaves at most a partial last line, which the reader
// skips.
#pragma once

#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

// The full json.hpp: SessionInfo and RecordingReader hold JSON values.
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "foundation/csv.hpp"

namespace crepuscular::recordings {

// One row of a pose CSV (`crepuscular track --out`, ground_truth.csv): T_cam_board in mm with a
// unit quaternion (w, x, y, z); state "tracked" or "lost"; rms_px the reprojection RMS (0 for truth).
struct PoseRow {
  int64_t frame = 0;
  int64_t timestamp_ns = 0;
  std::string board;
  std::string state = "tracked";
  double t[3] = {0, 0, 0};
  double q[4] = {1, 0, 0, 0};
  double rms_px = 0;
};

// "frame,timestamp_ns,board,state,tx,ty,tz,qw,qx,qy,qz,rms_px"
extern const char* const kPoseCsvHeader;
// One CSV line without the newline (mm to 1e-6, quaternion to 1e-12).
std::string format_pose_row(const PoseRow& row);
// One row from its fields (split_csv_line): 12 fields, integer frame and timestamp, state
// "tracked" with numbers in every pose field, or "lost" (pose fields empty or numbers).
// Throws Error "PATH: line N: ..." naming the column.
PoseRow parse_pose_row(const std::vector<std::string>& fields, const CsvLocation& at);

struct PoseCsv {
  std::vector<PoseRow> rows;
  std::vector<std::string> problems;  // rows skipped, each naming the file and line
};
// Reads a pose CSV; malformed or incomplete rows are skipped with a problem. Throws Error when the
// file cannot be opened or its header is not kPoseCsvHeader.
PoseCsv read_pose_csv(const std::string& path);

struct SessionInfo {
  std::string source;                        // where the frames came from (a frame source URI)
  std::string plan;                          // the plan folder this session belongs to, if any
  nlohmann::json boards = nlohmann::json();  // boards.json content ({"boards": [...]}) or null
  nlohmann::json extra = nlohmann::json::object();  // further fields to keep in session.json
};

// Writes a recording folder frame by frame. The folder must not exist or be empty.
class RecordingWriter {
 public:
  // image_format: "jpg" or "png"; jpeg_quality 1..100. Writes session.json at once
  // ("complete": false), so an interrupted recording is described too.
  RecordingWriter(const std::string& dir, const SessionInfo& session,
                  const std::string& image_format = "jpg", int jpeg_quality = 95,
                  bool with_ground_truth = false);
  ~RecordingWriter();
  RecordingWriter(const RecordingWriter&) = delete;
  RecordingWriter& operator=(const RecordingWriter&) = delete;

  const std::string& dir() const { return dir_; }

  // Encodes `image` (8-bit BGR or grey) in the recording's format and appends it as frame `frame`
  // (frame numbers must increase; gaps mean dropped frames). truth: ground-truth rows of this
  // frame (frame and timestamp are filled in). Throws Error on a write failure.
  void add_frame(int64_t frame, int64_t timestamp_ns, const cv::Mat& image,
                 const std::vector<PoseRow>& truth = {});
  // Appends already encoded bytes (e.g. a camera's MJPEG frame, corrupt ones included) with the
  // file extension `ext` ("jpg" or "png").
  void add_encoded(int64_t frame, int64_t timestamp_ns, const std::vector<uint8_t>& bytes,
                   const std::string& ext, const std::vector<PoseRow>& truth = {});

  int64_t frame_count() const { return count_; }

  // Rewrites session.json with "complete": true and the frame count; closes the CSV files.
  void finish();

 private:
  void write_session(bool complete);
  void append_row(int64_t frame, int64_t timestamp_ns, const std::string& file,
                  const std::vector<PoseRow>& truth);

  std::string dir_;
  SessionInfo session_;
  std::string format_;
  int quality_;
  bool with_truth_;
  std::string created_;
  std::FILE* frames_csv_ = nullptr;
  std::FILE* truth_csv_ = nullptr;
  int64_t count_ = 0;
  int64_t last_frame_ = -1;
  bool finished_ = false;
};

// Reads a recording folder, complete or interrupted.
class RecordingReader {
 public:
  struct Entry {
    int64_t frame = 0;
    int64_t timestamp_ns = 0;
    std::string file;  // relative to the folder
  };
  struct Loaded {
    cv::Mat image;                // BGR 8-bit; empty when the file is missing or cannot be decoded
    std::vector<uint8_t> bytes;   // the file's bytes as stored
    std::string problem;          // why image is empty
  };

  // Throws Error when the folder or its frames.csv is missing or frames.csv has the wrong header.
  explicit RecordingReader(const std::string& dir);

  const std::string& dir() const { return dir_; }
  // Complete rows of frames.csv, in order.
  const std::vector<Entry>& entries() const { return entries_; }
  // Things skipped while opening (incomplete or malformed rows, missing session.json, ...).
  const std::vector<std::string>& problems() const { return problems_; }
  // session.json (null when missing or unreadable: then problems() says so).
  const nlohmann::json& session() const { return session_; }
  // Path of camera.yaml, or "" when the recording has none.
  std::string camera_path() const;
  // Path of boards.json, or "" when the recording has none.
  std::string boards_path() const;
  bool has_ground_truth() const { return has_truth_; }
  // Ground-truth rows of one frame (empty when there are none).
  std::vector<PoseRow> ground_truth(int64_t frame) const;

  // Reads and decodes entry i; a missing or corrupt file gives an empty image and a problem.
  Loaded load(size_t i) const;

 private:
  std::string dir_;
  std::vector<Entry> entries_;
  std::vector<std::string> problems_;
  nlohmann::json session_;
  bool has_truth_ = false;
  std::vector<PoseRow> truth_;  // sorted by frame
};

// Decodes a JPEG or PNG image to 8-bit BGR (16-bit PNGs, e.g. TUM VI's, as to_8bit_by_range maps
// them). A truncated JPEG (no end-of-image marker), an empty buffer or undecodable bytes give an
// empty Mat and set *problem; never throws.
cv::Mat decode_image(const std::vector<uint8_t>& bytes, std::string* problem);

// An 8-bit image as it is; a 16-bit one (any channels) mapped linearly from its own range (the
// 0.01 % to 99.99 % quantiles of its values, so a few hot pixels do not matter) to 0..255,
// saturating beyond: 10- or 12-bit data in 16-bit words keep their contrast.
cv::Mat to_8bit_by_range(const cv::Mat& image);

}  // namespace crepuscular::recordings
