// Input specs of the form FILE[:QUALIFIER] (a label map and its table, a tumor file and its label):
// where the file name ends and the qualifier begins, even when paths hold ':' themselves.
#pragma once

#include <functional>
#include <optional>
#include <string>

namespace crepuscular::planning {

struct FileSpec {
  std::string path;
  std::optional<std::string> qualifier;  // the text after the separating ':', never empty
};

// Splits "FILE[:QUALIFIER]". The separator is, in this order of preference:
//  1. none, when `is_file` is given and says the whole spec is a file;
//  2. the first ':' whose head ends with a volume extension (.nii, .nii.gz, .nrrd, .nhdr, .mha,
//     .mhd, any case), so "labels.nii.gz:/tables/mine.json" and "C:/x/labels.nii.gz:5" split
//     after the volume;
//  3. the first ':' whose head `is_file` accepts, when given;
//  4. the last ':' whose tail holds no '/' or '\' ("C:\scans\labels" and "/data/a:b/labels" are
//     whole paths).
// Pure apart from `is_file`. Throws Error naming `role` (e.g. "tumor") when the spec is empty or
// the qualifier after the separator is empty.
FileSpec split_file_spec(const std::string& spec, const std::string& role,
                         const std::function<bool(const std::string&)>& is_file = {});

// A label value given as text ("5"): an integer in [1, 65535]; nullopt for anything else (e.g. a
// segment name of a 3D Slicer segmentation).
std::optional<int> parse_label_value(const std::string& text);

}  // namespace crepuscular::planning
