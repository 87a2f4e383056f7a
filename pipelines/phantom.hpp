// The phantom job: the built-in phantom abdomen written to a folder, with a summary of what it
// holds (grid, tumor size and centroid, voxels per label) in the log.
#pragma once

#include <string>
#include <vector>

#include "planning/simulation/phantom.hpp"

namespace crepuscular::pipelines {

// Builds the phantom, writes it into `out_dir` (planning::write_phantom) and logs its summary.
void run_phantom(const planning::PhantomOptions& options, const std::string& out_dir);

// Writes a breathing cycle of `phases` phases (planning::write_breathing_phantom) into `out_dir`
// and logs each phase's tumor centroid and its motion.
// four_d: also {ct,labels,tumor}_4d.nii.gz, the phases along the 4th axis.
void run_breathing_phantom(const planning::PhantomOptions& options, int phases,
                           const std::string& out_dir, bool four_d = false);

// One-line summaries of the phantom: grid; tumor voxels, volume, equivalent diameter, centroid;
// voxels per label.
std::vector<std::string> phantom_summary(const planning::Phantom& phantom);

}  // namespace crepuscular::pipelines
