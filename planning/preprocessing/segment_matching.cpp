// Segment names -> vulnerability levels: one table per layer of a 3D Slicer segmentation.
#include "planning/preprocessing/segment_matching.hpp"

#include <algorithm>
#include <set>
#include <string>
#include <vector>

#include "foundation/error.hpp"

namespace crepuscular::planning {

namespace {

struct Excluded {
  std::string given;
  bool used = false;
};

bool is_excluded(const Segment& s, std::vector<Excluded>& excluded) {
  bool hit = false;
  for (Excluded& e : excluded) {
    if (e.given == s.id || structure_names_match(e.given, s.name)) {
      e.used = true;
      hit = true;
    }
  }
  return hit;
}

// The table of `segments`; names that match nothing are appended to `unmatched`.
VulnerabilityTable match(const std::vector<Segment>& segments, const VulnerabilityTable& table,
                         const std::string& source, std::vector<Excluded>& excluded,
                         std::vector<std::string>& unmatched) {
  if (table.levels.empty()) throw Error("vulnerability table '" + table.name + "' has no levels");
  VulnerabilityTable out;
  out.name = table.name + " (matched to the segments of " + source + ")";
  out.levels = table.levels;
  for (const Segment& s : segments) {
    for (const LabelClass& other : out.labels) {
      if (other.value == s.label_value) {
        throw Error(source + ": segments '" + other.name + "' and '" + s.name +
                    "' share label value " + std::to_string(s.label_value) +
                    " (expected unique values within a layer)");
      }
    }
    int level = 0;
    bool found = false;
    if (is_excluded(s, excluded)) {
      level = table.levels.front().level;
      found = true;
    } else {
      for (const LabelClass& entry : table.labels) {
        if (!structure_names_match(entry.name, s.name)) continue;
        level = found ? std::max(level, entry.level) : entry.level;
        found = true;
      }
    }
    if (!found) {
      unmatched.push_back(s.name);
      continue;
    }
    out.labels.push_back({s.label_value, s.name, level});
  }
  std::sort(out.labels.begin(), out.labels.end(),
            [](const LabelClass& a, const LabelClass& b) { return a.value < b.value; });
  return out;
}

std::string quoted_list(const std::vector<std::string>& names) {
  std::string s;
  for (const std::string& n : names) s += (s.empty() ? "'" : ", '") + n + "'";
  return s;
}

void report(const std::vector<std::string>& unmatched, const std::vector<Excluded>& excluded,
            const std::vector<Segment>& segments, const VulnerabilityTable& table,
            const std::string& source) {
  std::vector<std::string> unused;
  for (const Excluded& e : excluded) {
    if (!e.used) unused.push_back(e.given);
  }
  if (!unused.empty()) {
    std::vector<std::string> names;
    for (const Segment& s : segments) names.push_back(s.name);
    throw Error(source + ": no segment named " + quoted_list(unused) +
                " (segments: " + quoted_list(names) + ")");
  }
  if (unmatched.empty()) return;
  std::vector<std::string> table_names;
  for (const LabelClass& l : table.labels) table_names.push_back(l.name);
  throw Error(source + ": " + std::to_string(unmatched.size()) + " segment" +
              (unmatched.size() == 1 ? "" : "s") + " not in vulnerability table '" + table.name +
              "': " + quoted_list(unmatched) +
              " (names compare case-insensitively, spaces as underscores; table names: " +
              quoted_list(table_names) +
              "); rename the segments, add them to a table, or exclude them)");
}

}  // namespace

VulnerabilityTable match_segment_names(const std::vector<Segment>& segments,
                                       const VulnerabilityTable& table, const std::string& source,
                                       const std::vector<std::string>& excluded) {
  std::vector<Excluded> ex;
  for (const std::string& e : excluded) ex.push_back({e});
  std::vector<std::string> unmatched;
  VulnerabilityTable out = match(segments, table, source, ex, unmatched);
  report(unmatched, ex, segments, table, source);
  return out;
}

std::vector<VulnerabilityTable> layer_tables(const Segmentation& segmentation,
                                             const VulnerabilityTable& table,
                                             const std::vector<std::string>& excluded) {
  std::vector<Excluded> ex;
  for (const std::string& e : excluded) ex.push_back({e});
  std::vector<std::string> unmatched;
  std::vector<VulnerabilityTable> tables;
  for (size_t l = 0; l < segmentation.layers.size(); ++l) {
    tables.push_back(match(segmentation.segments_in_layer(int(l)), table,
                           segmentation.source + " layer " + std::to_string(l), ex, unmatched));
  }
  report(unmatched, ex, segmentation.segments, table, segmentation.source);
  return tables;
}

std::vector<LabelMapInput> segmentation_label_maps(const Segmentation& segmentation,
                                                   const std::vector<VulnerabilityTable>& tables) {
  if (tables.size() != segmentation.layers.size()) {
    throw Error(segmentation.source + ": " + std::to_string(tables.size()) + " tables for " +
                std::to_string(segmentation.layers.size()) + " layers");
  }
  std::vector<LabelMapInput> inputs;
  for (size_t l = 0; l < tables.size(); ++l) {
    inputs.push_back(
        {&segmentation.layers[l], &tables[l], segmentation.source + " layer " + std::to_string(l)});
  }
  return inputs;
}

}  // namespace crepuscular::planning
