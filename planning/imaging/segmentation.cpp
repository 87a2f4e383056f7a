// 3D Slicer segmentations (.seg.nrrd) through ITK's NrrdImageIO: header keys Segment<N>_* from and
// to the MetaDataDictionary, voxels as stored (one component per layer), converted to label maps.
#include "planning/imaging/segmentation.hpp"

#include <Eigen/Core>
#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <type_traits>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "planning/imaging/itk_image.hpp"
#include "planning/imaging/volume_io.hpp"

// ITK headers after itk_image.hpp, which has ITK use the system Eigen: one Eigen in this unit.
#include <itkImageFileWriter.h>
#include <itkMetaDataObject.h>
#include <itkNrrdImageIO.h>

namespace fs = std::filesystem;

namespace crepuscular::planning {

namespace {

constexpr int kMaxLabelValue = 65535;

std::string trimmed(const std::string& s) {
  const auto first = s.find_first_not_of(" \t\r\n");
  if (first == std::string::npos) return {};
  return s.substr(first, s.find_last_not_of(" \t\r\n") - first + 1);
}

std::string one_line(const itk::ExceptionObject& e) {
  std::string text = e.GetDescription();
  std::replace(text.begin(), text.end(), '\n', ' ');
  const auto innermost = text.rfind("[nrrd] ");  // teem nests its messages; the last says why
  if (innermost != std::string::npos) text = text.substr(innermost + 7);
  // Without ITK's "ITK ERROR: NrrdImageIO(0x...): " prefix.
  const auto itk_error = text.find("ITK ERROR: ");
  const auto after_class = text.find("): ", itk_error);
  if (itk_error != std::string::npos && after_class != std::string::npos) {
    text = text.substr(after_class + 3);
  }
  return trimmed(text);
}

std::string segment_key(int n, const char* field) {
  return "Segment" + std::to_string(n) + "_" + field;
}

std::optional<std::string> header_value(const itk::MetaDataDictionary& dict,
                                        const std::string& key) {
  std::string value;
  if (!dict.HasKey(key) || !itk::ExposeMetaData<std::string>(dict, key, value)) {
    return std::nullopt;
  }
  return trimmed(value);
}

// An integer header value in [lo, hi]; Error naming the file and the key otherwise.
int header_integer(const std::string& path, const std::string& key, const std::string& text, int lo,
                   int hi, const std::string& expected_extra = {}) {
  long long value = 0;
  size_t used = 0;
  bool ok = !text.empty();
  try {
    value = std::stoll(text, &used);
  } catch (const std::exception&) {
    ok = false;
  }
  if (!ok || used != text.size() || value < lo || value > hi) {
    throw Error(path + ": " + key + " is '" + text + "' (expected an integer " +
                std::to_string(lo) + " to " + std::to_string(hi) + expected_extra + ")");
  }
  return int(value);
}

// Segment<N>_Extent: "i0 i1 j0 j1 k0 k1" in file index coordinates (empty when i0 > i1 ...).
struct Extent {
  int64_t lo[3];
  int64_t hi[3];
  bool contains(const Index3& ijk) const {
    for (int a = 0; a < 3; ++a) {
      if (ijk[a] < lo[a] || ijk[a] > hi[a]) return false;
    }
    return true;
  }
};

Extent parse_extent(const std::string& path, const std::string& key, const std::string& text) {
  std::istringstream in(text);
  Extent e{};
  long long v[6];
  for (long long& x : v) {
    if (!(in >> x)) {
      throw Error(path + ": " + key + " is '" + text +
                  "' (expected six integers: i0 i1 j0 j1 k0 k1)");
    }
  }
  std::string rest;
  if (in >> rest) {
    throw Error(path + ": " + key + " is '" + text +
                "' (expected six integers: i0 i1 j0 j1 k0 k1)");
  }
  for (int a = 0; a < 3; ++a) {
    e.lo[a] = v[2 * a];
    e.hi[a] = v[2 * a + 1];
  }
  return e;
}

// Segment<N>_Color "r g b" with each in [0, 1]; nothing otherwise.
std::optional<std::array<double, 3>> parse_colour(const std::string& text) {
  std::istringstream in(text);
  std::array<double, 3> c{};
  for (double& x : c) {
    if (!(in >> x) || !(x >= 0.0 && x <= 1.0)) return std::nullopt;
  }
  std::string rest;
  if (in >> rest) return std::nullopt;
  return c;
}

// Reads every stored value (component fastest, as ITK orders them) into `raw`.
void read_raw(itk::NrrdImageIO& io, const std::string& path, std::vector<char>& raw) {
  const unsigned n = io.GetNumberOfDimensions();
  itk::ImageIORegion region(n);
  for (unsigned a = 0; a < n; ++a) {
    region.SetIndex(a, 0);
    region.SetSize(a, io.GetDimensions(a));
  }
  io.SetIORegion(region);
  raw.assign(size_t(io.GetImageSizeInBytes()), 0);
  try {
    const std::lock_guard<std::recursive_mutex> one_reader(image_read_mutex());
    io.Read(raw.data());
  } catch (const itk::ExceptionObject& e) {
    throw Error(path + ": cannot read the voxels (" + one_line(e) + ")");
  }
}

// Calls f(const S* values) with S the stored component type.
template <typename F>
void with_stored_values(const itk::NrrdImageIO& io, const std::vector<char>& raw,
                        const std::string& path, F&& f) {
  using C = itk::IOComponentEnum;
  const char* p = raw.data();
  switch (io.GetComponentType()) {
    case C::UCHAR:
      return f(reinterpret_cast<const uint8_t*>(p));
    case C::CHAR:
      return f(reinterpret_cast<const int8_t*>(p));
    case C::USHORT:
      return f(reinterpret_cast<const uint16_t*>(p));
    case C::SHORT:
      return f(reinterpret_cast<const int16_t*>(p));
    case C::UINT:
      return f(reinterpret_cast<const uint32_t*>(p));
    case C::INT:
      return f(reinterpret_cast<const int32_t*>(p));
    case C::ULONG:
    case C::ULONGLONG:
      return f(reinterpret_cast<const uint64_t*>(p));
    case C::LONG:
    case C::LONGLONG:
      return f(reinterpret_cast<const int64_t*>(p));
    case C::FLOAT:
      return f(reinterpret_cast<const float*>(p));
    case C::DOUBLE:
      return f(reinterpret_cast<const double*>(p));
    default:
      throw Error(path + ": voxel component type " +
                  itk::ImageIOBase::GetComponentTypeAsString(io.GetComponentType()) +
                  " is not supported (expected an integer type)");
  }
}

// A stored value as an integer; Error for a non-integral floating-point value.
template <typename S>
int64_t integer_value(S x, int64_t element, const std::string& path) {
  if constexpr (std::is_floating_point_v<S>) {
    if (!std::isfinite(x) || double(x) != std::round(double(x)) || std::abs(double(x)) > 1e9) {
      std::ostringstream m;
      m << path << ": voxel value " << x << " at element " << element
        << " is not an integer (expected label values 0 to " << kMaxLabelValue << ")";
      throw Error(m.str());
    }
  }
  return int64_t(x);
}

std::string list_segments(const std::vector<Segment>& segments) {
  std::string s;
  for (const Segment& seg : segments) {
    if (!s.empty()) s += ", ";
    s += "'" + seg.name + "' (ID " + seg.id + ", layer " + std::to_string(seg.layer) + ", value " +
         std::to_string(seg.label_value) + ")";
  }
  return s.empty() ? "none" : s;
}

// The file's NRRD ImageIO with its header read; Error when it is no readable NRRD file.
itk::NrrdImageIO::Pointer open_nrrd(const std::string& path) {
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) {
    throw Error(path + ": " + (fs::exists(path, ec) ? "not a file" : "no such file") +
                " (expected a 3D Slicer segmentation, .seg.nrrd)");
  }
  const std::lock_guard<std::recursive_mutex> one_reader(image_read_mutex());
  auto io = itk::NrrdImageIO::New();
  if (!io->CanReadFile(path.c_str())) {
    throw Error(path + ": not a NRRD file (expected a 3D Slicer segmentation, .seg.nrrd)");
  }
  io->SetFileName(path);
  try {
    io->ReadImageInformation();
  } catch (const itk::ExceptionObject& e) {
    throw Error(path + ": cannot read the NRRD header (" + one_line(e) + ")");
  }
  return io;
}

// Layout: 3D with one component per layer, or the obsolete 4D (4th axis = segment).
struct Layout {
  bool legacy_4d = false;
  int layer_count = 0;
};

Layout layout_of(const itk::NrrdImageIO& io, const std::string& path) {
  const unsigned dims = io.GetNumberOfDimensions();
  const unsigned components = io.GetNumberOfComponents();
  Layout layout;
  layout.layer_count = int(components);
  if (dims == 4 && io.GetDimensions(3) > 1) {
    if (components != 1) {
      throw Error(path + ": 4D image with " + std::to_string(components) +
                  " components per voxel (expected 3D with one component per layer, or the "
                  "obsolete 4D layout with one segment per 4th-axis index)");
    }
    layout.legacy_4d = true;
    layout.layer_count = int(io.GetDimensions(3));
  } else if (dims < 3 || dims > 4) {
    throw Error(path + ": image is " + std::to_string(dims) +
                "D (expected 3D, one component per layer)");
  }
  return layout;
}

std::string layers_text(int layer_count) {
  return std::to_string(layer_count) + " layer" + (layer_count == 1 ? "" : "s");
}

// Segment n's layer: the 4th-axis index in the obsolete layout, else Segment<n>_Layer, else n
// (Slicer's default: each segment in a layer of its own).
int segment_layer(const std::string& path, int n, const std::string& name,
                  const std::optional<std::string>& layer, const Layout& layout) {
  if (layout.legacy_4d) {
    if (n >= layout.layer_count) {
      throw Error(path + ": segment " + std::to_string(n) + " '" + name + "' has no volume (" +
                  std::to_string(layout.layer_count) + " along the 4th axis)");
    }
    return n;
  }
  if (layer) {
    return header_integer(path, segment_key(n, "Layer"), *layer, 0, layout.layer_count - 1,
                          " for a file of " + layers_text(layout.layer_count));
  }
  if (n >= layout.layer_count) {
    throw Error(path + ": " + segment_key(n, "Layer") + " is missing and the file holds " +
                layers_text(layout.layer_count) + " (expected a layer for every segment)");
  }
  return n;
}

// Segment n of the header with its extent (none in the obsolete layout); nothing when the header
// has no Segment<n>_ID, _Name, _LabelValue or _Layer key.
struct SegmentEntry {
  Segment segment;
  std::optional<Extent> extent;
};

std::optional<SegmentEntry> segment_entry(const itk::MetaDataDictionary& dict,
                                          const std::string& path, int n, const Layout& layout) {
  const auto id = header_value(dict, segment_key(n, "ID"));
  const auto name = header_value(dict, segment_key(n, "Name"));
  const auto value = header_value(dict, segment_key(n, "LabelValue"));
  const auto layer = header_value(dict, segment_key(n, "Layer"));
  if (!id && !name && !value && !layer) return std::nullopt;
  SegmentEntry entry;
  Segment& s = entry.segment;
  s.index = n;
  s.id = id.value_or("");
  s.name = name && !name->empty() ? *name : s.id;
  if (s.name.empty()) s.name = "Segment" + std::to_string(n);
  if (value) {
    s.label_value = header_integer(path, segment_key(n, "LabelValue"), *value, 1, kMaxLabelValue);
  }
  s.layer = segment_layer(path, n, s.name, layer, layout);
  if (const auto colour = header_value(dict, segment_key(n, "Color"))) {
    s.colour = parse_colour(*colour);
  }
  const auto extent = header_value(dict, segment_key(n, "Extent"));
  if (extent && !layout.legacy_4d) {
    entry.extent = parse_extent(path, segment_key(n, "Extent"), *extent);
  }
  return entry;
}

// Segments: N = 0, 1, ... while any Segment<N>_ key exists (Slicer itself counts Segment<N>_ID);
// their extents in the same order. Error on a label value repeated within a layer, or no segment.
void read_segments(const itk::MetaDataDictionary& dict, const std::string& path,
                   const Layout& layout, std::vector<Segment>& segments,
                   std::vector<std::optional<Extent>>& extents) {
  for (int n = 0;; ++n) {
    std::optional<SegmentEntry> entry = segment_entry(dict, path, n, layout);
    if (!entry) break;
    const Segment& s = entry->segment;
    extents.push_back(entry->extent);
    for (const Segment& other : segments) {
      if (other.layer == s.layer && other.label_value == s.label_value) {
        throw Error(path + ": " + segment_key(n, "LabelValue") + " is " +
                    std::to_string(s.label_value) + ", as for segment " +
                    std::to_string(other.index) + " '" + other.name + "' in the same layer " +
                    std::to_string(s.layer) + " (expected unique values within a layer)");
      }
    }
    segments.push_back(s);
  }
  if (segments.empty()) {
    throw Error(path +
                ": no segments in the header (no key Segment0_ID, Segment0_Name, "
                "Segment0_LabelValue or Segment0_Layer; expected a 3D Slicer segmentation; a plain "
                "label map needs a vulnerability table by label value)");
  }
}

// Every stored value; Error unless they are `voxels` x layer_count components.
std::vector<char> read_voxels(itk::NrrdImageIO& io, const std::string& path, int64_t voxels,
                              int layer_count) {
  std::vector<char> raw;
  read_raw(io, path, raw);
  const size_t component_bytes = io.GetComponentSize();
  if (component_bytes == 0 || raw.size() != size_t(voxels * layer_count) * component_bytes) {
    throw Error(path + ": holds " + std::to_string(raw.size()) + " bytes of voxels for " +
                std::to_string(voxels) + " voxels x " + std::to_string(layer_count) + " layers");
  }
  return raw;
}

// The label map of layer l: each voxel the label value of its segment, 0 elsewhere. Values no
// segment declares and voxels outside their segment's extent are left out, with a warning.
Volume<int32_t> layer_labels(const itk::NrrdImageIO& io, const std::vector<char>& raw,
                             const std::string& path, const ImageGeometry& g, const Layout& layout,
                             int l, const std::vector<Segment>& segments,
                             const std::vector<std::optional<Extent>>& extents) {
  const bool legacy_4d = layout.legacy_4d;
  const int layer_count = layout.layer_count;
  const int64_t voxels = g.voxel_count();
  // Value -> segment (position in segments).
  std::vector<int> segment_of_value(size_t(kMaxLabelValue) + 1, -1);
  for (size_t i = 0; i < segments.size(); ++i) {
    if (segments[i].layer != l) continue;
    // The obsolete 4D layout stores each segment as a binary volume: any value > 0 is inside.
    segment_of_value[size_t(legacy_4d ? 1 : segments[i].label_value)] = int(i);
  }
  Volume<int32_t> labels(g, 0);
  std::map<int64_t, int64_t> undeclared;  // value -> voxels
  int64_t outside_extent = 0;
  with_stored_values(io, raw, path, [&](const auto* stored) {
    for (int64_t v = 0; v < voxels; ++v) {
      const int64_t element = legacy_4d ? v + voxels * l : v * layer_count + l;
      int64_t x = integer_value(stored[element], element, path);
      if (x == 0) continue;
      if (legacy_4d) x = x > 0 ? 1 : x;
      const int i = x > 0 && x <= kMaxLabelValue ? segment_of_value[size_t(x)] : -1;
      if (i < 0) {
        ++undeclared[x];
        continue;
      }
      const auto& extent = extents[size_t(i)];
      if (extent && !extent->contains(g.index_of_offset(v))) {
        ++outside_extent;
        continue;
      }
      labels[v] = int32_t(segments[size_t(i)].label_value);
    }
  });
  for (const auto& [x, count] : undeclared) {
    spdlog::warn("{}: layer {} holds value {} in {} voxels, which no segment declares; ignored",
                 path, l, x, count);
  }
  if (outside_extent > 0) {
    spdlog::warn("{}: layer {}: {} labelled voxels outside their segment's extent; ignored", path,
                 l, outside_extent);
  }
  return labels;
}

}  // namespace

