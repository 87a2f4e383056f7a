// Input specs FILE[:QUALIFIER]: the separator rules of file_spec.hpp.
#include "planning/imaging/file_spec.hpp"

#include <algorithm>
#include <cctype>
#include <string>

#include "foundation/error.hpp"

namespace crepuscular::planning {

namespace {

bool ends_with_volume_extension(const std::string& path) {
  std::string lower(path);
  std::transform(lower.begin(), lower.end(), lower.begin(),
                 [](unsigned char c) { return char(std::tolower(c)); });
  for (const char* ext : {".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd"}) {
    const std::string e(ext);
    if (lower.size() > e.size() && lower.compare(lower.size() - e.size(), e.size(), e) == 0) {
      return true;
    }
  }
  return false;
}

FileSpec split_at(const std::string& spec, size_t colon, const std::string& role) {
  FileSpec out{spec.substr(0, colon), spec.substr(colon + 1)};
  if (out.qualifier->empty()) {
    throw Error(role + " '" + spec + "': nothing after ':' (expected FILE or FILE:" +
                "QUALIFIER, e.g. a label value or a table name)");
  }
  if (out.path.empty()) {
    throw Error(role + " '" + spec + "': no file before ':'");
  }
  return out;
}

}  // namespace

FileSpec split_file_spec(const std::string& spec, const std::string& role,
                         const std::function<bool(const std::string&)>& is_file) {
  if (spec.empty()) throw Error(role + ": empty file name");
  if (is_file && is_file(spec)) return {spec, std::nullopt};
  for (size_t c = spec.find(':'); c != std::string::npos; c = spec.find(':', c + 1)) {
    if (ends_with_volume_extension(spec.substr(0, c))) return split_at(spec, c, role);
  }
  if (is_file) {
    for (size_t c = spec.find(':'); c != std::string::npos; c = spec.find(':', c + 1)) {
      if (c > 0 && is_file(spec.substr(0, c))) return split_at(spec, c, role);
    }
  }
  const size_t last = spec.rfind(':');
  if (last != std::string::npos && spec.find_first_of("/\\", last + 1) == std::string::npos) {
    return split_at(spec, last, role);
  }
  return {spec, std::nullopt};
}

std::optional<int> parse_label_value(const std::string& text) {
  if (text.empty() || text.size() > 5) return std::nullopt;
  if (!std::all_of(text.begin(), text.end(), [](unsigned char c) { return std::isdigit(c); })) {
    return std::nullopt;
  }
  const int value = std::stoi(text);
  if (value < 1 || value > 65535) return std::nullopt;
  return value;
}

}  // namespace crepuscular::planning
