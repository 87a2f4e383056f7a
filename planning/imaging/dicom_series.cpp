// DICOM series folders checked slice by slice before ITK reads them (dicom_series.hpp). Tag values
// are read through GDCM; only the element structure is walked here, because GDCM (as packaged,
// with its assertions on) aborts on a file that ends inside an element and fills Pixel Data that
// end early with zeros.
#include "planning/imaging/dicom_series.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <sstream>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "planning/imaging/volume_io.hpp"

#include <gdcmDataSet.h>
#include <gdcmFile.h>
#include <gdcmReader.h>
#include <gdcmStringFilter.h>
#include <gdcmTag.h>
#include <gdcmVR.h>

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

constexpr uint32_t kUndefined = 0xFFFFFFFFu;
constexpr int kMaxDepth = 16;

std::string tag_text(uint16_t group, uint16_t element) {
  char text[16];
  std::snprintf(text, sizeof text, "(%04X,%04X)", group, element);
  return text;
}

// Walks the elements of a DICOM Part 10 file: each element's declared length must fit in the
// file, sequences and items must close. Values are not interpreted, except the transfer syntax.
class StructureWalk {
 public:
  explicit StructureWalk(const std::string& bytes) : b_(bytes) {}

  // "" when the structure is whole, else what is wrong.
  std::string walk() {
    if (b_.size() < 132 || b_.compare(128, 4, "DICM") != 0) {
      return "not a DICOM Part 10 file (no \"DICM\" at byte 128)";
    }
    size_t at = 132;
    // File meta information: group 0002, explicit VR little endian.
    while (at + 8 <= b_.size() && u16(at) == 0x0002) {
      const bool ts = u16(at + 2) == 0x0010;
      size_t value = 0;
      uint32_t length = 0;
      std::string problem = element_header(at, b_.size(), value, length);
      if (!problem.empty()) return "file meta information: " + problem;
      // The meta information's elements have these value representations only (PS3.10 7.1);
      // GDCM asserts on any other.
      static const std::set<std::string> kMetaVr = {"AE", "OB", "SH", "UI", "UL"};
      if (!kMetaVr.count(b_.substr(at + 4, 2))) {
        return "file meta information: element " + tag_text(0x0002, u16(at + 2)) +
               " has the value representation " + b_.substr(at + 4, 2) +
               ", expected AE, OB, SH, UI or UL";
      }
      if (length == kUndefined || length > b_.size() - value) {
        return "file meta information: element " + tag_text(0x0002, u16(at + 2)) +
               " runs past the end of the file";
      }
      if (ts) {
        transfer_syntax_ = b_.substr(value, length);
        while (!transfer_syntax_.empty() &&
               (transfer_syntax_.back() == '\0' || transfer_syntax_.back() == ' ')) {
          transfer_syntax_.pop_back();
        }
      }
      at = value + length;
    }
    if (transfer_syntax_.empty() ||
        transfer_syntax_.find_first_not_of("0123456789.") != std::string::npos) {
      return "file meta information: the transfer syntax (0002,0010) is not a UID";
    }
    if (transfer_syntax_ == "1.2.840.10008.1.2.1.99") {
      return "deflated transfer syntax (not supported for slices)";
    }
    explicit_vr_ = transfer_syntax_ != "1.2.840.10008.1.2";
    big_endian_ = transfer_syntax_ == "1.2.840.10008.1.2.2";
    return elements(at, b_.size(), false, 0);
  }

  bool pixel_data() const { return pixel_data_; }
  bool encapsulated() const { return encapsulated_; }
  uint64_t pixel_bytes_stored() const { return pixel_stored_; }
  uint64_t pixel_bytes_declared() const { return pixel_declared_; }
  // Where the top-level pixel data element starts (the file's size when it has none): the
  // header ends there.
  size_t header_end() const { return pixel_data_ ? pixel_element_at_ : b_.size(); }

 private:
  uint16_t u16(size_t at) const {
    const auto* p = reinterpret_cast<const unsigned char*>(b_.data() + at);
    return big_endian_ ? uint16_t(p[0] << 8 | p[1]) : uint16_t(p[1] << 8 | p[0]);
  }
  uint32_t u32(size_t at) const {
    return big_endian_ ? uint32_t(u16(at)) << 16 | u16(at + 2)
                       : uint32_t(u16(at + 2)) << 16 | u16(at);
  }

