// Where a run may write: outputs against inputs, against each other, and against folders of
// other commands.
#include "foundation/run_paths.hpp"

#include <filesystem>
#include <optional>
#include <system_error>

#include "foundation/error.hpp"
#include "foundation/output_files.hpp"

namespace fs = std::filesystem;

namespace crepuscular {

namespace {

// Absolute, symlinks resolved as far as the path exists, "." and ".." gone, no trailing "/".
fs::path resolved(const std::string& path) {
  std::error_code ec;
  fs::path p = fs::absolute(path, ec);
  if (ec) p = path;
  const fs::path canonical = fs::weakly_canonical(p, ec);
  if (!ec) p = canonical;
  p = p.lexically_normal();
  if (!p.has_filename() && p.has_parent_path() && p != p.root_path()) p = p.parent_path();
  return p;
}

// True when `inner` lies strictly inside `outer`.
bool inside(const fs::path& inner, const fs::path& outer) {
  auto i = inner.begin();
  for (auto o = outer.begin(); o != outer.end(); ++o, ++i) {
    if (i == inner.end() || *i != *o) return false;
  }
  return i != inner.end();
}

std::string named(const std::string& flag, const std::string& path) {
  return flag + " " + path;
}

std::string check_against_input(const RunOutput& out, const fs::path& o, const RunInput& in,
                                 const fs::path& i) {
  const std::string head = named(out.flag, out.path) + ": ";
  if (o == i) {
    return head + "is the input " + named(in.flag, in.path) +
           "; an output never replaces the run's inputs: give " + out.flag +
           " a path of its own";
  }
  if (inside(i, o) && out.kind != OutputKind::kFilesInFolder) {
    return head + "holds the input " + named(in.flag, in.path) +
           "; an output never replaces the run's inputs: give " + out.flag +
           " a folder that holds none of them";
  }
  if (inside(o, i)) {
    return head + "lies inside the input " + named(in.flag, in.path) +
           "; outputs are never written into the run's inputs: give " + out.flag +
           " a path outside it";
  }
  return "";
}

std::string check_against_output(const RunOutput& a, const fs::path& pa, const RunOutput& b,
                                 const fs::path& pb) {
  if (pa == pb) {
    return named(a.flag, a.path) + ": is also " + named(b.flag, b.path) +
           "; each output needs a path of its own";
  }
  if (b.kind == OutputKind::kFolder && inside(pa, pb)) {
    return named(a.flag, a.path) + ": lies inside " + named(b.flag, b.path) +
           ", a folder this run replaces whole; give " + a.flag + " a path outside it";
  }
  return "";
}

std::string check_maker(const RunOutput& out, const std::string& command) {
  std::error_code ec;
  if (!fs::is_directory(out.path, ec)) return "";
  const std::optional<std::string> maker = output_folder_maker(out.path);
  if (!maker || *maker == command) return "";
  const std::string made_by =
      maker->empty() ? "was made by an older crepuscular that did not note which command made it"
                     : "was made by `crepuscular " + *maker + "`";
  return named(out.flag, out.path) + ": " + made_by + "; `crepuscular " + command +
         "` replaces it only with --overwrite: add --overwrite, or give " + out.flag +
         " another folder";
}

}  // namespace

std::string why_run_refused(const RunPaths& run) {
  std::vector<std::pair<const RunOutput*, fs::path>> outputs;
  for (const RunOutput& out : run.outputs) {
    if (!out.path.empty()) outputs.emplace_back(&out, resolved(out.path));
  }
  std::vector<std::pair<const RunInput*, fs::path>> inputs;
  for (const RunInput& in : run.inputs) {
    if (!in.path.empty()) inputs.emplace_back(&in, resolved(in.path));
  }
  for (const auto& [out, o] : outputs) {
    for (const auto& [in, i] : inputs) {
      const std::string why = check_against_input(*out, o, *in, i);
      if (!why.empty()) return why;
    }
  }
  for (size_t a = 0; a < outputs.size(); ++a) {
    for (size_t b = 0; b < outputs.size(); ++b) {
      if (a == b) continue;
      if (b < a && outputs[a].second == outputs[b].second) continue;  // said once
      const std::string why = check_against_output(*outputs[a].first, outputs[a].second,
                                                   *outputs[b].first, outputs[b].second);
      if (!why.empty()) return why;
    }
  }
  if (!run.overwrite) {
    for (const auto& [out, o] : outputs) {
      if (out->kind != OutputKind::kFolder) continue;
      const std::string why = check_maker(*out, run.command);
      if (!why.empty()) return why;
    }
  }
  return "";
}

void claim_run_paths(const RunPaths& run) {
  const std::string why = why_run_refused(run);
  if (!why.empty()) throw Error(why);
  set_output_command(run.command);
  for (const RunOutput& out : run.outputs) {
    if (out.path.empty()) continue;
    const fs::path p = fs::absolute(out.path).lexically_normal();
    remove_stale_outputs((p.has_filename() ? p : p.parent_path()).parent_path().string());
    if (out.kind == OutputKind::kFilesInFolder) remove_stale_outputs(out.path);
  }
}

}  // namespace crepuscular