std::string normalized_structure_name(const std::string& name) {
  const std::string t = trimmed(name);
  std::string out;
  out.reserve(t.size());
  for (const unsigned char c : t) {
    if (c == ' ' || c == '_' || c == '\t') {
      if (out.empty() || out.back() != '_') out.push_back('_');
    } else {
      out.push_back(char(std::tolower(c)));
    }
  }
  return out;
}

bool structure_names_match(const std::string& a, const std::string& b) {
  return normalized_structure_name(a) == normalized_structure_name(b);
}

bool is_segmentation_file(const std::string& path) {
  std::string lower(path);
  std::transform(lower.begin(), lower.end(), lower.begin(),
                 [](unsigned char c) { return char(std::tolower(c)); });
  for (const std::string ext : {".seg.nrrd", ".seg.nhdr"}) {
    if (lower.size() > ext.size() && lower.compare(lower.size() - ext.size(), ext.size(), ext) == 0)
      return true;
  }
  return false;
}

std::vector<Segment> Segmentation::segments_in_layer(int layer) const {
  std::vector<Segment> out;
  for (const Segment& s : segments) {
    if (s.layer == layer) out.push_back(s);
  }
  return out;
}

const Segment& Segmentation::find_segment(const std::string& name_or_id) const {
  for (const Segment& s : segments) {
    if (s.id == name_or_id) return s;
  }
  const Segment* found = nullptr;
  int count = 0;
  for (const Segment& s : segments) {
    if (structure_names_match(s.name, name_or_id)) {
      found = &s;
      ++count;
    }
  }
  if (count == 1) return *found;
  throw Error(source + ": " +
              (count == 0 ? "no segment named '" + name_or_id + "'"
                          : std::to_string(count) + " segments named '" + name_or_id + "'") +
              " (segments: " + list_segments(segments) + ")");
}

