// Subcommands of the `crepuscular` command. Each adds itself to the app; its callback parses
// nothing more and calls the libraries.
#pragma once

#include <CLI/CLI.hpp>

namespace crepuscular::apps {

void add_phantom_command(CLI::App& app);
void add_plan_command(CLI::App& app);
void add_area_command(CLI::App& app);
void add_slices_command(CLI::App& app);
void add_evaluate_command(CLI::App& app);
void add_synth_command(CLI::App& app);
void add_record_command(CLI::App& app);
void add_track_command(CLI::App& app);
void add_calibrate_command(CLI::App& app);
void add_register_command(CLI::App& app);
void add_guide_command(CLI::App& app);
void add_demo_command(CLI::App& app);

}  // namespace crepuscular::apps
