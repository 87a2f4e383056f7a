// Volume IO through ITK: NIfTI, NRRD, MetaImage files and DICOM series folders to Volume<T> and
// back. ITK is LPS like Volume, so the geometry is copied as is; every ITK error becomes an Error.
#include "planning/imaging/volume_io.hpp"
#include "planning/imaging/itk_image.hpp"
#include "planning/imaging/dicom_series.hpp"

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cctype>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <regex>
#include <sstream>
#include <string>
#include <tuple>
#include <system_error>
#include <type_traits>
#include <utility>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"

// ITK headers after ours: they are large and only planning/ sees them. ITK 5.2 bundles its own
// Eigen 3.3; itk_image.hpp (included above) tells ITK to use the system Eigen, which keeps one
// Eigen in this translation unit.
#include <itkGDCMImageIO.h>
#include <itkGDCMImageIOFactory.h>
#include <itkImage.h>
#include <itkImageFileReader.h>
#include <itkImageFileWriter.h>
#include <itkImageIOBase.h>
#include <itkImageIOFactory.h>
#include <itkImageSeriesReader.h>
#include <itkMetaImageIO.h>
#include <itkMetaImageIOFactory.h>
#include <itkNiftiImageIO.h>
#include <itkNiftiImageIOFactory.h>
#include <itkNrrdImageIO.h>
#include <itkNrrdImageIOFactory.h>
#include <itk_zlib.h>

namespace fs = std::filesystem;

namespace crepuscular::planning {

std::recursive_mutex& image_read_mutex() {
  static std::recursive_mutex mutex;
  return mutex;
}

namespace {

using Component = itk::IOComponentEnum;

// The project does not use ITK_USE_FILE, so nothing registers the IO factories for us.
void register_io_factories() {
  static std::once_flag once;
  std::call_once(once, [] {
    itk::NiftiImageIOFactory::RegisterOneFactory();
    itk::NrrdImageIOFactory::RegisterOneFactory();
    itk::MetaImageIOFactory::RegisterOneFactory();
    itk::GDCMImageIOFactory::RegisterOneFactory();
  });
}

// ITK's description on one line, without the "ITK ERROR: Class(0x...): " prefix; for NRRD only
// the innermost of teem's nested messages ("[nrrd] fn: ... [nrrd] fn: what went wrong").
std::string describe(const itk::ExceptionObject& e) {
  std::string text = e.GetDescription();
  std::replace(text.begin(), text.end(), '\n', ' ');
  static const std::regex kItkPrefix(R"(^\s*(ITK ERROR|itk::ERROR):\s*\w+\(0x[0-9a-fA-F]+\):\s*)");
  text = std::regex_replace(text, kItkPrefix, "");
  const auto innermost = text.rfind("[nrrd] ");
  if (innermost != std::string::npos) {
    static const std::regex kFunction(R"(^\w+:\s*)");
    text = std::regex_replace(text.substr(innermost + 7), kFunction, "");
  }
  const auto first = text.find_first_not_of(" \t");
  const auto last = text.find_last_not_of(" \t");
  return first == std::string::npos ? std::string("unknown ITK error")
                                    : text.substr(first, last - first + 1);
}

std::string voxel_text(const ImageGeometry& g, int64_t offset) {
  const Index3 ijk = g.index_of_offset(offset);
  std::ostringstream s;
  s << "voxel (" << ijk[0] << ", " << ijk[1] << ", " << ijk[2] << ")";
  return s.str();
}

std::string value_text(double value) {
  std::ostringstream s;
  s.precision(10);
  s << value;
  return s.str();
}

template <typename T>
const char* type_name() {
  if constexpr (std::is_same_v<T, uint8_t>) return "uint8";
  if constexpr (std::is_same_v<T, int16_t>) return "int16";
  if constexpr (std::is_same_v<T, int32_t>) return "int32";
  if constexpr (std::is_same_v<T, float>) return "float32";
  if constexpr (std::is_same_v<T, double>) return "float64";
  return "?";
}

// Geometry and pixel layout of a file as its ImageIO reports them; throws Error when the file is
// not a scalar 3D volume (a 4D file whose extra axes have size 1 counts as 3D).
ImageGeometry geometry_of_file(itk::ImageIOBase& io, const std::string& path) {
  const unsigned n = io.GetNumberOfDimensions();
  if (n < 3) {
    throw Error(path + ": image is " + std::to_string(n) + "D (expected a 3D volume)");
  }
  for (unsigned a = 3; a < n; ++a) {
    if (io.GetDimensions(a) != 1) {
      throw Error(path + ": image is " + std::to_string(n) + "D with " +
                  std::to_string(io.GetDimensions(a)) + " samples along axis " + std::to_string(a) +
                  " (expected a 3D volume)");
    }
  }
  if (io.GetNumberOfComponents() != 1) {
    throw Error(path + ": voxels have " + std::to_string(io.GetNumberOfComponents()) +
                " components (pixel type " +
                itk::ImageIOBase::GetPixelTypeAsString(io.GetPixelType()) +
                "; expected scalar values)");
  }
  return geometry_of_image_io(io, path);
}

// niftilib inside ITK 5.2 fills the missing part of a short data read with zeros and reports
// nothing, so a truncated .nii or .nii.gz would load as a partly empty volume. This checks the
// stored length against vox_offset + dims x bitpix from the header itself (ImageIO's size may be
// that of rescaled float values, not of the stored ones).
// The first bytes of a NIfTI-1 or NIfTI-2 file (gzip-compressed or not), its fields read in the
// file's byte order: sizeof_hdr (348 or 540) tells which order that is. `file` stays open after
// the header for a reader of the data.
struct NiftiHeader {
  std::unique_ptr<gzFile_s, int (*)(gzFile)> file{nullptr, &gzclose};
  unsigned char bytes[540] = {};
  int read = 0;
  bool swapped = false;