  // Reads the header of the element at `at` (below `end`): where its value starts, its length.
  std::string element_header(size_t at, size_t end, size_t& value, uint32_t& length) {
    if (end - at < 8) return "the file ends inside an element's header";
    const bool meta = u16(at) == 0x0002;
    if ((explicit_vr_ || meta) && u16(at) != 0xFFFE) {
      const char v0 = b_[at + 4], v1 = b_[at + 5];
      // GDCM reads a value representation it does not know with a 4-byte length: only the
      // standard's (PS3.5 6.2), so that both read the same lengths.
      static const std::set<std::string> kKnown = {
          "AE", "AS", "AT", "CS", "DA", "DS", "DT", "FD", "FL", "IS", "LO", "LT", "OB", "OD", "OF",
          "OL", "OV", "OW", "PN", "SH", "SL", "SQ", "SS", "ST", "SV", "TM", "UC", "UI", "UL", "UN",
          "UR", "US", "UT", "UV"};
      if (!kKnown.count(std::string{v0, v1})) {
        return "element " + tag_text(u16(at), u16(at + 2)) + " has no known value representation";
      }
      static const std::set<std::string> kLong = {"OB", "OD", "OF", "OL", "OV", "OW", "SQ",
                                                  "SV", "UC", "UN", "UR", "UT", "UV"};
      if (kLong.count(std::string{v0, v1})) {
        if (end - at < 12) return "the file ends inside an element's header";
        length = u32(at + 8);
        value = at + 12;
      } else {
        length = u16(at + 6);
        value = at + 8;
      }
      return {};
    }
    length = u32(at + 4);
    value = at + 8;
    return {};
  }

  // Elements from `at` up to `end`; with `in_item`, up to the item delimiter (consumed).
  std::string elements(size_t& at, size_t end, bool in_item, int depth) {
    // Tags ascend within a data set (PS3.5 7.1); GDCM reads one that does not as another
    // encoding, with other lengths than those checked here.
    uint32_t last_tag = 0;
    while (at < end) {
      if (end - at < 8) return "the file ends inside an element's header";
      const uint16_t group = u16(at), element = u16(at + 2);
      if (group == 0xFFFE && element == 0xE00D && in_item) {
        at += 8;
        return {};
      }
      const uint32_t tag = uint32_t(group) << 16 | element;
      if (group != 0xFFFE && tag <= last_tag) {
        return "element " + tag_text(group, element) + " out of order (after " +
               tag_text(uint16_t(last_tag >> 16), uint16_t(last_tag & 0xFFFF)) + ")";
      }
      last_tag = tag;
      size_t value = 0;
      uint32_t length = 0;
      std::string problem = element_header(at, end, value, length);
      if (!problem.empty()) return problem;
      if (group == 0xFFFE) return "misplaced item tag " + tag_text(group, element);
      const bool pixels = depth == 0 && group == 0x7FE0 && element == 0x0010;
      if (pixels) pixel_element_at_ = at;
      if (length == kUndefined) {  // a sequence of items (or encapsulated pixel data)
        if (depth >= kMaxDepth) return "sequences nested too deep";
        at = value;
        problem = items(at, end, true, depth + 1, pixels);
        if (!problem.empty()) return "in " + tag_text(group, element) + ": " + problem;
        if (pixels) pixel_data_ = encapsulated_ = true;
        continue;
      }
      if (pixels) {  // GDCM pads short pixel data itself: measured, reported by the caller
        pixel_data_ = true;
        pixel_declared_ = length;
        pixel_stored_ = std::min<uint64_t>(length, end - value);
        if (length > end - value) {
          at = end;
          return {};
        }
      } else if (length > end - value) {
        return "element " + tag_text(group, element) + " declares " + std::to_string(length) +
               " bytes, " + std::to_string(end - value) + " are left in the file";
      }
      const bool sequence = explicit_vr_ && b_.compare(at + 4, 2, "SQ") == 0;
      at = value;
      if (sequence) {
        if (depth >= kMaxDepth) return "sequences nested too deep";
        problem = items(at, value + length, false, depth + 1, false);
        if (!problem.empty()) return "in " + tag_text(group, element) + ": " + problem;
      }
      at = value + length;
    }
    return in_item ? "the file ends inside an item" : "";
  }

