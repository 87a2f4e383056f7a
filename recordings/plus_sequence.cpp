#include "recordings/plus_sequence.hpp"

#include <zlib.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iterator>
#include <limits>
#include <set>
#include <sstream>

#include "foundation/error.hpp"
#include "foundation/output_files.hpp"

namespace crepuscular::recordings {

namespace {

constexpr const char* kFramePrefix = "Seq_Frame";

std::string trim(const std::string& s) {
  size_t a = 0, b = s.size();
  while (a < b && std::isspace(static_cast<unsigned char>(s[a]))) ++a;
  while (b > a && std::isspace(static_cast<unsigned char>(s[b - 1]))) --b;
  return s.substr(a, b - a);
}

std::vector<std::string> words(const std::string& s) {
  std::istringstream in(s);
  return {std::istream_iterator<std::string>(in), std::istream_iterator<std::string>()};
}

// Bytes per channel of a MetaImage element type; 0 for an unknown one.
int element_bytes(const std::string& type) {
  static const std::map<std::string, int> kBytes = {
      {"MET_UCHAR", 1}, {"MET_CHAR", 1},  {"MET_USHORT", 2}, {"MET_SHORT", 2},
      {"MET_UINT", 4},  {"MET_INT", 4},   {"MET_FLOAT", 4},  {"MET_ULONG_LONG", 8},
      {"MET_LONG_LONG", 8}, {"MET_DOUBLE", 8}};
  const auto it = kBytes.find(type);
  return it == kBytes.end() ? 0 : it->second;
}

// A NRRD type's MetaImage name; "" for one sequences do not use.
std::string nrrd_element_type(const std::string& t) {
  static const std::map<std::string, std::string> kTypes = {
      {"uchar", "MET_UCHAR"},     {"unsigned char", "MET_UCHAR"}, {"uint8", "MET_UCHAR"},
      {"uint8_t", "MET_UCHAR"},   {"signed char", "MET_CHAR"},    {"int8", "MET_CHAR"},
      {"int8_t", "MET_CHAR"},     {"short", "MET_SHORT"},         {"int16", "MET_SHORT"},
      {"int16_t", "MET_SHORT"},   {"short int", "MET_SHORT"},     {"signed short", "MET_SHORT"},
      {"ushort", "MET_USHORT"},   {"unsigned short", "MET_USHORT"}, {"uint16", "MET_USHORT"},
      {"uint16_t", "MET_USHORT"}, {"int", "MET_INT"},             {"int32", "MET_INT"},
      {"int32_t", "MET_INT"},     {"uint", "MET_UINT"},           {"unsigned int", "MET_UINT"},
      {"uint32", "MET_UINT"},     {"uint32_t", "MET_UINT"},       {"float", "MET_FLOAT"},
      {"double", "MET_DOUBLE"}};
  const auto it = kTypes.find(t);
  return it == kTypes.end() ? std::string() : it->second;
}

// Inflates `data` (zlib, or gzip when gzip) into exactly `expected` bytes.
std::vector<uint8_t> inflate_exactly(const std::string& path, const uint8_t* data, size_t size,
                                     size_t expected, bool gzip) {
  std::vector<uint8_t> out(expected);
  z_stream z{};
  if (inflateInit2(&z, gzip ? 16 + MAX_WBITS : MAX_WBITS) != Z_OK) {
    throw Error(path + ": cannot start decompressing its image data");
  }
  z.next_in = const_cast<Bytef*>(data);
  z.avail_in = uInt(std::min<size_t>(size, std::numeric_limits<uInt>::max()));
  z.next_out = out.data();
  z.avail_out = uInt(std::min<size_t>(expected, std::numeric_limits<uInt>::max()));
  const int rc = expected == 0 ? Z_STREAM_END : inflate(&z, Z_FINISH);
  const size_t produced = expected - z.avail_out;
  inflateEnd(&z);
  if (rc != Z_STREAM_END || produced != expected) {
    throw Error(path + ": the compressed image data " +
                (rc == Z_DATA_ERROR ? std::string("is corrupt")
                                    : "does not hold the " + std::to_string(expected) +
                                          " bytes its sizes call for"));
  }
  return out;
}

size_t checked_count(const std::string& path, const std::string& field, const std::string& text) {
  try {
    size_t used = 0;
    const long long v = std::stoll(text, &used);
    if (used != text.size() || v < 0 || v > (1LL << 31)) throw std::invalid_argument(text);
    return size_t(v);
  } catch (const std::exception&) {
    throw Error(path + ": " + field + " '" + text + "' is not a size");
  }
}

// The per-frame fields: "NNNN_Name" after "Seq_Frame" -> frame NNNN, field Name.
bool frame_field(const std::string& key, size_t* frame, std::string* name) {
  if (key.rfind(kFramePrefix, 0) != 0) return false;
  const size_t digits = std::strlen(kFramePrefix);
  size_t end = digits;
  while (end < key.size() && std::isdigit(static_cast<unsigned char>(key[end]))) ++end;
  if (end == digits || end - digits > 9 || end >= key.size() || key[end] != '_') return false;
  *frame = size_t(std::stoul(key.substr(digits, end - digits)));
  *name = key.substr(end + 1);
  return !name->empty();
}

struct Parsed {
  std::vector<std::pair<std::string, std::string>> header;
  std::vector<std::pair<size_t, std::pair<std::string, std::string>>> frame_fields;
  std::vector<size_t> sizes;  // image axes, the time axis last when there is one
  size_t frames = 0;          // from the sizes (0: none stated)
};

void add_field(Parsed& p, const std::string& key, const std::string& value) {
  size_t frame = 0;
  std::string name;
  if (frame_field(key, &frame, &name)) {
    p.frame_fields.push_back({frame, {name, value}});
  } else {
    p.header.emplace_back(key, value);
  }
}

std::string read_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path + ": cannot open the sequence file");
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) throw Error(path + ": cannot read the sequence file");
  return bytes;
}