Volume<uint8_t> Segmentation::segment_mask(const Segment& segment) const {
  if (segment.layer < 0 || size_t(segment.layer) >= layers.size()) {
    throw Error(source + ": segment '" + segment.name + "' is in layer " +
                std::to_string(segment.layer) + ", but the file holds " +
                std::to_string(layers.size()) + " layers");
  }
  const Volume<int32_t>& layer = layers[size_t(segment.layer)];
  Volume<uint8_t> mask(layer.geometry(), 0);
  const int64_t n = layer.voxel_count();
  for (int64_t v = 0; v < n; ++v) mask[v] = layer[v] == segment.label_value ? 1 : 0;
  return mask;
}

Segmentation read_segmentation(const std::string& path) {
  const itk::NrrdImageIO::Pointer io = open_nrrd(path);
  const Layout layout = layout_of(*io, path);
  const ImageGeometry g = geometry_of_image_io(*io, path);
  Segmentation seg;
  seg.source = path;
  std::vector<std::optional<Extent>> extents;
  read_segments(io->GetMetaDataDictionary(), path, layout, seg.segments, extents);
  const std::vector<char> raw = read_voxels(*io, path, g.voxel_count(), layout.layer_count);
  for (int l = 0; l < layout.layer_count; ++l) {
    seg.layers.push_back(layer_labels(*io, raw, path, g, layout, l, seg.segments, extents));
  }
  spdlog::debug("{}: {} segments in {} layers, {} x {} x {} voxels", path, seg.segments.size(),
                layout.layer_count, g.dims[0], g.dims[1], g.dims[2]);
  return seg;
}