  // Items of a sequence from `at` up to `end`; with `undefined`, up to the sequence delimiter
  // (consumed). `fragments`: the items hold compressed pixel data, not elements.
  std::string items(size_t& at, size_t end, bool undefined, int depth, bool fragments) {
    while (at < end) {
      if (end - at < 8) return "the file ends inside an item's header";
      const uint16_t group = u16(at), element = u16(at + 2);
      const uint32_t length = u32(at + 4);
      at += 8;
      if (group == 0xFFFE && element == 0xE0DD && undefined) return {};
      if (group != 0xFFFE || element != 0xE000) {
        return "expected an item, found " + tag_text(group, element);
      }
      if (length == kUndefined) {
        if (fragments) return "a pixel data fragment of undefined length";
        const std::string problem = elements(at, end, true, depth);
        if (!problem.empty()) return problem;
        continue;
      }
      if (length > end - at) {
        return "an item declares " + std::to_string(length) + " bytes, " +
               std::to_string(end - at) + " are left";
      }
      if (fragments) {
        pixel_stored_ += length;
      } else {
        size_t inner = at;
        const std::string problem = elements(inner, at + length, false, depth);
        if (!problem.empty()) return problem;
      }
      at += length;
    }
    return undefined ? "the file ends inside a sequence" : "";
  }

  const std::string& b_;
  std::string transfer_syntax_;
  bool explicit_vr_ = true;
  bool big_endian_ = false;
  bool pixel_data_ = false;
  bool encapsulated_ = false;
  uint64_t pixel_declared_ = 0;
  uint64_t pixel_stored_ = 0;
  size_t pixel_element_at_ = 0;
};

// One file of the folder, as far as the checks need it.
struct Slice {
  std::string path, name;
  std::string series_uid, sop_uid, modality, description;
  std::optional<Eigen::Vector3d> position;
  std::optional<std::array<double, 6>> orientation;
  long rows = 0, columns = 0, bits_allocated = 0, samples = 1, frames = 1;
  bool pixel_data = false, encapsulated = false;
  uint64_t pixel_bytes = 0;  // stored bytes of uncompressed pixel data
  uint64_t pixel_bytes_declared = 0;  // the length its pixel data element declares
  double along_normal = 0.0;
};

std::string trimmed(std::string text) {
  while (!text.empty() && (text.back() == ' ' || text.back() == '\0')) text.pop_back();
  const size_t first = text.find_first_not_of(' ');
  return first == std::string::npos ? std::string() : text.substr(first);
}

// Numbers of a multi-valued decimal string ("0.5\-12\40"); nullopt unless there are `count`.
std::optional<std::vector<double>> numbers(const std::string& text, size_t count) {
  std::vector<double> out;
  std::stringstream in(text);
  for (std::string item; std::getline(in, item, '\\');) {
    char* end = nullptr;
    const std::string t = trimmed(item);
    const double v = std::strtod(t.c_str(), &end);
    if (t.empty() || *end != '\0' || !std::isfinite(v)) return std::nullopt;
    out.push_back(v);
  }
  if (out.size() != count) return std::nullopt;
  return out;
}

long whole_number(const std::string& text, long fallback) {
  const std::string t = trimmed(text);
  char* end = nullptr;
  const long v = std::strtol(t.c_str(), &end, 10);
  return t.empty() || *end != '\0' ? fallback : v;
}