// The header's lines up to `stop` (inclusive) or the first empty line (NRRD); pos: after them.
std::vector<std::string> header_lines(const std::string& path, const std::string& bytes,
                                      bool nrrd, size_t* pos) {
  std::vector<std::string> lines;
  size_t at = 0;
  while (true) {
    if (at >= bytes.size()) {
      throw Error(path + ": the header ends without " +
                  std::string(nrrd ? "the empty line before the data" : "ElementDataFile"));
    }
    const size_t nl = bytes.find('\n', at);
    std::string line = bytes.substr(at, (nl == std::string::npos ? bytes.size() : nl) - at);
    at = nl == std::string::npos ? bytes.size() : nl + 1;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    for (const char c : line) {
      if (c == '\0' || (static_cast<unsigned char>(c) < 0x20 && c != '\t')) {
        throw Error(path + ": binary bytes in the header (line " + std::to_string(lines.size() + 1) +
                    "): not a sequence file");
      }
    }
    if (nrrd && line.empty()) break;
    lines.push_back(line);
    if (!nrrd && trim(line.substr(0, line.find('='))) == "ElementDataFile") break;
  }
  *pos = at;
  return lines;
}

PlusSequence finish(const std::string& path, Parsed& p, std::vector<uint8_t> pixels,
                    int width, int height, int channels, const std::string& type,
                    size_t time_frames) {
  PlusSequence s;
  s.header = std::move(p.header);
  s.width = width;
  s.height = height;
  s.channels = channels;
  s.element_type = type;
  s.pixels = std::move(pixels);
  size_t frames = time_frames;
  std::stable_sort(p.frame_fields.begin(), p.frame_fields.end(),
                   [](const auto& a, const auto& b) { return a.first < b.first; });
  if (!p.frame_fields.empty()) {
    const size_t last = p.frame_fields.back().first;
    if (time_frames > 0 && last >= time_frames) {
      throw Error(path + ": Seq_Frame" + std::to_string(last) + " lies beyond the " +
                  std::to_string(time_frames) + " frames of its time axis");
    }
    frames = std::max(frames, last + 1);
  }
  s.frames.resize(frames);
  for (auto& [index, field] : p.frame_fields) s.frames[index].fields.push_back(std::move(field));
  for (size_t f = 0; f < s.frames.size(); ++f) {
    PlusFrame& frame = s.frames[f];
    const std::string where = path + ": frame " + std::to_string(f);
    frame.timestamp_s = std::numeric_limits<double>::quiet_NaN();
    for (const auto& [name, value] : frame.fields) {
      if (name == "Timestamp") {
        try {
          size_t used = 0;
          frame.timestamp_s = std::stod(value, &used);
          if (trim(value.substr(used)).size() > 0 || !std::isfinite(frame.timestamp_s)) {
            throw std::invalid_argument(value);
          }
        } catch (const std::exception&) {
          throw Error(where + ": Timestamp '" + value + "' is not a number of seconds");
        }
        continue;
      }
      const std::string transform = plus_transform_name(name);
      if (transform.empty()) continue;
      const std::vector<std::string> numbers = words(value);
      PlusTransform t;
      bool ok = numbers.size() == 16;
      for (size_t k = 0; ok && k < 16; ++k) {
        char* end = nullptr;
        const double v = std::strtod(numbers[k].c_str(), &end);
        ok = end && *end == '\0' && std::isfinite(v);
        t.matrix(int(k / 4), int(k % 4)) = v;
      }
      if (!ok) {
        throw Error(where + ": " + name + " is not 16 numbers (a row-major 4x4 matrix): '" +
                    value + "'");
      }
      frame.transforms[transform] = t;
    }
    for (const auto& [name, value] : frame.fields) {
      const std::string suffix = "TransformStatus";
      if (name.size() <= suffix.size() || name.compare(name.size() - suffix.size(), suffix.size(), suffix) != 0) {
        continue;
      }
      const std::string transform = name.substr(0, name.size() - suffix.size());
      const std::string status = trim(value);
      if (status != "OK" && status != "INVALID") {
        throw Error(where + ": " + name + " is '" + value + "', expected OK or INVALID");
      }
      auto it = frame.transforms.find(transform);
      if (it == frame.transforms.end()) {
        throw Error(where + ": " + name + " without its transform " + transform + "Transform");
      }
      it->second.valid = status == "OK";
    }
  }
  return s;
}

