// The `crepuscular synth` command (being built).
#include "apps/commands.hpp"

namespace crepuscular::apps {

void add_synth_command(CLI::App& app) { (void)app; }

}  // namespace crepuscular::apps
