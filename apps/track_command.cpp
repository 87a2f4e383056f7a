// The `crepuscular track` command (being built).
#include "apps/commands.hpp"

namespace crepuscular::apps {

void add_track_command(CLI::App& app) { (void)app; }

}  // namespace crepuscular::apps