// The image data after the header: `encoding` "raw", "zlib" or "gzip", byte-swapped to little
// endian when big_endian; then the frames' fields made into the sequence.
PlusSequence with_image_data(const std::string& path, Parsed& p, const std::string& bytes,
                             size_t pos, const std::vector<size_t>& sizes, int channels,
                             const std::string& type, const std::string& encoding,
                             bool big_endian) {
  const int bytes_per = element_bytes(type);
  const size_t frames = sizes.size() == 3 ? sizes[2] : 1;
  const size_t count = sizes[0] * sizes[1] * frames;
  if (count > (size_t(1) << 32)) throw Error(path + ": its sizes call for too many pixels");
  const size_t expected = count * size_t(channels) * size_t(bytes_per);
  const uint8_t* data = reinterpret_cast<const uint8_t*>(bytes.data()) + pos;
  const size_t available = bytes.size() - pos;
  std::vector<uint8_t> pixels;
  if (encoding == "zlib" || encoding == "gzip") {
    pixels = inflate_exactly(path, data, available, expected, encoding == "gzip");
  } else {
    if (available < expected) {
      throw Error(path + ": the image data holds " + std::to_string(available) + " bytes, its " +
                  "sizes call for " + std::to_string(expected));
    }
    pixels.assign(data, data + expected);
  }
  if (big_endian && bytes_per > 1) {
    for (size_t i = 0; i + size_t(bytes_per) <= pixels.size(); i += size_t(bytes_per)) {
      std::reverse(pixels.begin() + long(i), pixels.begin() + long(i) + bytes_per);
    }
  }
  const bool images = sizes[0] > 0 && sizes[1] > 0;
  return finish(path, p, images ? std::move(pixels) : std::vector<uint8_t>(),
                images ? int(sizes[0]) : 0, images ? int(sizes[1]) : 0, channels, type, frames);
}