namespace {

bool ends_with_segmentation_nrrd(const std::string& path) {
  const std::string ext = ".seg.nrrd";
  std::string lower = fs::path(path).filename().string();
  std::transform(lower.begin(), lower.end(), lower.begin(),
                 [](unsigned char c) { return char(std::tolower(c)); });
  return lower.size() > ext.size() &&
         lower.compare(lower.size() - ext.size(), ext.size(), ext) == 0;
}

// A number as a stream writes it, with every digit a double needs to come back unchanged.
std::string exact_text(double x) {
  std::ostringstream out;
  out.precision(std::numeric_limits<double>::max_digits10);
  out << x;
  return out.str();
}

// Error unless the specs have unique IDs and label values 1 to 255 and colours in [0, 1]; the
// position of each label value's segment in `segments` (-1: none) otherwise.
std::array<int, 256> check_segment_specs(const std::string& path,
                                         const std::vector<SegmentSpec>& segments) {
  if (segments.empty()) throw Error(path + ": cannot write a segmentation without segments");
  std::array<int, 256> segment_of_value;
  segment_of_value.fill(-1);
  for (size_t n = 0; n < segments.size(); ++n) {
    const SegmentSpec& s = segments[n];
    const std::string which = "segment " + std::to_string(n) + " '" + s.name + "'";
    if (s.id.empty()) throw Error(path + ": " + which + " has no ID (expected a unique ID)");
    for (size_t m = 0; m < n; ++m) {
      if (segments[m].id == s.id) {
        throw Error(path + ": " + which + " has the ID '" + s.id + "' of segment " +
                    std::to_string(m) + " (expected unique IDs)");
      }
    }
    if (s.label_value == 0) {
      throw Error(path + ": " + which + " has label value 0 (expected 1 to 255; 0 is no segment)");
    }
    if (segment_of_value[s.label_value] >= 0) {
      throw Error(path + ": " + which + " has label value " + std::to_string(s.label_value) +
                  ", as segment " + std::to_string(segment_of_value[s.label_value]) +
                  " (expected unique label values in the one layer)");
    }
    segment_of_value[s.label_value] = int(n);
    for (const double c : s.colour) {
      if (!(c >= 0.0 && c <= 1.0)) {
        throw Error(path + ": " + which + " has the colour component " + exact_text(c) +
                    " (expected red, green, blue in [0, 1])");
      }
    }
  }
  return segment_of_value;
}

}  // namespace