// Reads one file's structure and tags; throws Error naming the folder and the file.
Slice read_slice(const fs::path& path, const std::string& folder) {
  Slice s;
  s.path = path.string();
  s.name = path.filename().string();
  const auto unreadable = [&](const std::string& why) {
    return Error(folder + ": slice " + s.name + " is not a readable DICOM file (" + why + ")");
  };
  std::string bytes;
  {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw unreadable("cannot open it");
    bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  StructureWalk walk(bytes);
  const std::string problem = walk.walk();
  if (!problem.empty()) throw unreadable(problem);
  if (!walk.pixel_data()) {
    throw Error(folder + ": slice " + s.name + " holds no pixel data (7FE0,0010): not an image slice");
  }
  // GDCM reads the header alone: the pixel data are measured by the walk, and GDCM would reserve
  // their declared length (gigabytes in a damaged file) before finding them missing.
  std::istringstream stream(bytes.substr(0, walk.header_end()));
  gdcm::Reader reader;
  reader.SetStream(stream);
  bool read = false;
  try {
    read = reader.Read();
  } catch (const std::exception& e) {
    throw unreadable(e.what());
  }
  if (!read) throw unreadable("GDCM cannot read its header");
  // GDCM's image reader asserts (ends the process) on an attribute of the image pixel module
  // stored with another value representation than the standard's: refused here first.
  static const std::vector<std::pair<gdcm::Tag, gdcm::VR::VRType>> kImageAttributes = {
      {{0x0028, 0x0002}, gdcm::VR::US}, {{0x0028, 0x0004}, gdcm::VR::CS},
      {{0x0028, 0x0006}, gdcm::VR::US}, {{0x0028, 0x0008}, gdcm::VR::IS},
      {{0x0028, 0x0010}, gdcm::VR::US}, {{0x0028, 0x0011}, gdcm::VR::US},
      {{0x0028, 0x0030}, gdcm::VR::DS}, {{0x0028, 0x0100}, gdcm::VR::US},
      {{0x0028, 0x0101}, gdcm::VR::US}, {{0x0028, 0x0102}, gdcm::VR::US},
      {{0x0028, 0x0103}, gdcm::VR::US}, {{0x0028, 0x1050}, gdcm::VR::DS},
      {{0x0028, 0x1051}, gdcm::VR::DS}, {{0x0028, 0x1052}, gdcm::VR::DS},
      {{0x0028, 0x1053}, gdcm::VR::DS}, {{0x0020, 0x0032}, gdcm::VR::DS},
      {{0x0020, 0x0037}, gdcm::VR::DS}, {{0x0018, 0x0050}, gdcm::VR::DS}};
  const gdcm::DataSet& data = reader.GetFile().GetDataSet();
  for (const auto& [attribute, expected] : kImageAttributes) {
    if (!data.FindDataElement(attribute)) continue;
    const gdcm::VR vr = data.GetDataElement(attribute).GetVR();
    if (vr != gdcm::VR::INVALID && vr != gdcm::VR::UN && vr != expected) {
      throw unreadable("element " + tag_text(attribute.GetGroup(), attribute.GetElement()) +
                       " is stored as " + gdcm::VR::GetVRString(vr) + ", expected " +
                       gdcm::VR::GetVRString(expected));
    }
  }
  gdcm::StringFilter text;
  text.SetFile(reader.GetFile());
  const auto tag = [&](uint16_t group, uint16_t element) {
    return trimmed(text.ToString(gdcm::Tag(group, element)));
  };
  s.series_uid = tag(0x0020, 0x000E);
  if (s.series_uid.empty()) throw unreadable("no SeriesInstanceUID (0020,000E)");
  s.sop_uid = tag(0x0008, 0x0018);
  s.modality = tag(0x0008, 0x0060);
  s.description = tag(0x0008, 0x103E);
  if (const auto p = numbers(tag(0x0020, 0x0032), 3)) s.position = Eigen::Vector3d((*p)[0], (*p)[1], (*p)[2]);
  if (const auto o = numbers(tag(0x0020, 0x0037), 6)) {
    s.orientation = std::array<double, 6>{(*o)[0], (*o)[1], (*o)[2], (*o)[3], (*o)[4], (*o)[5]};
  }
  s.rows = whole_number(tag(0x0028, 0x0010), 0);
  s.columns = whole_number(tag(0x0028, 0x0011), 0);
  s.bits_allocated = whole_number(tag(0x0028, 0x0100), 0);
  s.samples = whole_number(tag(0x0028, 0x0002), 1);
  s.frames = whole_number(tag(0x0028, 0x0008), 1);
  s.pixel_data = walk.pixel_data();
  s.encapsulated = walk.encapsulated();
  s.pixel_bytes = walk.pixel_bytes_stored();
  s.pixel_bytes_declared = walk.pixel_bytes_declared();
  return s;
}

std::string series_text(const std::string& uid, const std::vector<const Slice*>& slices) {
  const Slice& first = *slices.front();
  std::string text = uid + " (" + std::to_string(slices.size()) +
                     (slices.size() == 1 ? " slice" : " slices");
  if (!first.modality.empty() || !first.description.empty()) text += ",";
  if (!first.modality.empty()) text += " " + first.modality;
  if (!first.description.empty()) text += " '" + first.description + "'";
  return text + ")";
}

std::string mm(double v) {
  char text[32];
  std::snprintf(text, sizeof text, "%.4g mm", v);
  return text;
}

// The checks of one series' slices (dicom_series.hpp); returns them ordered along the normal.
std::vector<const Slice*> checked_series(std::vector<const Slice*> slices, const std::string& folder) {
  const Slice& first = *slices.front();
  std::map<std::string, const Slice*> by_sop;
  for (const Slice* s : slices) {
    const std::string at = folder + ": slice " + s->name;
    if (!s->pixel_data) throw Error(at + " holds no pixel data (7FE0,0010): not an image slice");
    if (s->rows <= 0 || s->columns <= 0 || s->bits_allocated <= 0 || s->samples <= 0 ||
        s->frames <= 0) {
      throw Error(at + " has rows " + std::to_string(s->rows) + ", columns " +
                  std::to_string(s->columns) + ", bits allocated " +
                  std::to_string(s->bits_allocated) + ", samples per pixel " +
                  std::to_string(s->samples) + " (expected numbers > 0)");
    }
    const uint64_t needed = (uint64_t(s->rows) * uint64_t(s->columns) * uint64_t(s->samples) *
                                 uint64_t(s->frames) * uint64_t(s->bits_allocated) + 7) / 8;
    // Compressed pixel data are decoded by GDCM into a buffer of the size the header declares,
    // reserved first: a header that declares far more than any compression of the fragments
    // gives (a damaged file) is refused before that.
    constexpr uint64_t kMostCompression = 1000, kAnySlice = uint64_t(1) << 20;
    if (s->encapsulated && needed > kAnySlice && needed / kMostCompression > s->pixel_bytes) {
      throw Error(at + " declares " + std::to_string(needed) + " bytes of pixels (" +
                  std::to_string(s->rows) + " rows x " + std::to_string(s->columns) +
                  " columns) compressed into " + std::to_string(s->pixel_bytes) +
                  " bytes: more than any compression gives, a damaged header");
    }
    if (!s->encapsulated) {
      if (s->pixel_bytes < needed) {
        throw Error(at + " is truncated: its pixel data hold " + std::to_string(s->pixel_bytes) +
                    " bytes, expected " + std::to_string(needed) + " (" +
                    std::to_string(s->rows) + " rows x " + std::to_string(s->columns) +
                    " columns x " + std::to_string(s->bits_allocated) + " bits x " +
                    std::to_string(s->samples) + " samples" +
                    (s->frames > 1 ? " x " + std::to_string(s->frames) + " frames" : "") + ")");
      }
      if (s->pixel_bytes < s->pixel_bytes_declared) {
        throw Error(at + " is truncated: its pixel data element declares " +
                    std::to_string(s->pixel_bytes_declared) + " bytes, the file holds " +
                    std::to_string(s->pixel_bytes));
      }
    }
    if (s->rows != first.rows || s->columns != first.columns) {
      throw Error(at + " is " + std::to_string(s->columns) + " x " + std::to_string(s->rows) +
                  " pixels, slice " + first.name + " " + std::to_string(first.columns) + " x " +
                  std::to_string(first.rows) + " (expected one size in a series)");
    }
    if (!s->sop_uid.empty()) {
      const auto [other, fresh] = by_sop.emplace(s->sop_uid, s);
      if (!fresh) {
        throw Error(folder + ": slices " + other->second->name + " and " + s->name +
                    " are the same slice (SOPInstanceUID " + s->sop_uid + "): a duplicate");
      }
    }
  }
  if (slices.size() == 1) return slices;
  for (const Slice* s : slices) {
    if (!s->position || !s->orientation) {
      throw Error(folder + ": slice " + s->name +
                  " has no ImagePositionPatient (0020,0032) or ImageOrientationPatient "
                  "(0020,0037): the slices cannot be placed");
    }
  }
  const auto& o = *first.orientation;
  const Eigen::Vector3d row(o[0], o[1], o[2]), column(o[3], o[4], o[5]);
  const Eigen::Vector3d normal = row.cross(column);
  if (!(normal.norm() > 0.5)) {
    throw Error(folder + ": slice " + first.name +
                " has an ImageOrientationPatient whose row and column are not perpendicular");
  }
  for (const Slice* s : slices) {
    const auto& q = *s->orientation;
    double differs = 0.0;
    for (int i = 0; i < 6; ++i) differs = std::max(differs, std::fabs(q[size_t(i)] - o[size_t(i)]));
    if (differs > 1e-4) {
      throw Error(folder + ": slice " + s->name + " lies in another orientation than slice " +
                  first.name + " (ImageOrientationPatient differs by " + std::to_string(differs) +
                  ")");
    }
  }
  std::vector<std::pair<double, const Slice*>> along;
  for (const Slice* s : slices) along.emplace_back(normal.normalized().dot(*s->position), s);
  std::stable_sort(along.begin(), along.end(),
                   [](const auto& a, const auto& b) { return a.first < b.first; });
  std::vector<double> gaps;
  for (size_t i = 1; i < along.size(); ++i) gaps.push_back(along[i].first - along[i - 1].first);
  std::vector<double> sorted_gaps = gaps;
  std::nth_element(sorted_gaps.begin(), sorted_gaps.begin() + sorted_gaps.size() / 2,
                   sorted_gaps.end());
  const double spacing = sorted_gaps[sorted_gaps.size() / 2];
  const double tolerance = std::max(0.01, 0.01 * spacing);
  for (size_t i = 0; i < gaps.size(); ++i) {
    const Slice& a = *along[i].second;
    const Slice& b = *along[i + 1].second;
    if (gaps[i] <= 0.01) {
      throw Error(folder + ": slices " + a.name + " and " + b.name + " lie at the same position (" +
                  mm(gaps[i]) + " apart along the slice normal): a duplicate slice");
    }
    if (std::fabs(gaps[i] - spacing) > tolerance) {
      throw Error(folder + ": slices " + a.name + " and " + b.name + " are " + mm(gaps[i]) +
                  " apart along the slice normal, expected " + mm(spacing) +
                  " (the series' usual spacing, within " + mm(tolerance) + "): " +
                  (gaps[i] > spacing ? "a missing slice" : "unequal spacing"));
    }
  }
  std::vector<const Slice*> ordered;
  for (const auto& [d, s] : along) ordered.push_back(s);
  return ordered;
}

}  // namespace

