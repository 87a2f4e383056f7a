// Recording folders: frame-by-frame writer that survives being killed, and a reader that replays
// whatever complete frames a folder holds.
#include "recordings/recording.hpp"

#include <csetjmp>
#include <cstdio>

#include <jpeglib.h>

#include <unistd.h>

#include <algorithm>
#include <cinttypes>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <fmt/format.h>

#include <opencv2/imgcodecs.hpp>

#include "foundation/csv.hpp"
#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "foundation/text.hpp"

namespace crepuscular::recordings {

namespace fs = std::filesystem;

const char* const kPoseCsvHeader = "frame,timestamp_ns,board,state,tx,ty,tz,qw,qx,qy,qz,rms_px";

namespace {

constexpr const char* kFramesHeader = "frame,timestamp_ns,file";

// Lines of a text file. `incomplete` is set when the last line lacks its newline (a writer was
// interrupted in the middle of it); that line is not returned.
std::vector<std::string> read_lines(const std::string& path, bool* incomplete) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path + ": cannot open");
  std::stringstream buffer;
  buffer << in.rdbuf();
  const std::string text = buffer.str();
  std::vector<std::string> lines;
  size_t start = 0;
  *incomplete = false;
  while (start < text.size()) {
    const size_t nl = text.find('\n', start);
    if (nl == std::string::npos) {
      *incomplete = true;
      break;
    }
    std::string line = text.substr(start, nl - start);
    if (!line.empty() && line.back() == '\r') line.pop_back();
    lines.push_back(line);
    start = nl + 1;
  }
  return lines;
}

bool is_jpeg(const std::vector<uint8_t>& b) {
  return b.size() >= 3 && b[0] == 0xFF && b[1] == 0xD8 && b[2] == 0xFF;
}

}  // namespace

std::string format_pose_row(const PoseRow& r) {
  return fmt::format("{},{},{},{},{:.6f},{:.6f},{:.6f},{:.12f},{:.12f},{:.12f},{:.12f},{:.4f}",
                     r.frame, r.timestamp_ns, r.board, r.state, r.t[0], r.t[1], r.t[2], r.q[0],
                     r.q[1], r.q[2], r.q[3], r.rms_px);
}

PoseRow parse_pose_row(const std::vector<std::string>& f, const CsvLocation& at) {
  if (f.size() != 12) {
    throw Error(at.describe() + ": " + std::to_string(f.size()) + " fields, expected 12 (" +
                kPoseCsvHeader + ")");
  }
  PoseRow r;
  r.frame = csv_int64(f[0], "frame", at);
  r.timestamp_ns = csv_int64(f[1], "timestamp_ns", at);
  r.board = f[2];
  r.state = f[3];
  const bool lost = r.state == "lost";
  if (!lost && r.state != "tracked") {
    throw Error(at.describe() + ": state '" + r.state + "', expected tracked or lost");
  }
  // Pose fields: numbers; a lost row may leave them empty (then they keep their defaults).
  static const char* const kNames[8] = {"tx", "ty", "tz", "qw", "qx", "qy", "qz", "rms_px"};
  double* const values[8] = {&r.t[0], &r.t[1], &r.t[2], &r.q[0],
                             &r.q[1], &r.q[2], &r.q[3], &r.rms_px};
  for (size_t k = 0; k < 8; ++k) {
    if (lost && f[4 + k].empty()) continue;
    *values[k] = csv_double(f[4 + k], kNames[k], at);
  }
  return r;
}