void write_segmentation(const std::string& path, const Volume<uint8_t>& labels,
                        const std::vector<SegmentSpec>& segments) {
  if (!ends_with_segmentation_nrrd(path)) {
    throw Error(path + ": cannot write a segmentation (expected a file name ending in .seg.nrrd)");
  }
  const ImageGeometry& g = labels.geometry();
  check_geometry(g, path);
  if (int64_t(labels.values().size()) != g.voxel_count()) {
    throw Error(path + ": cannot write (the label map holds " +
                std::to_string(labels.values().size()) + " values for " +
                std::to_string(g.voxel_count()) + " voxels)");
  }
  const std::array<int, 256> segment_of_value = check_segment_specs(path, segments);
  std::array<int64_t, 256> voxels_of_value{};
  for (const uint8_t v : labels.values()) ++voxels_of_value[v];
  for (int v = 1; v < 256; ++v) {
    if (voxels_of_value[size_t(v)] > 0 && segment_of_value[size_t(v)] < 0) {
      throw Error(path + ": " + std::to_string(voxels_of_value[size_t(v)]) +
                  " voxels hold the value " + std::to_string(v) +
                  ", which no segment declares (expected 0 or a segment's label value)");
    }
  }

  using Image = itk::Image<uint8_t, 3>;
  auto image = Image::New();
  set_image_geometry(*image, g);
  // The writer only reads the buffer; the container does not own it.
  image->GetPixelContainer()->SetImportPointer(const_cast<uint8_t*>(labels.data()),
                                               itk::SizeValueType(g.voxel_count()), false);
  itk::MetaDataDictionary& dict = image->GetMetaDataDictionary();
  const auto put = [&dict](const std::string& key, const std::string& value) {
    itk::EncapsulateMetaData<std::string>(dict, key, value);
  };
  put("Segmentation_MasterRepresentation", "Binary labelmap");
  put("Segmentation_ContainedRepresentationNames", "Binary labelmap|");
  put("Segmentation_ReferenceImageExtentOffset", "0 0 0");
  // Every segment's extent is the whole grid: Slicer reads a layer within the extent of its first
  // segment.
  const std::string extent = "0 " + std::to_string(g.dims[0] - 1) + " 0 " +
                             std::to_string(g.dims[1] - 1) + " 0 " + std::to_string(g.dims[2] - 1);
  for (size_t n = 0; n < segments.size(); ++n) {
    const SegmentSpec& s = segments[n];
    const auto key = [n](const char* field) { return segment_key(int(n), field); };
    put(key("ID"), s.id);
    put(key("Name"), s.name);
    put(key("NameAutoGenerated"), "0");
    put(key("Color"),
        exact_text(s.colour[0]) + " " + exact_text(s.colour[1]) + " " + exact_text(s.colour[2]));
    put(key("ColorAutoGenerated"), "0");
    put(key("Extent"), extent);
    put(key("Tags"), "");
    put(key("Layer"), "0");
    put(key("LabelValue"), std::to_string(int(s.label_value)));
  }

  write_file_atomically(path, [&](const std::string& temporary) {
    try {
      auto writer = itk::ImageFileWriter<Image>::New();
      writer->SetImageIO(itk::NrrdImageIO::New());
      writer->SetFileName(temporary);
      writer->SetInput(image);
      writer->SetUseCompression(true);  // gzip, as Slicer writes .seg.nrrd
      writer->SetCompressionLevel(1);
      writer->Update();
    } catch (const itk::ExceptionObject& e) {
      throw Error(path + ": cannot write (" + one_line(e) + ")");
    }
  });
  spdlog::debug("{}: wrote {} segments on {} x {} x {} voxels", path, segments.size(), g.dims[0],
                g.dims[1], g.dims[2]);
}

}  // namespace crepuscular::planning
