// The one rule on where a run may write (docs/ARCHITECTURE.md §3), checked before any work: outputs
// never replace, hold or go into the run's inputs, never meet each other, and a folder another
// command made is replaced only when the user says so (--overwrite).
#pragma once

#include <string>
#include <vector>

namespace crepuscular {

// What an output path is.
enum class OutputKind {
  kFile,          // one file, written through a temporary sibling
  kFolder,        // a folder written whole and replacing an earlier one (StagedDirectory)
  kFilesInFolder  // a folder that files are added to (snapshots): never replaced
};

struct RunInput {
  std::string flag;  // how the user named it ("--labels"), for messages
  std::string path;  // "" = not given
};

struct RunOutput {
  std::string flag;
  std::string path;  // "" = not written
  OutputKind kind = OutputKind::kFile;
};

struct RunPaths {
  std::string command;  // "plan": named in the markers of the folders the run makes
  std::vector<RunInput> inputs;
  std::vector<RunOutput> outputs;
  bool overwrite = false;  // a folder made by another command may be replaced
};

// Why `run` may not start, or "" when it may. Paths are compared after
// std::filesystem::weakly_canonical (symlinks resolved). Refused:
// - an output that is an input, holds one (an input inside an output folder) or lies inside one
//   (a kFilesInFolder output may hold inputs: it is never replaced);
// - two outputs at one path, or an output inside a kFolder output of the same run;
// - an existing kFolder output whose marker names another command, or none (an older
//   crepuscular's), unless `overwrite`. Folders without a marker are left to StagedDirectory,
//   which replaces only empty ones.
// The message starts with the flag and the path and says how to proceed.
std::string why_run_refused(const RunPaths& run);

// Before any work: throws Error with why_run_refused's message when the run may not start;
// otherwise names `run.command` as the maker of the folders this process commits
// (set_output_command) and removes what killed runs left beside the outputs
// (remove_stale_outputs in the folder of each output, and inside each kFilesInFolder output).
void claim_run_paths(const RunPaths& run);

}  // namespace crepuscular