PlusSequence read_metaimage(const std::string& path, const std::string& bytes) {
  size_t pos = 0;
  const std::vector<std::string> lines = header_lines(path, bytes, false, &pos);
  Parsed p;
  std::map<std::string, std::string> known;
  for (size_t i = 0; i < lines.size(); ++i) {
    const size_t eq = lines[i].find('=');
    if (eq == std::string::npos) {
      if (trim(lines[i]).empty()) continue;
      throw Error(path + ": header line " + std::to_string(i + 1) + " is not KEY = VALUE: '" +
                  lines[i] + "'");
    }
    const std::string key = trim(lines[i].substr(0, eq)), value = trim(lines[i].substr(eq + 1));
    static const std::set<std::string> kData = {
        "ObjectType", "NDims", "DimSize", "ElementType", "ElementNumberOfChannels", "CompressedData",
        "CompressedDataSize", "BinaryData", "BinaryDataByteOrderMSB", "ElementByteOrderMSB",
        "ElementDataFile", "HeaderSize"};
    if (kData.count(key)) {
      known[key] = value;
    } else {
      add_field(p, key, value);
    }
  }
  if (known["ObjectType"] != "Image" || !known.count("NDims") || !known.count("DimSize") ||
      !known.count("ElementType")) {
    throw Error(path + ": not a MetaImage sequence file (ObjectType Image, NDims, DimSize and "
                "ElementType expected)");
  }
  if (known["ElementDataFile"] != "LOCAL") {
    throw Error(path + ": its image data lies in another file ('" + known["ElementDataFile"] +
                "'): only sequence files holding their data (ElementDataFile = LOCAL) are read");
  }
  const size_t ndims = checked_count(path, "NDims", known["NDims"]);
  const std::vector<std::string> dims = words(known["DimSize"]);
  if ((ndims != 2 && ndims != 3) || dims.size() != ndims) {
    throw Error(path + ": NDims " + known["NDims"] + " and DimSize '" + known["DimSize"] +
                "': a sequence is 2D images over time (NDims 3) or one 2D image");
  }
  std::vector<size_t> sizes;
  for (const auto& d : dims) sizes.push_back(checked_count(path, "DimSize", d));
  const std::string type = known["ElementType"];
  const int bytes_per = element_bytes(type);
  if (bytes_per == 0) throw Error(path + ": ElementType '" + type + "' is not a pixel type");
  const int channels = known.count("ElementNumberOfChannels")
                           ? int(checked_count(path, "ElementNumberOfChannels",
                                               known["ElementNumberOfChannels"]))
                           : 1;
  if (channels < 1 || channels > 4) throw Error(path + ": " + std::to_string(channels) + " channels");
  const bool msb = known["BinaryDataByteOrderMSB"] == "True" || known["ElementByteOrderMSB"] == "True";
  return with_image_data(path, p, bytes, pos, sizes, channels, type,
                         known["CompressedData"] == "True" ? "zlib" : "raw", msb);
}

PlusSequence read_nrrd(const std::string& path, const std::string& bytes) {
  size_t pos = 0;
  const std::vector<std::string> lines = header_lines(path, bytes, true, &pos);
  Parsed p;
  std::map<std::string, std::string> fields;
  for (size_t i = 1; i < lines.size(); ++i) {
    const std::string& line = lines[i];
    if (line.empty() || line[0] == '#') continue;
    const size_t kv = line.find(":=");
    if (kv != std::string::npos) {
      add_field(p, line.substr(0, kv), line.substr(kv + 2));
      continue;
    }
    const size_t colon = line.find(": ");
    if (colon == std::string::npos) {
      throw Error(path + ": header line " + std::to_string(i + 1) +
                  " is neither 'field: value' nor 'key:=value': '" + line + "'");
    }
    const std::string field = line.substr(0, colon), value = trim(line.substr(colon + 2));
    static const std::set<std::string> kData = {"dimension", "type", "sizes", "encoding",
                                                "endian", "data file", "datafile",
                                                "byte skip", "line skip"};
    if (kData.count(field)) {
      fields[field] = value;
    } else {
      p.header.emplace_back(field, value);
    }
  }
  if (fields.count("data file") || fields.count("datafile")) {
    throw Error(path + ": its data lies in another file: only NRRD sequences holding their data "
                "are read");
  }
  if (fields.count("byte skip") || fields.count("line skip")) {
    throw Error(path + ": byte or line skips are not read in sequence files");
  }
  const size_t dimension = checked_count(path, "dimension", fields["dimension"]);
  const std::vector<std::string> dims = words(fields["sizes"]);
  if ((dimension != 2 && dimension != 3) || dims.size() != dimension) {
    throw Error(path + ": dimension " + fields["dimension"] + " and sizes '" + fields["sizes"] +
                "': a sequence is 2D images over time or one 2D image");
  }
  std::vector<size_t> sizes;
  for (const auto& d : dims) sizes.push_back(checked_count(path, "sizes", d));
  const std::string type = nrrd_element_type(fields["type"]);
  if (type.empty()) throw Error(path + ": type '" + fields["type"] + "' is not a pixel type");
  std::string encoding = fields["encoding"];
  if (encoding == "gz") encoding = "gzip";
  if (encoding != "gzip" && encoding != "raw") {
    throw Error(path + ": encoding '" + fields["encoding"] + "': sequence files are read raw or gzip");
  }
  return with_image_data(path, p, bytes, pos, sizes, 1, type, encoding, fields["endian"] == "big");
}

}  // namespace