std::vector<std::string> dicom_series_slices(const std::string& folder,
                                             const std::vector<std::string>& chosen) {
  std::vector<fs::path> files;
  std::error_code ec;
  for (fs::directory_iterator it(folder, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name.empty() || name[0] == '.' || name == "DICOMDIR") continue;
    if (it->is_regular_file(ec)) files.push_back(it->path());
  }
  if (ec) throw Error(folder + ": cannot read the folder (" + ec.message() + ")");
  if (files.empty()) throw Error(folder + ": cannot read (folder holds no DICOM series)");
  std::sort(files.begin(), files.end());

  std::vector<Slice> slices;
  slices.reserve(files.size());
  {
    // GDCM reads under the lock that ITK's readers take turns with (image_read_mutex).
    const std::lock_guard<std::recursive_mutex> one_reader(image_read_mutex());
    for (const fs::path& f : files) slices.push_back(read_slice(f, folder));
  }
  std::map<std::string, std::vector<const Slice*>> series;
  for (const Slice& s : slices) series[s.series_uid].push_back(&s);

  const std::vector<const Slice*>* pick = nullptr;
  if (series.size() == 1) {
    pick = &series.begin()->second;
  } else {
    for (const std::string& uid : chosen) {
      const auto found = series.find(uid);
      if (found != series.end()) pick = &found->second;
    }
    if (pick == nullptr) {
      std::string list;
      for (const auto& [uid, members] : series) {
        list += (list.empty() ? "" : ", ") + series_text(uid, members);
      }
      throw Error(folder + " holds " + std::to_string(series.size()) + " DICOM series: " + list +
                  "; choose one with --series UID");
    }
  }
  spdlog::debug("{}: DICOM series {}", folder, series_text(pick->front()->series_uid, *pick));
  std::vector<std::string> out;
  for (const Slice* s : checked_series(*pick, folder)) out.push_back(s->path);
  return out;
}

}  // namespace crepuscular::planning
