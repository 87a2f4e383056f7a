// The `crepuscular` command: plans safe straight needle paths to a tumor and guides the needle.
#include <CLI/CLI.hpp>
#include <algorithm>
#include <sstream>
#include <csignal>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <exception>

#include "apps/commands.hpp"
#include "foundation/error.hpp"
#include "foundation/interruptions.hpp"
#include "foundation/log.hpp"

namespace crepuscular::apps {

const std::atomic<bool>* stop_on_signals() { return stop_flag_on_interruption(); }

void parse_size(const std::string& text, int& width, int& height) {
  const auto x = text.find('x');
  try {
    if (x == std::string::npos) throw std::invalid_argument("no x");
    width = std::stoi(text.substr(0, x));
    height = std::stoi(text.substr(x + 1));
  } catch (const std::exception&) {
    throw Error("--size '" + text + "': expected WxH, e.g. 1280x960");
  }
}

}  // namespace crepuscular::apps

namespace {

// The top-level --help lists each command with the lead of its description (up to the first
// full stop or colon outside parentheses); each command's own --help keeps the whole text.
class CommandListFormatter : public CLI::Formatter {
 public:
  std::string make_subcommand(const CLI::App* sub) const override {
    const std::string& text = sub->get_description();
    size_t end = text.size();
    int depth = 0;
    for (size_t i = 0; i < text.size(); ++i) {
      const char c = text[i];
      depth += c == '(' ? 1 : c == ')' ? -1 : 0;
      const bool stop = (c == '.' || c == ':') && depth == 0 &&
                        (i + 1 == text.size() || text[i + 1] == ' ' || text[i + 1] == '\n');
      if (stop) {
        end = i;
        break;
      }
    }
    std::string lead = text.substr(0, end);
    std::replace(lead.begin(), lead.end(), '\n', ' ');
    std::stringstream out;
    CLI::detail::format_help(out, sub->get_display_name(true), lead, get_column_width());
    return out.str();
  }
};

}  // namespace

int main(int argc, char** argv) {
  // Ctrl-C, SIGTERM and SIGHUP remove the output in progress; a write past the file size limit or
  // into a closed pipe fails as an error (foundation/interruptions.hpp).
  crepuscular::watch_interruptions();
  CLI::App app{
      "Crepuscular: how safe are the straight needle paths from every point around a tumor?\n"
      "The tumor is treated as a light source and vulnerable structures cast shadows (the\n"
      "'crepuscular rays' method). Start with `crepuscular demo`, or see each command's --help."};
  app.formatter(std::make_shared<CommandListFormatter>());
  app.set_version_flag("--version", std::string("crepuscular ") + CREPUSCULAR_VERSION);
  app.require_subcommand(1);
  // Option errors read like every other error: "error: ..." on one line.
  app.failure_message([](const CLI::App*, const CLI::Error& e) {
    return std::string("error: ") + e.what() + "\nRun with --help for more information.\n";
  });
  bool verbose = false;
  app.add_flag("-v,--verbose", verbose, "Print debug messages");
  app.parse_complete_callback([&] {
    spdlog::set_pattern("[%H:%M:%S] %^%l%$ %v");
    spdlog::set_level(verbose ? spdlog::level::debug : spdlog::level::info);
  });
  crepuscular::apps::add_phantom_command(app);
  crepuscular::apps::add_plan_command(app);
  crepuscular::apps::add_area_command(app);
  crepuscular::apps::add_slices_command(app);
  crepuscular::apps::add_evaluate_command(app);
  crepuscular::apps::add_synth_command(app);
  crepuscular::apps::add_record_command(app);
  crepuscular::apps::add_track_command(app);
  crepuscular::apps::add_calibrate_command(app);
  crepuscular::apps::add_register_command(app);
  crepuscular::apps::add_guide_command(app);
  crepuscular::apps::add_render_command(app);
  crepuscular::apps::add_view_command(app);
  crepuscular::apps::add_demo_command(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  } catch (const crepuscular::Error& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  } catch (const std::bad_alloc&) {
    std::fprintf(stderr, "error: out of memory\n");
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
  // Results printed to standard output (evaluate) may have met a closed pipe (EPIPE; SIGPIPE is
  // ignored) or a full disk: said, never a silent success.
  if (std::fflush(stdout) != 0 || std::ferror(stdout)) {
    std::fprintf(stderr, "error: standard output: write failed (%s)\n", std::strerror(errno));
    return 1;
  }
  return 0;
}