PoseCsv read_pose_csv(const std::string& path) {
  bool incomplete = false;
  const std::vector<std::string> lines = read_lines(path, &incomplete);
  PoseCsv out;
  check_csv_header(path, lines.empty() ? std::string() : lines[0], kPoseCsvHeader);
  for (size_t i = 1; i < lines.size(); ++i) {
    if (lines[i].empty()) continue;
    try {
      out.rows.push_back(parse_pose_row(split_csv_line(lines[i]), {path, int64_t(i + 1)}));
    } catch (const Error& e) {
      out.problems.push_back(std::string(e.what()) + "; row skipped");
    }
  }
  if (incomplete) {
    out.problems.push_back(path + ": last line is incomplete (interrupted writer), skipped");
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// Writer

RecordingWriter::RecordingWriter(const std::string& dir, const SessionInfo& session,
                                 const std::string& image_format, int jpeg_quality,
                                 bool with_ground_truth)
    : dir_(dir),
      session_(session),
      format_(image_format),
      quality_(jpeg_quality),
      with_truth_(with_ground_truth) {
  if (format_ != "jpg" && format_ != "png") {
    throw Error(dir + ": image format '" + format_ + "' is not supported, expected jpg or png");
  }
  if (quality_ < 1 || quality_ > 100) {
    throw Error(dir + ": JPEG quality " + std::to_string(quality_) + ", expected 1 to 100");
  }
  std::error_code ec;
  if (fs::exists(dir_) && !fs::is_empty(dir_, ec)) {
    throw Error(dir_ + ": recording folder exists and is not empty; choose another folder");
  }
  fs::create_directories(fs::path(dir_) / "frames", ec);
  if (ec) throw Error(dir_ + ": cannot create recording folder (" + ec.message() + ")");
  created_ = utc_now_iso8601();
  if (!session_.boards.is_null()) {
    write_text_file((fs::path(dir_) / "boards.json").string(), session_.boards.dump(2) + "\n");
  }
  write_session(false);
  const std::string frames_path = (fs::path(dir_) / "frames.csv").string();
  frames_csv_ = std::fopen(frames_path.c_str(), "wb");
  if (!frames_csv_) throw Error(frames_path + ": cannot write");
  std::fprintf(frames_csv_, "%s\n", kFramesHeader);
  std::fflush(frames_csv_);
  if (with_ground_truth) {
    const std::string truth_path = (fs::path(dir_) / "ground_truth.csv").string();
    truth_csv_ = std::fopen(truth_path.c_str(), "wb");
    if (!truth_csv_) throw Error(truth_path + ": cannot write");
    std::fprintf(truth_csv_, "%s\n", kPoseCsvHeader);
    std::fflush(truth_csv_);
  }
}

RecordingWriter::~RecordingWriter() {
  if (frames_csv_) std::fclose(frames_csv_);
  if (truth_csv_) std::fclose(truth_csv_);
}

void RecordingWriter::write_session(bool complete) {
  nlohmann::json s = session_.extra.is_object() ? session_.extra : nlohmann::json::object();
  s["format"] = "crepuscular-recording";
  s["version"] = 1;
  s["created"] = created_;
  // Final paths, never those of a folder still staged (the demo's plan and scene).
  const size_t colon = session_.source.find(':');
  s["source"] = colon == std::string::npos
                    ? session_.source
                    : session_.source.substr(0, colon + 1) +
                          final_path_of(session_.source.substr(colon + 1));
  s["plan"] = session_.plan.empty() ? session_.plan : final_path_of(session_.plan);
  s["boards"] = session_.boards.is_null() ? nlohmann::json::array()
                                          : session_.boards.value("boards", nlohmann::json::array());
  s["frames"] = {{"file", "frames.csv"}, {"image_format", format_}};
  s["ground_truth"] = with_truth_ ? "ground_truth.csv" : "";
  s["frame_count"] = count_;
  s["complete"] = complete;
  write_text_file((fs::path(dir_) / "session.json").string(), s.dump(2) + "\n");
}

void RecordingWriter::add_frame(int64_t frame, int64_t timestamp_ns, const cv::Mat& image,
                                const std::vector<PoseRow>& truth) {
  if (image.empty()) throw Error(dir_ + ": frame " + std::to_string(frame) + " has no image");
  std::vector<uint8_t> bytes;
  std::vector<int> params;
  if (format_ == "jpg") params = {cv::IMWRITE_JPEG_QUALITY, quality_};
  if (!cv::imencode("." + format_, image, bytes, params)) {
    throw Error(dir_ + ": cannot encode frame " + std::to_string(frame) + " as " + format_);
  }
  add_encoded(frame, timestamp_ns, bytes, format_, truth);
}

void RecordingWriter::add_encoded(int64_t frame, int64_t timestamp_ns,
                                  const std::vector<uint8_t>& bytes, const std::string& ext,
                                  const std::vector<PoseRow>& truth) {
  if (finished_) throw Error(dir_ + ": recording already finished");
  if (frame <= last_frame_) {
    throw Error(dir_ + ": frame number " + std::to_string(frame) + " after " +
                std::to_string(last_frame_) + ", expected increasing frame numbers");
  }
  if (ext != "jpg" && ext != "png") {
    throw Error(dir_ + ": frame extension '" + ext + "', expected jpg or png");
  }
  const std::string name = fmt::format("frames/{:06}.{}", frame, ext);
  write_binary_file((fs::path(dir_) / name).string(), bytes.data(), bytes.size());
  append_row(frame, timestamp_ns, name, truth);
  last_frame_ = frame;
  ++count_;
}

void RecordingWriter::append_row(int64_t frame, int64_t timestamp_ns, const std::string& file,
                                 const std::vector<PoseRow>& truth) {
  if (truth_csv_) {
    for (PoseRow r : truth) {
      r.frame = frame;
      r.timestamp_ns = timestamp_ns;
      std::fprintf(truth_csv_, "%s\n", format_pose_row(r).c_str());
    }
    if (std::fflush(truth_csv_) != 0) throw Error(dir_ + "/ground_truth.csv: cannot write");
  }
  std::fprintf(frames_csv_, "%" PRId64 ",%" PRId64 ",%s\n", frame, timestamp_ns, file.c_str());
  if (std::fflush(frames_csv_) != 0) throw Error(dir_ + "/frames.csv: cannot write");
}

void RecordingWriter::finish() {
  if (finished_) return;
  if (frames_csv_) std::fclose(frames_csv_);
  if (truth_csv_) std::fclose(truth_csv_);
  frames_csv_ = nullptr;
  truth_csv_ = nullptr;
  finished_ = true;
  write_session(true);
}

// ---------------------------------------------------------------------------------------------
// Reader

RecordingReader::RecordingReader(const std::string& dir) : dir_(dir) {
  if (!fs::is_directory(dir_)) throw Error(dir_ + ": recording folder not found");
  const std::string frames_path = (fs::path(dir_) / "frames.csv").string();
  if (!fs::exists(frames_path)) {
    throw Error(frames_path + ": missing; a recording folder has frames.csv (" + kFramesHeader +
                ")");
  }
  bool incomplete = false;
  const std::vector<std::string> lines = read_lines(frames_path, &incomplete);
  check_csv_header(frames_path, lines.empty() ? std::string() : lines[0], kFramesHeader);
  for (size_t i = 1; i < lines.size(); ++i) {
    if (lines[i].empty()) continue;
    const std::vector<std::string> f = split_csv_line(lines[i]);
    Entry e;
    if (f.size() != 3 || !parse_int64(f[0], &e.frame) || !parse_int64(f[1], &e.timestamp_ns) ||
        f[2].empty()) {
      problems_.push_back(frames_path + ": line " + std::to_string(i + 1) +
                          " is malformed, skipped (expected " + kFramesHeader + ")");
      continue;
    }
    if (!entries_.empty() && e.frame <= entries_.back().frame) {
      problems_.push_back(frames_path + ": line " + std::to_string(i + 1) + " frame " + f[0] +
                          " does not follow frame " + std::to_string(entries_.back().frame) +
                          ", skipped");
      continue;
    }
    e.file = f[2];
    entries_.push_back(e);
  }
  if (incomplete) {
    problems_.push_back(frames_path +
                        ": last line is incomplete (the recording was interrupted), skipped");
  }

  const fs::path session_path = fs::path(dir_) / "session.json";
  if (fs::exists(session_path)) {
    try {
      std::ifstream in(session_path);
      in >> session_;
    } catch (const std::exception& e) {
      session_ = nlohmann::json();
      problems_.push_back(session_path.string() + ": not valid JSON, ignored");
    }
  } else {
    problems_.push_back(session_path.string() + ": missing");
  }

  const std::string truth_path = (fs::path(dir_) / "ground_truth.csv").string();
  if (fs::exists(truth_path)) {
    PoseCsv truth = read_pose_csv(truth_path);
    problems_.insert(problems_.end(), truth.problems.begin(), truth.problems.end());
    truth_ = std::move(truth.rows);
    std::stable_sort(truth_.begin(), truth_.end(),
                     [](const PoseRow& a, const PoseRow& b) { return a.frame < b.frame; });
    has_truth_ = true;
  }
}

std::string RecordingReader::camera_path() const {
  const fs::path p = fs::path(dir_) / "camera.yaml";
  return fs::exists(p) ? p.string() : std::string();
}

std::string RecordingReader::boards_path() const {
  const fs::path p = fs::path(dir_) / "boards.json";
  return fs::exists(p) ? p.string() : std::string();
}

std::vector<PoseRow> RecordingReader::ground_truth(int64_t frame) const {
  const auto lo = std::lower_bound(truth_.begin(), truth_.end(), frame,
                                   [](const PoseRow& r, int64_t f) { return r.frame < f; });
  std::vector<PoseRow> out;
  for (auto it = lo; it != truth_.end() && it->frame == frame; ++it) out.push_back(*it);
  return out;
}

RecordingReader::Loaded RecordingReader::load(size_t i) const {
  Loaded out;
  if (i >= entries_.size()) {
    out.problem = dir_ + ": frame entry " + std::to_string(i) + " does not exist";
    return out;
  }
  const Entry& e = entries_[i];
  const fs::path path = fs::path(dir_) / e.file;
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) {
    out.problem = path.string() + (fs::exists(path, ec) ? ": not a file" : ": frame file missing");
    return out;
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    out.problem = path.string() + ": frame file cannot be read";
    return out;
  }
  out.bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  out.image = decode_image(out.bytes, &out.problem);
  if (out.image.empty()) out.problem = path.string() + ": " + out.problem;
  return out;
}

namespace {

// libjpeg's error manager: errors jump back instead of exiting; warnings ("Corrupt JPEG data",
// "Premature end of JPEG file") are counted, since libjpeg decodes through them and a frame with
// garbage in it would be drawn over as if it were live.
struct JpegErrors {
  jpeg_error_mgr mgr;
  std::jmp_buf jump;
  char first_warning[JMSG_LENGTH_MAX] = {0};
};

void jpeg_error_exit(j_common_ptr info) {
  std::longjmp(reinterpret_cast<JpegErrors*>(info->err)->jump, 1);
}

void jpeg_emit_message(j_common_ptr info, int level) {
  if (level >= 0) return;  // trace messages
  auto* errors = reinterpret_cast<JpegErrors*>(info->err);
  if (errors->mgr.num_warnings++ == 0) (*info->err->format_message)(info, errors->first_warning);
}

// The largest frame accepted (a 8K camera has 33 M pixels); checked from the header, before a
// corrupt header claiming 30000 x 30000 pixels allocates gigabytes.
constexpr int64_t kMaxFramePixels = int64_t(1) << 26;

cv::Mat decode_jpeg(const std::vector<uint8_t>& bytes, std::string* problem) {
  jpeg_decompress_struct info;
  JpegErrors errors;
  info.err = jpeg_std_error(&errors.mgr);
  errors.mgr.error_exit = jpeg_error_exit;
  errors.mgr.emit_message = jpeg_emit_message;
  cv::Mat image;
  if (setjmp(errors.jump)) {
    char text[JMSG_LENGTH_MAX];
    (*info.err->format_message)(reinterpret_cast<j_common_ptr>(&info), text);
    jpeg_destroy_decompress(&info);
    *problem = std::string("corrupt JPEG (") + text + ")";
    return {};
  }
  jpeg_create_decompress(&info);
  jpeg_mem_src(&info, bytes.data(), static_cast<unsigned long>(bytes.size()));
  jpeg_read_header(&info, TRUE);
  if (int64_t(info.image_width) * int64_t(info.image_height) > kMaxFramePixels) {
    *problem = "JPEG header claims " + std::to_string(info.image_width) + "x" +
               std::to_string(info.image_height) + " pixels, more than any camera frame; skipped";
    jpeg_destroy_decompress(&info);
    return {};
  }
  info.out_color_space = JCS_EXT_BGR;
  jpeg_start_decompress(&info);
  image.create(int(info.output_height), int(info.output_width), CV_8UC3);
  while (info.output_scanline < info.output_height) {
    JSAMPROW row = image.ptr<uint8_t>(int(info.output_scanline));
    jpeg_read_scanlines(&info, &row, 1);
  }
  jpeg_finish_decompress(&info);
  const long warnings = errors.mgr.num_warnings;
  jpeg_destroy_decompress(&info);
  if (warnings > 0) {
    *problem = std::string("corrupt JPEG (") + errors.first_warning + ")";
    return {};
  }
  problem->clear();
  return image;
}

}  // namespace

cv::Mat to_8bit_by_range(const cv::Mat& image) {
  if (image.empty() || image.depth() == CV_8U) return image;
  if (image.depth() != CV_16U) {  // float or signed images (TIFF, EXR): darkest to brightest
    double lo = 0, hi = 0;
    cv::minMaxLoc(image.reshape(1), &lo, &hi);
    const double scale = hi > lo && std::isfinite(hi - lo) ? 255.0 / (hi - lo) : 0.0;
    cv::Mat out;
    image.convertTo(out, CV_8U, scale, -lo * scale);
    return out;
  }
  // The range between the 0.01 % and 99.99 % quantiles of the values: a few hot or dead pixels do
  // not squeeze the rest into a handful of grey levels.
  std::vector<uint32_t> histogram(65536, 0);
  const cv::Mat values = image.reshape(1);
  for (int y = 0; y < values.rows; ++y) {
    const uint16_t* row = values.ptr<uint16_t>(y);
    for (int x = 0; x < values.cols; ++x) ++histogram[row[x]];
  }
  const size_t total = values.total(), tail = total / 10000;
  double lo = 0, hi = 65535;
  size_t seen = 0;
  for (size_t v = 0; v < histogram.size(); ++v) {
    seen += histogram[v];
    if (seen > tail) {
      lo = double(v);
      break;
    }
  }
  seen = 0;
  for (size_t v = histogram.size(); v-- > 0;) {
    seen += histogram[v];
    if (seen > tail) {
      hi = double(v);
      break;
    }
  }
  const double scale = hi > lo ? 255.0 / (hi - lo) : 0.0;
  cv::Mat out;
  image.convertTo(out, CV_8U, scale, -lo * scale);
  return out;
}

cv::Mat decode_image(const std::vector<uint8_t>& bytes, std::string* problem) {
  if (bytes.empty()) {
    *problem = "empty image data";
    return {};
  }
  if (is_jpeg(bytes)) {
    // libjpeg decodes a truncated JPEG with only a warning, filling the rest with grey; a complete
    // JPEG ends with the EOI marker (FF D9), possibly followed by zero padding from the camera.
    size_t end = bytes.size();
    while (end > 2 && bytes[end - 1] == 0x00) --end;
    const bool eoi = bytes[end - 2] == 0xFF && bytes[end - 1] == 0xD9;
    if (!eoi) {
      *problem = "corrupt JPEG (" + std::to_string(bytes.size()) + " bytes, no end-of-image marker)";
      return {};
    }
  }
  if (is_jpeg(bytes)) return decode_jpeg(bytes, problem);
  cv::Mat image;
  try {
    image = to_8bit_by_range(cv::imdecode(bytes, cv::IMREAD_COLOR | cv::IMREAD_ANYDEPTH));
  } catch (const cv::Exception& e) {
    *problem = std::string("cannot decode image (") + e.err + ")";
    return {};
  }
  if (image.empty()) {
    *problem = std::string("corrupt ") + (is_jpeg(bytes) ? "JPEG" : "image") + " (" +
               std::to_string(bytes.size()) + " bytes could not be decoded)";
    return {};
  }
  problem->clear();
  return image;
}

}  // namespace crepuscular::recordings
