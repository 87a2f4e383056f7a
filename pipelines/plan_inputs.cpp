// Label maps, segmentations and the tumor lesion -> blocking volume, tumor mask, scanned volume.
#include "pipelines/plan_inputs.hpp"

#include <algorithm>
#include <cctype>
#include <deque>
#include <chrono>
#include <filesystem>
#include <future>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/log.hpp"
#include "pipelines/job_inputs.hpp"
#include "planning/imaging/file_spec.hpp"
#include "planning/imaging/lesions.hpp"
#include "planning/imaging/segmentation.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/preprocessing/label_maps.hpp"
#include "planning/preprocessing/segment_matching.hpp"

namespace crepuscular::pipelines {

using namespace planning;  // NOLINT: the job drives the planning modules throughout

namespace {

bool is_file(const std::string& path) {
  std::error_code ec;
  return std::filesystem::exists(path, ec);
}

planning::FileSpec split(const std::string& spec, const std::string& role) {
  return split_file_spec(spec, role, is_file);
}

// The table of one label map: its own (":TABLE"), else the table file or preset of the plan, else
// vulnerability.json beside it.
ChosenTable table_for(const planning::FileSpec& spec, const PlanInputOptions& o) {
  if (spec.qualifier) {
    const auto names = VulnerabilityTable::preset_names();
    if (std::find(names.begin(), names.end(), *spec.qualifier) != names.end()) {
      return {VulnerabilityTable::preset(*spec.qualifier), "preset " + *spec.qualifier};
    }
    require_input(*spec.qualifier, "the vulnerability table of " + spec.path);
    return {VulnerabilityTable::load(*spec.qualifier), *spec.qualifier};
  }
  return choose_vulnerability_table(spec.path, o.vulnerability, o.preset);
}

// What the tumor spec names within this very label map (a label value or a segment name), when the
// tumor is part of it: that structure is the target, not an obstacle.
std::optional<std::string> tumor_part_of(const std::string& file, const PlanInputOptions& o) {
  if (o.tumor.empty()) return std::nullopt;
  const planning::FileSpec t = split(o.tumor, "tumor");
  std::error_code ec;
  if (!t.qualifier || !std::filesystem::equivalent(t.path, file, ec)) return std::nullopt;
  return t.qualifier;
}

struct LabelSources {
  std::deque<Volume<int32_t>> maps;  // deques: the inputs point into them
  std::deque<VulnerabilityTable> tables;
  std::deque<Segmentation> segmentations;
  std::deque<std::vector<VulnerabilityTable>> layer_tables;
  std::vector<LabelMapInput> inputs;
  nlohmann::json description = nlohmann::json::array();
};

void add_label_spec(const std::string& text, const PlanInputOptions& o, LabelSources& s) {
  const planning::FileSpec spec = split(text, "label map");
  require_input(spec.path, "a label map");
  const ChosenTable table = table_for(spec, o);
  if (is_segmentation_file(spec.path)) {
    spdlog::info("reading segmentation {}", spec.path);
    s.segmentations.push_back(read_segmentation(spec.path));
    const Segmentation& seg = s.segmentations.back();
    std::vector<std::string> tumor_segment;
    const std::optional<std::string> part = tumor_part_of(spec.path, o);
    if (part && !parse_label_value(*part)) tumor_segment.push_back(*part);
    s.layer_tables.push_back(layer_tables(seg, table.table, tumor_segment));
    for (const LabelMapInput& in : segmentation_label_maps(seg, s.layer_tables.back())) {
      s.inputs.push_back(in);
    }
    nlohmann::json segments = nlohmann::json::array();
    for (const Segment& g : seg.segments) {
      segments.push_back({{"name", g.name}, {"label_value", g.label_value}, {"layer", g.layer}});
    }
    s.description.push_back({{"file", spec.path}, {"kind", "3D Slicer segmentation"},
                             {"vulnerability_source", table.source}, {"segments", segments}});
    return;
  }
  spdlog::info("reading label map {}", spec.path);
  s.maps.push_back(read_label_map(spec.path, {o.series}));
  s.tables.push_back(table.table);
  const std::optional<std::string> part = tumor_part_of(spec.path, o);
  if (const std::optional<int> tumor_label = part ? parse_label_value(*part) : std::nullopt) {
    for (LabelClass& c : s.tables.back().labels) {
      if (c.value != *tumor_label) continue;
      spdlog::info("{}: label {} ('{}') is the tumor: it does not block", spec.path, c.value, c.name);
      c.level = s.tables.back().levels.front().level;
    }
  }
  s.inputs.push_back({&s.maps.back(), &s.tables.back(), spec.path});
  s.description.push_back({{"file", spec.path}, {"kind", "label map"},
                           {"vulnerability_source", table.source},
                           {"vulnerability", table.table.to_json()}});
}

void blocking_from_label_specs(const PlanInputOptions& o, PlanInputs& in) {
  LabelSources s;
  const auto t = std::chrono::steady_clock::now();
  for (const std::string& spec : o.labels) add_label_spec(spec, o, s);
  in.seconds["read_labels"] =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
  if (s.inputs.size() == 1 && s.segmentations.empty()) {
    // One plain map: on its own grid, exactly as always.
    const LabelMapInput& only = s.inputs.front();
    in.blocking = blocking_from_labels(*only.labels, *only.table, o.margin, only.source);
    in.coverage.add(only.labels->geometry(), only.source);
    // Kept for the plan's own files: moved, not copied (4 bytes a voxel), where it is ours.
    if (!s.maps.empty() && only.labels == &s.maps.back()) {
      in.labels = std::move(s.maps.back());
    } else {
      in.labels = *only.labels;
    }
  } else {
    const CombinedLabels c = combine_label_maps(s.inputs);
    in.blocking = blocking_from_labels(c.labels, c.table, o.margin, "the label maps");
    in.coverage = c.coverage;
    in.labels = c.labels;
  }
  in.blocking_source = s.inputs.front().source;
  in.preprocessing = {{"mode", "labels"}, {"label_maps", s.description},
                      {"margin_fwhm_mm", o.margin.fwhm_mm}};
  // plan.json readers of one map (slices, evaluate, guidance) find its table here.
  if (s.description.front().contains("vulnerability")) {
    in.preprocessing["vulnerability_source"] = s.description.front()["vulnerability_source"];
    in.preprocessing["vulnerability"] = s.description.front()["vulnerability"];
  }
}

void make_blocking(const PlanInputOptions& o, PlanInputs& in) {
  if (!o.blocking.empty()) {
    spdlog::info("reading blocking volume {}", o.blocking);
    in.blocking = read_volume<float>(o.blocking, {o.series});
    in.blocking_source = o.blocking;
    in.preprocessing = {{"mode", "ready blocking volume"}};
    in.coverage.add(in.blocking.geometry(), o.blocking);
  } else if (!o.labels.empty()) {
    blocking_from_label_specs(o, in);
  } else {
    spdlog::info("reading CT {} for thresholding", o.ct);
    const Volume<float> ct = read_volume<float>(o.ct, {o.series});
    in.blocking = blocking_from_ct(ct, o.ct_thresholds, o.margin);
    in.blocking_source = o.ct;
    in.preprocessing = {{"mode", "ct thresholds"},
                        {"bone_hu", o.ct_thresholds.bone_hu},
                        {"air_hu", o.ct_thresholds.air_hu},
                        {"impassable_per_mm", o.ct_thresholds.impassable_per_mm},
                        {"margin_fwhm_mm", o.margin.fwhm_mm}};
  }
  // A CT given beside labels or a blocking volume describes the anatomy too: part of the scan.
  // Only its grid is used: its header is read, not its voxels (a 513^3 CT took a second).
  if (!o.ct.empty() && (!o.labels.empty() || !o.blocking.empty())) {
    in.coverage.add(read_volume_geometry(o.ct, {o.series}), o.ct);
  }
  validate_blocking(in.blocking, in.blocking_source);
}

void read_tumor(const PlanInputOptions& o, PlanInputs& in) {
  const planning::FileSpec spec = split(o.tumor, "tumor");
  require_input(spec.path, "the tumor");
  Volume<uint8_t> mask;
  std::string what = spec.path;
  in.tumor_source = {{"file", spec.path}};
  if (!spec.qualifier) {
    spdlog::info("reading tumor mask {}", spec.path);
    mask = read_mask(spec.path, {o.series});
  } else if (const std::optional<int> value = parse_label_value(*spec.qualifier)) {
    spdlog::info("reading tumor label {} of {}", *value, spec.path);
    mask = label_mask(read_label_map(spec.path, {o.series}), *value, spec.path);
    what = spec.path + " label " + std::to_string(*value);
    in.tumor_source["label"] = *value;
  } else {
    if (!is_segmentation_file(spec.path)) {
      throw Error(spec.path + ": tumor label '" + *spec.qualifier +
                  "' is not a label value (1 to 65535); segment names need a 3D Slicer "
                  "segmentation (.seg.nrrd)");
    }
    const Segmentation seg = read_segmentation(spec.path);
    const Segment& segment = seg.find_segment(*spec.qualifier);
    mask = seg.segment_mask(segment);
    what = spec.path + " segment '" + segment.name + "'";
    in.tumor_source["segment"] = segment.name;
    in.tumor_source["label"] = segment.label_value;
  }
  const LesionSelection selection = o.lesion_at ? LesionSelection::at(*o.lesion_at)
                                    : o.lesion > 0 ? LesionSelection::by_rank(o.lesion)
                                                   : LesionSelection::only();
  SelectedLesion chosen = select_lesion(mask, selection, what);
  const Lesion& l = chosen.lesion;
  in.tumor_source["lesion"] = {{"rank", l.rank},
                               {"lesions_in_mask", chosen.lesion_count},
                               {"voxels", l.voxels},
                               {"volume_ml", l.volume_ml},
                               {"centroid_lps_mm", {l.centroid.x(), l.centroid.y(), l.centroid.z()}}};
  if (o.lesion_at) {
    in.tumor_source["lesion"]["selected_at_lps_mm"] = {o.lesion_at->x(), o.lesion_at->y(),
                                                       o.lesion_at->z()};
    in.tumor_source["lesion"]["distance_mm"] = chosen.distance_mm;
    if (chosen.distance_mm > 0.0) {
      spdlog::warn("{}: no lesion at the point given; the nearest lesion (#{}) is {:.1f} mm away",
                   what, l.rank, chosen.distance_mm);
    }
  }
  if (chosen.lesion_count > 1) {
    spdlog::info("{}: lesion #{} of {} ({:.2f} mL)", what, l.rank, chosen.lesion_count,
                 l.volume_ml);
  }
  in.tumor = std::move(chosen.mask);
}

}  // namespace

std::vector<std::string> label_files(const std::vector<std::string>& label_specs) {
  std::vector<std::string> files;
  for (const auto& s : label_specs) files.push_back(split(s, "label map").path);
  return files;
}

std::string tumor_file(const std::string& tumor_spec) {
  return tumor_spec.empty() ? std::string() : split(tumor_spec, "tumor").path;
}

namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

}  // namespace