  // "" when at least a NIfTI-1 header's 348 bytes were read, else why not.
  std::string open(const std::string& path) {
    file.reset(gzopen(path.c_str(), "rb"));
    if (!file) return "cannot open the file";
    read = gzread(file.get(), bytes, sizeof bytes);
    if (read < 348) return "file ends inside the NIfTI header";
    int32_t stored_size;
    std::memcpy(&stored_size, bytes, 4);
    const int32_t reversed = int32_t(__builtin_bswap32(uint32_t(stored_size)));
    if (stored_size == 348 || stored_size == 540) {
      swapped = false;
    } else if (reversed == 348 || reversed == 540) {
      swapped = true;
    } else {
      // A damaged sizeof_hdr: niftilib then goes by dim[0] (1..7 in the file's byte order).
      int16_t dim0;
      std::memcpy(&dim0, bytes + 40, 2);
      swapped = !(dim0 >= 1 && dim0 <= 7);
    }
    return {};
  }
  template <typename T>
  T field(size_t at) const {
    unsigned char b[sizeof(T)];
    std::memcpy(b, bytes + at, sizeof(T));
    if (swapped) std::reverse(b, b + sizeof(T));
    T value;
    std::memcpy(&value, b, sizeof(T));
    return value;
  }
  bool nifti1() const {
    return field<int32_t>(0) == 348 && std::memcmp(bytes + 344, "n+1", 4) == 0;
  }
  bool nifti2() const {
    return field<int32_t>(0) == 540 && read == 540 && std::memcmp(bytes + 4, "n+2", 4) == 0;
  }
};

bool path_ends_with(const std::string& path, const std::string& suffix) {
  return path.size() >= suffix.size() &&
         path.compare(path.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// Bytes per voxel of a NIfTI datatype code (nifti1.h), 0 when the code is unknown.
int64_t nifti_datatype_bytes(int datatype) {
  switch (datatype) {
    case 2: case 256: return 1;             // uint8, int8
    case 4: case 512: return 2;             // int16, uint16
    case 128: return 3;                     // RGB24
    case 8: case 16: case 768: case 2304: return 4;  // int32, float32, uint32, RGBA32
    case 32: case 64: case 1024: case 1280: return 8;  // complex64, float64, int64, uint64
    case 1536: case 1792: return 16;        // float128, complex128
    case 2048: return 32;                   // complex256
    default: return 0;
  }
}

// Where a single-file NIfTI stores its voxels, from its header.
struct NiftiLayout {
  uint64_t vox_offset = 0;
  uint64_t data_bytes = 0;     // dims x bytes per voxel
  int datatype = 0;            // nifti1.h code: 16 float32, 64 float64, ...
  std::array<int64_t, 8> dim{};
  uint64_t needed() const { return vox_offset + data_bytes; }
};

// Fills `layout` from an opened header. Returns "" when it is filled, kNotChecked for header and
// data in separate files (.hdr/.img) or Analyze, else why the header cannot describe a volume.
constexpr const char* kNotChecked = "-";
std::string nifti_layout(const NiftiHeader& header, const std::string& path, NiftiLayout& layout) {
  const int32_t sizeof_hdr = header.field<int32_t>(0);
  double vox_offset = 0.0;
  int64_t bitpix = 0;
  std::array<int64_t, 8>& dim = layout.dim;
  if (header.nifti1()) {
    vox_offset = header.field<float>(108);
    bitpix = header.field<int16_t>(72);
    for (int d = 0; d < 8; ++d) dim[d] = header.field<int16_t>(40 + 2 * size_t(d));
  } else if (header.nifti2()) {
    vox_offset = double(header.field<int64_t>(168));
    bitpix = header.field<int16_t>(14);
    for (int d = 0; d < 8; ++d) dim[d] = header.field<int64_t>(16 + 8 * size_t(d));
  } else if (path_ends_with(path, ".nii") || path_ends_with(path, ".nii.gz")) {
    // A single-file NIfTI always says so; without the magic ITK takes it for Analyze 7.5 and
    // trusts its sizes (12 GB for a 364-byte file).
    return "not a NIfTI file: its header lacks the magic \"n+1\" or \"n+2\"";
  } else {
    return kNotChecked;
  }
  // niftilib sizes the data by the datatype code and ignores bitpix: go by the larger of the two.
  layout.datatype = header.nifti2() ? header.field<int16_t>(12) : header.field<int16_t>(70);
  uint64_t data_bytes =
      uint64_t(std::max<int64_t>({bitpix / 8, nifti_datatype_bytes(layout.datatype), 0}));
  for (int d = 1; d <= std::clamp<int64_t>(dim[0], 0, 7); ++d) {
    data_bytes *= uint64_t(std::max<int64_t>(dim[d], 1));
  }
  if (!(vox_offset >= double(sizeof_hdr) && vox_offset < 1e15)) {
    return "NIfTI vox_offset is " + value_text(vox_offset) + ", expected at least " +
           std::to_string(sizeof_hdr);
  }
  layout.vox_offset = uint64_t(vox_offset);
  layout.data_bytes = data_bytes;
  return {};
}

std::string nifti_length_problem(const std::string& path) {
  NiftiHeader header;
  const std::string unreadable = header.open(path);
  if (!unreadable.empty()) return unreadable;
  NiftiLayout layout;
  const std::string bad_layout = nifti_layout(header, path, layout);
  if (bad_layout == kNotChecked) return {};
  if (!bad_layout.empty()) return bad_layout;
  const uint64_t needed = layout.needed();

  std::ifstream raw(path, std::ios::binary);
  unsigned char magic[2] = {0, 0};
  raw.read(reinterpret_cast<char*>(magic), 2);
  if (magic[0] != 0x1f || magic[1] != 0x8b) {  // not gzip-compressed
    std::error_code ec;
    const uintmax_t size = fs::file_size(path, ec);
    if (!ec && size >= needed) return {};
  } else {
    // Fast path: a gzip stream ends with its uncompressed length modulo 2^32.
    unsigned char trailer[4];
    raw.seekg(-4, std::ios::end);
    if (raw.read(reinterpret_cast<char*>(trailer), 4)) {
      const uint32_t isize = uint32_t(trailer[0]) | uint32_t(trailer[1]) << 8 |
                             uint32_t(trailer[2]) << 16 | uint32_t(trailer[3]) << 24;
      if (isize == uint32_t(needed & 0xffffffffu)) return {};
    }
  }
  // Slow path (several gzip members, trailing bytes, or a damaged file): count what is there.
  uint64_t total = uint64_t(header.read);
  std::vector<char> buffer(1 << 20);
  int got = 0;
  while (total < needed &&
         (got = gzread(header.file.get(), buffer.data(), unsigned(buffer.size()))) > 0) {
    total += uint64_t(got);
  }
  if (total < needed) {
    return "file is truncated: " + std::to_string(total) + " bytes of header and data, expected " +
           std::to_string(needed);
  }
  return {};
}

// niftilib (nifti_read_buffer) sets NaN and infinite float voxels to 0 as it reads them ("bad
// floats were set to 0"), so a label map or CT with NaN voxels would plan as if they were 0. This
// reads the stored float32 or float64 values of a .nii or .nii.gz itself, in the file's byte
// order: "" when every voxel is finite (or the data are of an integer type, or shorter than the
// header says: nifti_length_problem reports that), else the first bad voxel, "[phase T, ]voxel
// (I, J, K) has value nan (expected a finite number)". One pass over the (decompressed) data.
std::string nifti_value_problem(const std::string& path, bool nan_allowed) {
  NiftiHeader header;
  if (!header.open(path).empty()) return {};
  NiftiLayout layout;
  if (!nifti_layout(header, path, layout).empty()) return {};
  if (layout.datatype != 16 && layout.datatype != 64) return {};
  const size_t bytes = layout.datatype == 16 ? 4 : 8;
  const uint64_t count = layout.data_bytes / bytes;
  std::vector<unsigned char> buffer(1 << 20);
  size_t have = 0;
  const uint64_t already = uint64_t(header.read);
  if (layout.vox_offset < already) {
    have = size_t(already - layout.vox_offset);
    std::memcpy(buffer.data(), header.bytes + layout.vox_offset, have);
  } else {
    for (uint64_t skip = layout.vox_offset - already; skip > 0;) {
      const int got = gzread(header.file.get(), buffer.data(),
                             unsigned(std::min<uint64_t>(skip, buffer.size())));
      if (got <= 0) return {};
      skip -= uint64_t(got);
    }
  }
  const auto value_at = [&](size_t at) {
    unsigned char b[8];
    std::memcpy(b, buffer.data() + at, bytes);
    if (header.swapped) std::reverse(b, b + bytes);
    if (bytes == 4) {
      float f;
      std::memcpy(&f, b, 4);
      return double(f);
    }
    double d;
    std::memcpy(&d, b, 8);
    return d;
  };
  uint64_t index = 0;
  for (;;) {
    const int got = gzread(header.file.get(), buffer.data() + have, unsigned(buffer.size() - have));
    if (got > 0) have += size_t(got);
    const size_t whole = have / bytes * bytes;
    for (size_t at = 0; at < whole && index < count; at += bytes, ++index) {
      const double v = value_at(at);
      if (std::isfinite(v) || (nan_allowed && std::isnan(v))) continue;
      const auto& dim = layout.dim;
      const auto extent = [&](int d) { return d <= dim[0] ? std::max<int64_t>(dim[d], 1) : 1; };
      const uint64_t per_volume = uint64_t(extent(1) * extent(2) * extent(3));
      const uint64_t in_volume = index % per_volume;
      std::ostringstream s;
      if (count > per_volume) s << "phase " << index / per_volume << ", ";
      s << "voxel (" << in_volume % uint64_t(extent(1)) << ", "
        << in_volume / uint64_t(extent(1)) % uint64_t(extent(2)) << ", "
        << in_volume / uint64_t(extent(1) * extent(2)) << ") has value " << value_text(v)
        << " (expected a finite number)";
      return s.str();
    }
    if (index >= count || got <= 0) return {};
    std::memmove(buffer.data(), buffer.data() + whole, have - whole);
    have -= whole;
  }
}

std::string trimmed(const std::string& text) {
  const auto first = text.find_first_not_of(" \t\r");
  if (first == std::string::npos) return {};
  return text.substr(first, text.find_last_not_of(" \t\r") - first + 1);
}

// Names the first key a text header repeats (its readers act on every occurrence).
constexpr const char* kRepeatedKey = " repeated";

// The "key: value" (NRRD) or "key = value" (MetaImage) fields of a text header; a repeated key
// is named under kRepeatedKey.
std::map<std::string, std::string> text_header(const std::string& path, char separator,
                                               size_t& data_start) {
  std::ifstream in(path, std::ios::binary);
  std::map<std::string, std::string> fields;
  std::string line;
  data_start = 0;
  int lines = 0;
  while (std::getline(in, line) && ++lines < 10000) {
    data_start += line.size() + 1;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (separator == ':' && line.empty()) break;  // NRRD: a blank line ends the header
    const auto at = separator == ':' ? line.find(": ") : line.find('=');
    if (at == std::string::npos) continue;
    const std::string key = trimmed(line.substr(0, at));
    if (line.find('\0') != std::string::npos && !fields.count(kRepeatedKey)) {
      fields[kRepeatedKey] = key.substr(0, key.find('\0'));  // its readers end the key there
    }
    if (fields.count(key) && !fields.count(kRepeatedKey)) fields[kRepeatedKey] = key;
    fields[key] = trimmed(line.substr(at + (separator == ':' ? 2 : 1)));
    if (separator == '=' && key == "ElementDataFile") break;
  }
  return fields;
}

// MetaIO (ITK 5.2) only prints "data not read completely" for short data, raw or compressed, and
// ITK returns the volume padded with zeros. This checks the stored data length from the header:
// the image size, or CompressedDataSize for compressed data.
std::string metaimage_length_problem(const std::string& path) {
  size_t data_start = 0;  // ElementDataFile is the last header field; data follow
  std::map<std::string, std::string> fields = text_header(path, '=', data_start);
  if (fields.count("ElementDataFile") == 0 || fields["BinaryData"] == "False") return {};
  uint64_t needed = 0;
  if (fields["CompressedData"] == "True") {
    if (fields.count("CompressedDataSize") == 0) return {};  // optional field; nothing to compare
    needed = std::stoull(fields["CompressedDataSize"]);
  } else {
    static const std::map<std::string, uint64_t> kElementSize = {
        {"MET_CHAR", 1},  {"MET_UCHAR", 1},     {"MET_SHORT", 2},      {"MET_USHORT", 2},
        {"MET_INT", 4},   {"MET_UINT", 4},      {"MET_LONG", 4},       {"MET_ULONG", 4},
        {"MET_FLOAT", 4}, {"MET_LONG_LONG", 8}, {"MET_ULONG_LONG", 8}, {"MET_DOUBLE", 8}};
    const auto size = kElementSize.find(fields["ElementType"]);
    if (size == kElementSize.end()) return {};
    needed = size->second;
    if (fields.count("ElementNumberOfChannels")) {
      needed *= std::stoull(fields["ElementNumberOfChannels"]);
    }
    std::istringstream dims(fields["DimSize"]);
    for (uint64_t d = 0; dims >> d;) needed *= d;
  }
  std::error_code ec;
  uint64_t available = 0;
  const std::string& data_file = fields["ElementDataFile"];
  if (data_file == "LOCAL") {
    const uintmax_t size = fs::file_size(path, ec);
    if (ec) return {};
    available = size > uintmax_t(data_start) ? size - uintmax_t(data_start) : 0;
  } else if (data_file.find_first_of(" %") == std::string::npos && data_file != "LIST") {
    const uintmax_t size = fs::file_size(fs::path(path).parent_path() / data_file, ec);
    if (ec) return {};  // ITK reports a missing data file itself
    const int64_t skip = fields.count("HeaderSize") ? std::stoll(fields["HeaderSize"]) : 0;
    available = size - std::min<uintmax_t>(size, uintmax_t(std::max<int64_t>(skip, 0)));
  } else {
    return {};  // slice lists: not checked here
  }
  if (available < needed) {
    return "file is truncated: " + std::to_string(available) + " bytes of data, expected " +
           std::to_string(needed);
  }
  return {};
}

// Header values the image libraries would abort on (ITK's vnl asserts finite matrices: SIGABRT)
// or replace in silence (a NIfTI pixdim of 0 or NaN becomes 1 mm), and NRRD sizes that would be
// allocated before the data are found missing. Checked before ITK reads the header.

// NIfTI-1 and NIfTI-2: pixdim of the spatial axes finite and > 0; quaternion, offsets and the
// sform rows finite.
std::string nifti_header_problem(const std::string& path) {
  NiftiHeader header;
  const std::string unreadable = header.open(path);
  if (!unreadable.empty()) return unreadable;
  const double sizeof_hdr = header.field<int32_t>(0);
  if (sizeof_hdr != 348 && sizeof_hdr != 540) {
    // Every NIfTI-1 and Analyze 7.5 header says 348, every NIfTI-2 header 540; niftilib reads a
    // damaged one all the same, and ITK may then abort on what it finds.
    return "NIfTI header: sizeof_hdr is " + value_text(sizeof_hdr) +
           ", expected 348 (NIfTI-1) or 540 (NIfTI-2): a damaged header";
  }
  // A NIfTI-2 header is 540 bytes with the magic "n+2" at byte 4. Anything else, even when
  // sizeof_hdr says 540, niftilib reads in the NIfTI-1 layout, so that is the layout checked.
  const bool v2 = sizeof_hdr == 540 && header.nifti2();
  const auto dim_at = [&](size_t d) {
    return v2 ? double(header.field<int64_t>(16 + 8 * d)) : double(header.field<int16_t>(40 + 2 * d));
  };
  const auto pixdim = [&](size_t d) {
    return v2 ? header.field<double>(104 + 8 * d) : double(header.field<float>(76 + 4 * d));
  };
  const size_t spatial = size_t(std::clamp(dim_at(0), 1.0, 3.0));
  for (size_t d = 1; d <= spatial; ++d) {
    const double p = pixdim(d);
    if (!std::isfinite(p) || p <= 0.0) {
      return "NIfTI header: pixdim[" + std::to_string(d) + "] (voxel size along axis " +
             std::to_string(d) + ") is " + value_text(p) + "; expected a finite size > 0 mm";
    }
  }
  // quatern_b, c, d, qoffset_x, y, z, then srow_x, srow_y, srow_z (4 each).
  static const char* kNames[] = {"quatern_b", "quatern_c", "quatern_d", "qoffset_x", "qoffset_y",
                                 "qoffset_z", "srow_x[0]", "srow_x[1]", "srow_x[2]", "srow_x[3]",
                                 "srow_y[0]", "srow_y[1]", "srow_y[2]", "srow_y[3]", "srow_z[0]",
                                 "srow_z[1]", "srow_z[2]", "srow_z[3]"};
  for (int k = 0; k < 18; ++k) {
    const double v = v2 ? header.field<double>(352 + 8 * size_t(k))
                        : double(header.field<float>(256 + 4 * size_t(k)));
    if (!std::isfinite(v)) {
      return std::string("NIfTI header: ") + kNames[k] + " (orientation and origin) is " +
             value_text(v) + "; expected a finite number";
    }
    // Beyond a kilometre the header is damaged; such values also stall ITK's SVD of the
    // orientation for minutes.
    if (std::fabs(v) > 1e6) {
      return std::string("NIfTI header: ") + kNames[k] + " (orientation and origin) is " +
             value_text(v) + "; expected at most 1e6 in magnitude (mm)";
    }
  }
  return {};
}

// Numbers of a header value ("(1.5,0,0) (0,1.5,0)", "0.7 0.7 2.5"); words such as "none" are
// left out. `bad` receives the first token that reads as NaN or infinity.
std::vector<double> header_numbers(const std::string& text, std::string* bad) {
  std::vector<double> out;
  std::string token;
  const auto flush = [&] {
    if (token.empty()) return;
    char* end = nullptr;
    const double v = std::strtod(token.c_str(), &end);
    if (end != token.c_str() && *end == '\0') {
      if (!std::isfinite(v) && bad && bad->empty()) *bad = token;
      out.push_back(v);
    }
    token.clear();
  };
  for (char c : text) {
    if (c == ' ' || c == ',' || c == '(' || c == ')' || c == '\t') {
      flush();
    } else {
      token += c;
    }
  }
  flush();
  return out;
}

std::string numbers_problem(const std::map<std::string, std::string>& fields,
                            std::initializer_list<const char*> keys, const char* format) {
  for (const char* key : keys) {
    const auto f = fields.find(key);
    if (f == fields.end()) continue;
    std::string bad;
    header_numbers(f->second, &bad);
    if (!bad.empty()) {
      return std::string(format) + " header: '" + key + "' holds " + bad +
             "; expected finite numbers";
    }
  }
  return {};
}

std::string nrrd_header_problem(const std::string& path) {
  size_t data_start = 0;
  const auto fields = text_header(path, ':', data_start);
  std::string problem = numbers_problem(
      fields, {"space origin", "space directions", "spacings", "thicknesses", "axis mins", "axis maxs"},
      "NRRD");
  if (!problem.empty()) return problem;
  for (const char* key : {"spacings"}) {
    const auto f = fields.find(key);
    if (f == fields.end()) continue;
    for (double v : header_numbers(f->second, nullptr)) {
      if (!(v > 0.0)) return std::string("NRRD header: '") + key + "' holds " + value_text(v) +
                             "; expected voxel sizes > 0 mm";
    }
  }
  const auto sizes = fields.find("sizes");
  if (sizes == fields.end()) return {};
  double voxels = 1.0;
  for (double v : header_numbers(sizes->second, nullptr)) {
    if (!(v >= 1.0)) return "NRRD header: 'sizes' holds " + value_text(v) + "; expected sizes >= 1";
    voxels *= v;
  }
  static const std::map<std::string, double> kBytes = {
      {"uchar", 1}, {"unsigned char", 1}, {"uint8", 1}, {"uint8_t", 1}, {"char", 1},
      {"signed char", 1}, {"int8", 1}, {"int8_t", 1}, {"short", 2}, {"ushort", 2},
      {"unsigned short", 2}, {"int16", 2}, {"uint16", 2}, {"int16_t", 2}, {"uint16_t", 2},
      {"int", 4}, {"uint", 4}, {"unsigned int", 4}, {"int32", 4}, {"uint32", 4},
      {"int32_t", 4}, {"uint32_t", 4}, {"float", 4}, {"double", 8}, {"longlong", 8},
      {"int64", 8}, {"uint64", 8}, {"int64_t", 8}, {"uint64_t", 8}};
  const auto type = fields.find("type");
  const double bytes = voxels * (type != fields.end() && kBytes.count(type->second)
                                     ? kBytes.at(type->second)
                                     : 1.0);
  const auto data_file = fields.find("data file");
  const auto datafile = data_file != fields.end() ? data_file : fields.find("datafile");
  if (datafile != fields.end()) return {};  // detached data: ITK checks its length
  std::error_code ec;
  const double stored = double(fs::file_size(path, ec)) - double(data_start);
  if (ec) return {};
  const auto encoding = fields.find("encoding");
  const std::string enc = encoding != fields.end() ? encoding->second : "raw";
  // Deflate packs at most about 1032 bytes into one; raw data are stored whole.
  const double least = enc == "raw" ? bytes : enc == "gzip" || enc == "gz" ? bytes / 1032.0 : 0.0;
  if (least > stored + 1.0) {
    return "NRRD header: 'sizes' declares " + value_text(voxels) + " voxels (" +
           value_text(bytes / 1e6) + " MB) but the file holds " + value_text(stored) +
           " bytes of data";
  }
  return {};
}

// A header field of whole numbers, each within [lo, hi], `count` of them (0: any number of
// them, at least one); "" when the field is absent or fine.
std::string integers_problem(const std::map<std::string, std::string>& fields, const char* key,
                             double lo, double hi, size_t count, const char* format) {
  const auto f = fields.find(key);
  if (f == fields.end()) return {};
  // Every token must be a number: MetaIO reads "8888\xf5..." as 8888 where a word is skipped here.
  std::vector<double> values;
  std::istringstream tokens(f->second);
  for (std::string token; tokens >> token;) {
    char* end = nullptr;
    const double v = std::strtod(token.c_str(), &end);
    values.push_back(end != token.c_str() && *end == '\0' ? v : std::nan(""));
  }
  const std::string expected = "; expected " + (count > 0 ? std::to_string(count) : std::string("")) +
                               (count == 1 ? " whole number" : " whole numbers") + " from " +
                               value_text(lo) + " to " + value_text(hi);
  if (values.empty() || (count > 0 && values.size() != count)) {
    return std::string(format) + " header: '" + key + "' is \"" + f->second.substr(0, 40) + "\"" +
           expected;
  }
  for (double v : values) {
    if (!(v >= lo && v <= hi) || v != std::floor(v)) {
      return std::string(format) + " header: '" + key + "' holds " + value_text(v) + expected;
    }
  }
  return {};
}

std::string metaimage_header_problem(const std::string& path) {
  // MetaIO reads a key up to the next '=', across line ends: a line without one makes the next
  // line's key part of its own ("NDims" + newline + "Offset = -10 20 5" set NDims to -10, and
  // MetaIO then read Offset's numbers for minutes).
  {
    std::ifstream in(path, std::ios::binary);
    std::string line;
    for (int number = 1; std::getline(in, line) && number < 10000; ++number) {
      const std::string text = trimmed(line);
      if (text.empty()) continue;
      const auto at = text.find('=');
      if (at == std::string::npos) {
        return "MetaImage header: line " + std::to_string(number) + " ('" +
               text.substr(0, std::min<size_t>(text.size(), 40)) + "') has no '= value'";
      }
      // MetaIO copies keys and text values into buffers of 255 characters without checking
      // their length.
      if (line.size() > 250) {
        return "MetaImage header: line " + std::to_string(number) + " is " +
               std::to_string(line.size()) + " characters long; MetaIO reads at most 250";
      }
      if (line.find('=') > 200) {
        return "MetaImage header: line " + std::to_string(number) + " has a key of " +
               std::to_string(line.find('=')) + " characters; expected a field name";
      }
      if (trimmed(text.substr(0, at)) == "ElementDataFile") break;
    }
  }
  size_t data_start = 0;
  const auto fields = text_header(path, '=', data_start);
  std::string problem = numbers_problem(
      fields, {"Offset", "Origin", "Position", "ElementSpacing", "ElementSize", "TransformMatrix",
               "Orientation", "Rotation", "CenterOfRotation"},
      "MetaImage");
  if (!problem.empty()) return problem;
  if (fields.count(kRepeatedKey)) {
    return "MetaImage header: '" + fields.at(kRepeatedKey) +
           "' appears more than once (or holds a NUL byte)";
  }
  // MetaIO takes a data file name with '%' for a numbered series "pattern first last step" and
  // divides by the step as it finds it (0 crashed it); a plan reads one data file.
  if (fields.count("ElementDataFile") && fields.at("ElementDataFile").find('%') != std::string::npos) {
    return "MetaImage header: ElementDataFile '" + fields.at("ElementDataFile") +
           "' names a numbered series of files; expected LOCAL or one data file";
  }
  // Counts MetaIO trusts for its loops and allocations (NDims of 10^96 hung it).
  size_t ndims = 0;
  problem = integers_problem(fields, "NDims", 1, 4, 1, "MetaImage");
  if (!problem.empty()) return problem;
  if (fields.count("NDims")) ndims = size_t(std::stod(fields.at("NDims")));
  for (const auto& [key, lo, hi, count] :
       {std::tuple<const char*, double, double, size_t>{"DimSize", 1, 1e6, ndims},
        {"ElementNumberOfChannels", 1, 64, 1},
        {"HeaderSize", -1, 1e15, 1},
        {"CompressedDataSize", 0, 1e15, 1}}) {
    problem = integers_problem(fields, key, lo, hi, count, "MetaImage");
    if (!problem.empty()) return problem;
  }
  for (const char* key : {"ElementSpacing", "ElementSize"}) {
    const auto f = fields.find(key);
    if (f == fields.end()) continue;
    for (double v : header_numbers(f->second, nullptr)) {
      if (!(v > 0.0)) return std::string("MetaImage header: '") + key + "' holds " +
                             value_text(v) + "; expected voxel sizes > 0 mm";
    }
  }
  return {};
}

std::string header_problem(const std::string& path, const char* io_class) {
  if (std::strcmp(io_class, "NiftiImageIO") == 0) return nifti_header_problem(path);
  if (std::strcmp(io_class, "NrrdImageIO") == 0) return nrrd_header_problem(path);
  if (std::strcmp(io_class, "MetaImageIO") == 0) return metaimage_header_problem(path);
  return {};
}

// Checks for short data that the format's library would pass over in silence (see above).
std::string length_problem(const std::string& path, const char* io_class) {
  if (std::strcmp(io_class, "NiftiImageIO") == 0) return nifti_length_problem(path);
  if (std::strcmp(io_class, "MetaImageIO") == 0) return metaimage_length_problem(path);
  return {};
}

// The check of the stored values that the format's library would change in silence (NIfTI
// floats, see nifti_value_problem), started on its own thread to run beside ITK's read of the
// same voxels; no check (an invalid future) for other formats. The voxels ITK read are used only
// once require_stored_values_fine has found nothing.
std::future<std::string> check_stored_values_aside(const std::string& path, const char* io_class,
                                                   bool nan_allowed = false) {
  if (std::strcmp(io_class, "NiftiImageIO") != 0) return {};
  return std::async(std::launch::async, nifti_value_problem, path, nan_allowed);
}

void require_stored_values_fine(std::future<std::string>& check, const std::string& path) {
  if (!check.valid()) return;
  const std::string problem = check.get();
  if (!problem.empty()) throw Error(path + ": " + problem);
}

// The grid of the first three axes (a 4D image's frames share it).
template <unsigned N>
ImageGeometry geometry_of_image(const itk::ImageBase<N>& image) {
  ImageGeometry g;
  const auto region = image.GetLargestPossibleRegion();
  itk::Point<double, N> origin;
  image.TransformIndexToPhysicalPoint(region.GetIndex(), origin);
  for (unsigned a = 0; a < 3; ++a) {
    g.dims[a] = int64_t(region.GetSize()[a]);
    g.spacing[a] = image.GetSpacing()[a];
    g.origin[a] = origin[a];
    for (unsigned r = 0; r < 3; ++r) g.direction(r, a) = image.GetDirection()[r][a];
  }
  return g;
}

// Runs an ITK reader under image_read_mutex.
template <typename Reader>
void update_in_turn(Reader& reader) {
  const std::lock_guard<std::recursive_mutex> one_reader(image_read_mutex());
  reader.Update();
}

template <typename S>
Volume<S> copy_pixels(const itk::Image<S, 3>& image, const ImageGeometry& geometry,
                      const std::string& path) {
  const auto size = image.GetLargestPossibleRegion().GetSize();
  for (unsigned a = 0; a < 3; ++a) {
    if (int64_t(size[a]) != geometry.dims[a]) {
      throw Error(path + ": cannot read (image size changed while reading)");
    }
  }
  Volume<S> out(geometry);
  const S* in = image.GetBufferPointer();
  S* to = out.data();
  const int64_t n = out.voxel_count();
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) to[i] = in[i];
  return out;
}

template <typename S>
Volume<S> read_file_pixels(const std::string& path, itk::ImageIOBase* io,
                           const ImageGeometry& geometry) {
  using Image = itk::Image<S, 3>;
  auto reader = itk::ImageFileReader<Image>::New();
  reader->SetImageIO(io);
  reader->SetFileName(path);
  update_in_turn(*reader);
  return copy_pixels<S>(*reader->GetOutput(), geometry, path);
}

template <typename S>
Volume<S> read_series_pixels(const std::string& path, const std::vector<std::string>& files) {
  using Image = itk::Image<S, 3>;
  auto reader = itk::ImageSeriesReader<Image>::New();
  reader->SetImageIO(itk::GDCMImageIO::New());
  reader->SetFileNames(files);
  update_in_turn(*reader);
  const ImageGeometry geometry = geometry_of_image(*reader->GetOutput());
  check_geometry(geometry, path);
  return copy_pixels<S>(*reader->GetOutput(), geometry, path);
}

template <typename S>
struct Tag {
  using type = S;
};

// Calls f(Tag<S>{}) with S the C++ type that holds the file's component type without loss.
template <typename F>
auto with_component_type(Component c, const std::string& path, F&& f) {
  switch (c) {
    case Component::UCHAR:
      return f(Tag<uint8_t>{});
    case Component::CHAR:
      return f(Tag<int8_t>{});
    case Component::USHORT:
      return f(Tag<uint16_t>{});
    case Component::SHORT:
      return f(Tag<int16_t>{});
    case Component::UINT:
      return f(Tag<uint32_t>{});
    case Component::INT:
      return f(Tag<int32_t>{});
    case Component::ULONG:
    case Component::ULONGLONG:
      return f(Tag<uint64_t>{});
    case Component::LONG:
    case Component::LONGLONG:
      return f(Tag<int64_t>{});
    case Component::FLOAT:
      return f(Tag<float>{});
    case Component::DOUBLE:
    case Component::LDOUBLE:
      return f(Tag<double>{});
    default:
      throw Error(path + ": cannot read (unknown voxel component type " +
                  itk::ImageIOBase::GetComponentTypeAsString(c) + ")");
  }
}

// The ImageIO of a file with its header read (checked first for values ITK would abort on).
itk::ImageIOBase::Pointer image_io_of(const std::string& path) {
  register_io_factories();
  const std::lock_guard<std::recursive_mutex> one_reader(image_read_mutex());
  std::error_code ec;
  const fs::file_status status = fs::status(path, ec);
  if (ec || !fs::exists(status)) throw Error(path + ": cannot read (file does not exist)");
  if (fs::is_directory(status)) return nullptr;  // a DICOM series: 3D
  if (!std::ifstream(path, std::ios::binary)) {
    throw Error(path + ": cannot read (no permission to open the file)");
  }
  // A file named as NIfTI, NRRD or MetaImage is read as that format only: when its own reader
  // refuses it, the factory would hand it to GDCM, which parses any bytes as DICOM and may
  // reserve gigabytes for one element of a damaged file before it gives up.
  itk::ImageIOBase::Pointer io;
  const char* format = nullptr;
  if (path_ends_with(path, ".nii") || path_ends_with(path, ".nii.gz") ||
      path_ends_with(path, ".hdr") || path_ends_with(path, ".img")) {
    io = itk::NiftiImageIO::New();
    format = "NIfTI";
  } else if (path_ends_with(path, ".nrrd") || path_ends_with(path, ".nhdr")) {
    io = itk::NrrdImageIO::New();
    format = "NRRD";
  } else if (path_ends_with(path, ".mha") || path_ends_with(path, ".mhd")) {
    io = itk::MetaImageIO::New();
    format = "MetaImage";
  }
  if (io && !io->CanReadFile(path.c_str())) {
    throw Error(path + ": cannot read (not a " + format + " file, or a damaged one)");
  }
  if (!io) io = itk::ImageIOFactory::CreateImageIO(path.c_str(), itk::IOFileModeEnum::ReadMode);
  if (!io) {
    throw Error(path + ": cannot read (not a NIfTI, NRRD, MetaImage or DICOM file, or a damaged one)");
  }
  io->SetFileName(path);
  const std::string bad_header = header_problem(path, io->GetNameOfClass());
  if (!bad_header.empty()) throw Error(path + ": cannot read (" + bad_header + ")");
  io->ReadImageInformation();
  return io;
}

// Opens `path` (file or DICOM folder), reads its voxels in their stored type S and returns
// convert(Volume<S>&&). Every failure is an Error naming `path`.
template <typename Convert>
auto read_native(const std::string& path, const VolumeReadOptions& options, Convert&& convert) {
  register_io_factories();
  std::error_code ec;
  const fs::file_status status = fs::status(path, ec);
  if (ec || !fs::exists(status)) {
    throw Error(path + ": cannot read (file does not exist)");
  }
  try {
    if (fs::is_directory(status)) {
      const std::vector<std::string> files = dicom_series_slices(path, options.dicom_series);
      std::unique_lock<std::recursive_mutex> one_reader(image_read_mutex());
      auto io = itk::GDCMImageIO::New();
      io->SetFileName(files.front());
      io->ReadImageInformation();
      if (io->GetNumberOfComponents() != 1) {
        throw Error(path + ": DICOM voxels have " + std::to_string(io->GetNumberOfComponents()) +
                    " components (expected scalar values, e.g. CT or MR)");
      }
      one_reader.unlock();  // the series' voxels are read under it again
      spdlog::debug("{}: reading DICOM series of {} files", path, files.size());
      return with_component_type(io->GetComponentType(), path, [&](auto tag) {
        using S = typename decltype(tag)::type;
        return convert(read_series_pixels<S>(path, files));
      });
    }
    itk::ImageIOBase::Pointer io = image_io_of(path);
    const ImageGeometry geometry = geometry_of_file(*io, path);
    const std::string short_data = length_problem(path, io->GetNameOfClass());
    if (!short_data.empty()) throw Error(path + ": cannot read (" + short_data + ")");
    spdlog::debug("{}: reading {} x {} x {} voxels ({})", path, geometry.dims[0], geometry.dims[1],
                  geometry.dims[2],
                  itk::ImageIOBase::GetComponentTypeAsString(io->GetComponentType()));
    std::future<std::string> values =
        check_stored_values_aside(path, io->GetNameOfClass(), options.nan_means_no_value);
    return with_component_type(io->GetComponentType(), path, [&](auto tag) {
      using S = typename decltype(tag)::type;
      Volume<S> native = read_file_pixels<S>(path, io.GetPointer(), geometry);
      require_stored_values_fine(values, path);
      return convert(std::move(native));
    });
  } catch (const Error&) {
    throw;
  } catch (const itk::ExceptionObject& e) {
    throw Error(path + ": cannot read (" + describe(e) + ")");
  } catch (const std::bad_alloc&) {
    throw Error(path + ": cannot read (out of memory)");
  } catch (const std::exception& e) {
    throw Error(path + ": cannot read (" + e.what() + ")");
  }
}

// True when every value of S is a value of T (both integer types).
template <typename S, typename T>
constexpr bool integer_range_fits() {
  if constexpr (!std::is_integral_v<S> || !std::is_integral_v<T>) {
    return false;
  } else if constexpr (std::is_signed_v<S> && !std::is_signed_v<T>) {
    return false;
  } else {
    return std::numeric_limits<S>::digits <= std::numeric_limits<T>::digits;
  }
}

// Values of S to T: exact when T holds every S; floating targets take the nearest value; integer
// targets take the nearest integer and reject values outside their range (naming the voxel).
template <typename T, typename S>
Volume<T> convert_values(Volume<S>&& in, const std::string& path) {
  if constexpr (std::is_same_v<S, T>) {
    return std::move(in);
  } else {
    Volume<T> out(in.geometry());
    const int64_t n = in.voxel_count();
    if constexpr (std::is_floating_point_v<T> || integer_range_fits<S, T>()) {
#pragma omp parallel for schedule(static)
      for (int64_t i = 0; i < n; ++i) out[i] = static_cast<T>(in[i]);
    } else {
      constexpr double lo = double(std::numeric_limits<T>::lowest());
      constexpr double hi = double(std::numeric_limits<T>::max());
      const auto rounded = [&](int64_t i) {
        return std::is_floating_point_v<S> ? std::round(double(in[i])) : double(in[i]);
      };
      // On every core; only a volume with a value out of range is searched again, in order,
      // for its first.
      int bad = 0;
#pragma omp parallel for schedule(static) reduction(| : bad)
      for (int64_t i = 0; i < n; ++i) {
        const double v = rounded(i);
        bad |= !(v >= lo && v <= hi);
        out[i] = bad ? T{} : static_cast<T>(v);
      }
      for (int64_t i = 0; bad && i < n; ++i) {
        const double v = rounded(i);
        if (!(v >= lo && v <= hi)) {
          throw Error(path + ": " + voxel_text(in.geometry(), i) + " has value " +
                      value_text(double(in[i])) + ", which does not fit in " + type_name<T>() +
                      " [" + value_text(lo) + ", " + value_text(hi) + "]");
        }
      }
    }
    return out;
  }
}

bool ends_with(const std::string& text, const std::string& suffix) {
  return text.size() >= suffix.size() &&
         text.compare(text.size() - suffix.size(), suffix.size(), suffix) == 0;
}

}  // namespace

template <typename T>
Volume<T> read_volume(const std::string& path, const VolumeReadOptions& options) {
  return read_native(path, options, [&](auto&& native) {
    return convert_values<T>(std::forward<decltype(native)>(native), path);
  });
}

Volume<int32_t> read_label_map(const std::string& path, const VolumeReadOptions& options) {
  return read_native(path, options, [&](auto&& native) {
    const int64_t n = native.voxel_count();
    const auto label = [&](int64_t i) {
      const double v = double(native[i]);
      return v >= 0.0 && v <= 65535.0 && v == std::floor(v);
    };
    // On every core; only a bad map is searched again, in order, for its first bad voxel.
    int bad = 0;
#pragma omp parallel for schedule(static) reduction(| : bad)
    for (int64_t i = 0; i < n; ++i) bad |= !label(i);
    for (int64_t i = 0; bad && i < n; ++i) {
      if (!label(i)) {
        throw Error(path + ": " + voxel_text(native.geometry(), i) + " has value " +
                    value_text(double(native[i])) + " (expected an integer label in [0, 65535])");
      }
    }
    return convert_values<int32_t>(std::forward<decltype(native)>(native), path);
  });
}

Volume<uint8_t> read_mask(const std::string& path, const VolumeReadOptions& options) {
  return read_native(path, options, [&](auto&& native) {
    Volume<uint8_t> mask(native.geometry());
    const int64_t n = native.voxel_count();
    for (int64_t i = 0; i < n; ++i) {
      const double v = double(native[i]);
      if (!std::isfinite(v)) {  // NaN would read as background in silence
        throw Error(path + ": " + voxel_text(native.geometry(), i) + " has value " +
                    value_text(v) + " (expected a mask: 0 outside, 1 inside)");
      }
      mask[i] = v > 0.5 ? 1 : 0;
    }
    return mask;
  });
}

ImageGeometry read_volume_geometry(const std::string& path, const VolumeReadOptions& options) {
  try {
    const itk::ImageIOBase::Pointer io = image_io_of(path);
    if (!io) return read_volume<float>(path, options).geometry();  // a DICOM series: its slices place it
    return geometry_of_file(*io, path);
  } catch (const Error&) {
    throw;
  } catch (const itk::ExceptionObject& e) {
    throw Error(path + ": cannot read (" + describe(e) + ")");
  }
}

int volume_frames(const std::string& path) {
  try {
    const itk::ImageIOBase::Pointer io = image_io_of(path);
    if (!io || io->GetNumberOfDimensions() < 4) return 1;
    for (unsigned a = 4; a < io->GetNumberOfDimensions(); ++a) {
      if (io->GetDimensions(a) != 1) {
        throw Error(path + ": image is " + std::to_string(io->GetNumberOfDimensions()) + "D with " +
                    std::to_string(io->GetDimensions(a)) + " samples along axis " +
                    std::to_string(a) + " (expected 3D, or 4D with phases along the 4th axis)");
      }
    }
    return int(io->GetDimensions(3));
  } catch (const Error&) {
    throw;
  } catch (const itk::ExceptionObject& e) {
    throw Error(path + ": cannot read (" + describe(e) + ")");
  }
}

void split_volume_frames(const std::string& path, const std::vector<std::string>& frame_paths) {
  using Image4 = itk::Image<float, 4>;
  try {
    const itk::ImageIOBase::Pointer io = image_io_of(path);
    if (!io || io->GetNumberOfDimensions() < 4 ||
        int(io->GetDimensions(3)) != int(frame_paths.size())) {
      throw Error(path + ": cannot split into " + std::to_string(frame_paths.size()) +
                  " phases (not a 4D volume of that many frames)");
    }
    if (io->GetNumberOfComponents() != 1) {
      throw Error(path + ": voxels have " + std::to_string(io->GetNumberOfComponents()) +
                  " components (expected scalar values)");
    }
    const std::string short_data = length_problem(path, io->GetNameOfClass());
    if (!short_data.empty()) throw Error(path + ": cannot read (" + short_data + ")");
    std::future<std::string> values = check_stored_values_aside(path, io->GetNameOfClass());
    auto reader = itk::ImageFileReader<Image4>::New();
    reader->SetImageIO(io);
    reader->SetFileName(path);
    update_in_turn(*reader);
    require_stored_values_fine(values, path);
    const Image4& image = *reader->GetOutput();
    const ImageGeometry g = geometry_of_image(image);
    check_geometry(g, path);
    const int64_t per_frame = g.voxel_count();
    for (size_t t = 0; t < frame_paths.size(); ++t) {
      Volume<float> frame(g);
      const float* first = image.GetBufferPointer() + int64_t(t) * per_frame;
      for (int64_t i = 0; i < per_frame; ++i) {
        if (!std::isfinite(first[i])) {
          throw Error(path + ": phase " + std::to_string(t) + ", " + voxel_text(g, i) +
                      " has value " + value_text(first[i]) + " (expected a finite number)");
        }
      }
      std::copy_n(first, per_frame, frame.data());
      write_volume(frame, frame_paths[t]);
    }
  } catch (const Error&) {
    throw;
  } catch (const itk::ExceptionObject& e) {
    throw Error(path + ": cannot read (" + describe(e) + ")");
  } catch (const std::bad_alloc&) {
    throw Error(path + ": cannot read (out of memory)");
  }
}

void write_volume_frames(const std::vector<Volume<float>>& frames, const std::string& path) {
  register_io_factories();
  if (frames.empty()) throw Error(path + ": cannot write (no frames)");
  const ImageGeometry& g = frames.front().geometry();
  check_geometry(g, path);
  for (const Volume<float>& f : frames) {
    if (!f.geometry().same_grid(g, 0.0)) {
      throw Error(path + ": cannot write (the frames lie on different grids)");
    }
  }
  if (!ends_with(path, ".nii.gz") && !ends_with(path, ".nii")) {
    throw Error(path + ": cannot write (4D volumes are written as .nii.gz or .nii)");
  }
  using Image4 = itk::Image<float, 4>;
  auto image = Image4::New();
  Image4::SizeType size;
  Image4::SpacingType spacing;
  Image4::PointType origin;
  Image4::DirectionType direction;
  direction.SetIdentity();
  for (unsigned a = 0; a < 3; ++a) {
    size[a] = itk::SizeValueType(g.dims[a]);
    spacing[a] = g.spacing[a];
    origin[a] = g.origin[a];
    for (unsigned r = 0; r < 3; ++r) direction[r][a] = g.direction(r, a);
  }
  size[3] = itk::SizeValueType(frames.size());
  spacing[3] = 1.0;
  origin[3] = 0.0;
  image->SetRegions(Image4::RegionType(size));
  image->SetSpacing(spacing);
  image->SetOrigin(origin);
  image->SetDirection(direction);
  image->Allocate();
  for (size_t t = 0; t < frames.size(); ++t) {
    std::copy_n(frames[t].data(), g.voxel_count(),
                image->GetBufferPointer() + int64_t(t) * g.voxel_count());
  }
  write_file_atomically(path, [&](const std::string& temporary) {
    try {
      auto writer = itk::ImageFileWriter<Image4>::New();
      writer->SetFileName(temporary);
      writer->SetInput(image);
      writer->SetUseCompression(!ends_with(path, ".nii"));
      writer->SetCompressionLevel(1);
      writer->Update();
    } catch (const itk::ExceptionObject& e) {
      throw Error(path + ": cannot write (" + describe(e) + ")");
    }
  });
}

template <typename T>
void write_volume(const Volume<T>& volume, const std::string& path) {
  register_io_factories();
  const ImageGeometry& g = volume.geometry();
  check_geometry(g, path);
  if (int64_t(volume.values().size()) != g.voxel_count()) {
    throw Error(path + ": cannot write (volume holds " + std::to_string(volume.values().size()) +
                " values for " + std::to_string(g.voxel_count()) + " voxels)");
  }
  std::string lower = fs::path(path).filename().string();
  std::transform(lower.begin(), lower.end(), lower.begin(),
                 [](unsigned char c) { return char(std::tolower(c)); });
  if (!ends_with(lower, ".nii.gz") && !ends_with(lower, ".nii") && !ends_with(lower, ".nrrd") &&
      !ends_with(lower, ".mha")) {
    // .nhdr and .mhd are left out on purpose: their header names a separate data file, which
    // the write-then-rename scheme would leave pointing at the temporary name.
    throw Error(path +
                ": cannot write (unsupported extension; expected .nii.gz, .nii, .nrrd or "
                ".mha)");
  }
  const fs::path parent = fs::path(path).has_parent_path() ? fs::path(path).parent_path() : ".";
  std::error_code ec;
  if (!fs::is_directory(parent, ec)) {
    throw Error(path + ": cannot write (folder " + parent.string() + " does not exist)");
  }

  using Image = itk::Image<T, 3>;
  auto image = Image::New();
  set_image_geometry(*image, g);
  // The writer only reads the buffer; the container does not own it.
  image->GetPixelContainer()->SetImportPointer(const_cast<T*>(volume.data()),
                                               itk::SizeValueType(g.voxel_count()), false);

  write_file_atomically(path, [&](const std::string& temporary) {
    std::string problem;
    try {
      auto writer = itk::ImageFileWriter<Image>::New();
      writer->SetFileName(temporary);
      writer->SetInput(image);
      // .nii stays uncompressed by definition; NRRD and MetaImage compress their data
      // (gzip/zlib), which 3D Slicer and ITK read back.
      writer->SetUseCompression(!ends_with(lower, ".nii"));
      // zlib level 1: several times faster than the default at about 10 % more bytes; a plan's
      // volumes are written while the radiologist waits.
      writer->SetCompressionLevel(1);
      writer->Update();
      // niftilib cannot report a failed or short write to ITK (nifti_image_write returns
      // nothing), and MetaIO may only print it: check what reached the disk before it takes the
      // final name.
      problem = fs::is_regular_file(temporary, ec)
                    ? length_problem(temporary, writer->GetImageIO()->GetNameOfClass())
                    : "the " + std::string(writer->GetImageIO()->GetNameOfClass()) +
                          " writer produced no file";
    } catch (const itk::ExceptionObject& e) {
      problem = describe(e);
    } catch (const std::bad_alloc&) {
      problem = "out of memory (or the ITK writer failed without saying why)";
    } catch (const std::exception& e) {
      problem = e.what();
    }
    if (!problem.empty()) throw Error(path + ": cannot write (" + problem + ")");
  });
  spdlog::debug("{}: wrote {} x {} x {} voxels ({})", path, g.dims[0], g.dims[1], g.dims[2],
                type_name<T>());
}

template Volume<uint8_t> read_volume<uint8_t>(const std::string&, const VolumeReadOptions&);
template Volume<int16_t> read_volume<int16_t>(const std::string&, const VolumeReadOptions&);
template Volume<int32_t> read_volume<int32_t>(const std::string&, const VolumeReadOptions&);
template Volume<float> read_volume<float>(const std::string&, const VolumeReadOptions&);
template Volume<double> read_volume<double>(const std::string&, const VolumeReadOptions&);

template void write_volume<uint8_t>(const Volume<uint8_t>&, const std::string&);
template void write_volume<int16_t>(const Volume<int16_t>&, const std::string&);
template void write_volume<int32_t>(const Volume<int32_t>&, const std::string&);
template void write_volume<float>(const Volume<float>&, const std::string&);

}  // namespace crepuscular::planning