std::string PlusFrame::field(const std::string& name) const {
  for (const auto& [key, value] : fields) {
    if (key == name) return value;
  }
  return {};
}

std::vector<std::string> PlusSequence::transform_names() const {
  std::set<std::string> names;
  for (const PlusFrame& f : frames)
    for (const auto& [name, t] : f.transforms) names.insert(name);
  return {names.begin(), names.end()};
}

int PlusSequence::bytes_per_pixel() const { return element_bytes(element_type); }

std::string plus_matrix_text(const Eigen::Matrix4d& m) {
  std::string text;
  char number[32];
  for (int k = 0; k < 16; ++k) {
    std::snprintf(number, sizeof(number), "%s%.10g", k ? " " : "", m(k / 4, k % 4));
    text += number;
  }
  return text;
}

std::string plus_tool_name(const std::string& name) {
  std::string out = name;
  if (!out.empty()) out[0] = char(std::toupper(static_cast<unsigned char>(out[0])));
  return out;
}

std::string plus_transform_name(const std::string& field) {
  const std::string suffix = "Transform";
  if (field.size() <= suffix.size() ||
      field.compare(field.size() - suffix.size(), suffix.size(), suffix) != 0) {
    return {};
  }
  const std::string name = field.substr(0, field.size() - suffix.size());
  return name.find("To") == std::string::npos ? std::string() : name;
}

PlusSequence read_plus_sequence(const std::string& path) {
  const std::string bytes = read_bytes(path);
  if (bytes.rfind("NRRD000", 0) == 0) return read_nrrd(path, bytes);
  return read_metaimage(path, bytes);
}

std::string plus_sequence_header(const PlusSequence& s) {
  const bool images = s.width > 0 && s.height > 0;
  std::ostringstream h;
  h << "ObjectType = Image\nNDims = 3\n";
  for (const auto& [key, value] : s.header) h << key << " = " << value << "\n";
  h << "BinaryData = True\nBinaryDataByteOrderMSB = False\nCompressedData = False\n"
    << "DimSize = " << (images ? s.width : 0) << " " << (images ? s.height : 0) << " "
    << s.frames.size() << "\n";
  if (s.channels != 1) h << "ElementNumberOfChannels = " << s.channels << "\n";
  h << "ElementType = " << s.element_type << "\n";
  char prefix[32];
  for (size_t f = 0; f < s.frames.size(); ++f) {
    std::snprintf(prefix, sizeof(prefix), "%s%04zu_", kFramePrefix, f);
    for (const auto& [name, value] : s.frames[f].fields) h << prefix << name << " = " << value << "\n";
  }
  h << "ElementDataFile = LOCAL\n";
  return h.str();
}

void write_plus_sequence(const std::string& path, const PlusSequence& s) {
  const int bytes_per = element_bytes(s.element_type);
  if (bytes_per == 0) throw Error(path + ": element type '" + s.element_type + "' is not a pixel type");
  const bool images = s.width > 0 && s.height > 0;
  const size_t expected = images ? size_t(s.width) * size_t(s.height) * s.frames.size() *
                                       size_t(s.channels) * size_t(bytes_per)
                                 : 0;
  if (s.pixels.size() != expected) {
    throw Error(path + ": " + std::to_string(s.pixels.size()) + " bytes of pixels for " +
                std::to_string(s.frames.size()) + " frames of " + std::to_string(s.width) + "x" +
                std::to_string(s.height) + ", expected " + std::to_string(expected));
  }
  std::string out = plus_sequence_header(s);
  out.append(reinterpret_cast<const char*>(s.pixels.data()), s.pixels.size());
  write_binary_file(path, out.data(), out.size());
}

}  // namespace crepuscular::recordings