void read_plan_tumor(const PlanInputOptions& o, PlanInputs& in) {
  const auto t = Clock::now();
  read_tumor(o, in);
  in.seconds["tumor"] = since(t);
}

void read_plan_blocking(const PlanInputOptions& o, PlanInputs& in) {
  const auto t = Clock::now();
  make_blocking(o, in);
  in.seconds["blocking"] = since(t);
}

PlanInputs read_plan_inputs(const PlanInputOptions& o) {
  PlanInputs in;
  // The tumor (reading, lesion selection) on its own thread while the blocking volume is made:
  // they share nothing except `seconds`, filled once both are done. A failure of the blocking is
  // reported first, as it would be in turn.
  PlanInputs tumor_part;
  std::future<void> tumor = std::async(std::launch::async, [&] { read_plan_tumor(o, tumor_part); });
  try {
    read_plan_blocking(o, in);
  } catch (...) {
    tumor.wait();
    throw;
  }
  tumor.get();
  in.tumor = std::move(tumor_part.tumor);
  in.tumor_source = std::move(tumor_part.tumor_source);
  in.seconds["tumor"] = tumor_part.seconds["tumor"];
  return in;
}

namespace {

// A path of phases.json relative to its folder (absolute ones stay), keeping a ":QUALIFIER".
std::string relative_to(const std::filesystem::path& base, const std::string& spec) {
  if (spec.empty()) return spec;
  const std::filesystem::path p(spec);
  return p.is_absolute() ? spec : (base / p).lexically_normal().string();
}

}  // namespace

