// The `crepuscular area` command (being built).
#include "apps/commands.hpp"

namespace crepuscular::apps {

void add_area_command(CLI::App& app) { (void)app; }

}  // namespace crepuscular::apps
