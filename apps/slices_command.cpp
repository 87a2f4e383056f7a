// The `crepuscular slices` command (being built).
#include "apps/commands.hpp"

namespace crepuscular::apps {

void add_slices_command(CLI::App& app) { (void)app; }

}  // namespace crepuscular::apps