PhaseList read_phase_list(const std::string& path) {
  PhaseList list;
  list.file = path;
  const nlohmann::json doc = read_json_file(path, "phase list");
  const JsonPath root(path);
  as_object(doc, root);
  const std::filesystem::path base = std::filesystem::path(path).parent_path();
  list.vulnerability = relative_to(base, optional_string(doc, "vulnerability", root, ""));
  list.preset = optional_string(doc, "preset", root, "");
  const JsonPath at = root.key("phases");
  const nlohmann::json& phases = as_array(required_field(doc, "phases", root), at);
  if (phases.size() < 2) {
    at.fail("lists " + std::to_string(phases.size()) +
            " phase(s), expected at least 2 (a single scan: plan it without --phases)");
  }
  for (size_t k = 0; k < phases.size(); ++k) {
    const JsonPath pk = at.index(k);
    const nlohmann::json& p = as_object(phases[k], pk);
    PlanPhase phase;
    phase.name = optional_string(p, "name", pk, k < 10 ? "phase0" + std::to_string(k)
                                                        : "phase" + std::to_string(k));
    for (const char c : phase.name) {
      if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_' && c != '-') {
        pk.key("name").fail("is \"" + phase.name +
                            "\", expected letters, digits, '_' or '-' (it names output files)");
      }
    }
    const nlohmann::json& labels = required_field(p, "labels", pk);
    if (labels.is_array()) {
      for (size_t i = 0; i < labels.size(); ++i) {
        phase.labels.push_back(relative_to(base, as_string(labels[i], pk.key("labels").index(i))));
      }
    } else {
      phase.labels.push_back(relative_to(base, as_string(labels, pk.key("labels"))));
    }
    phase.tumor = relative_to(base, required_string(p, "tumor", pk));
    phase.ct = relative_to(base, optional_string(p, "ct", pk, ""));
    for (const auto& f : label_files(phase.labels)) {
      if (!std::filesystem::exists(f)) pk.key("labels").fail("names " + f + ", which does not exist");
    }
    if (!std::filesystem::exists(tumor_file(phase.tumor))) {
      pk.key("tumor").fail("names " + tumor_file(phase.tumor) + ", which does not exist");
    }
    if (!phase.ct.empty() && !std::filesystem::exists(phase.ct)) {
      pk.key("ct").fail("names " + phase.ct + ", which does not exist");
    }
    for (const PlanPhase& earlier : list.phases) {
      if (earlier.name == phase.name) pk.key("name").fail("repeats \"" + phase.name + "\"");
    }
    list.phases.push_back(phase);
  }
  return list;
}

}  // namespace crepuscular::pipelines
