// Subcommands of the `crepuscular` command. Each adds itself to the app and maps its flags to a
// pipeline's options (pipelines/); its callback calls the pipeline and nothing more. Includes the
// standard headers every command uses (<memory>, <string>, <vector>).
#pragma once

#include <CLI/CLI.hpp>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "foundation/run_paths.hpp"
#include "tracking/detector.hpp"

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
void add_render_command(CLI::App& app);
void add_view_command(CLI::App& app);

// --overwrite, on every command that replaces an output folder (foundation/run_paths.hpp).
inline CLI::Option* add_overwrite_flag(CLI::App* cmd, bool& overwrite) {
  return cmd->add_flag(
      "--overwrite", overwrite,
      "Replace an output folder that another crepuscular command made (its .crepuscular-output "
      "names the command; folders from before it named one count as another command's). "
      "Without it only the command's own folders are replaced. Never replaces the run's "
      "inputs, a folder of files crepuscular did not write, or a running process's output");
}

// The file or folder a frame source URI reads ("recording:DIR", "synthetic:SCENE.json"), as an
// input of the run; "" for cameras and the built-in scene.
inline std::string source_path(const std::string& uri) {
  for (const std::string prefix : {"recording:", "synthetic:"}) {
    if (uri.rfind(prefix, 0) == 0 && uri != "synthetic:builtin") {
      const std::string where = uri.substr(prefix.size());
      return where.substr(0, where.find('?'));
    }
  }
  return "";
}

// "WxH" (e.g. "1280x960") of --size into width and height; throws Error naming the text.
void parse_size(const std::string& text, int& width, int& height);

// A flag that SIGINT and SIGTERM (Ctrl-C) set from now on, cleared here: for jobs that end
// cleanly when asked to (guidance, recording).
const std::atomic<bool>* stop_on_signals();

// An enum option's names -> values (CLI::CheckedTransformer, any case, spaces ignored), shown in
// --help as {name,...}.
template <typename T>
CLI::Validator enum_names(const std::map<std::string, T>& names) {
  std::string list;
  for (const auto& entry : names) list += (list.empty() ? "" : ",") + entry.first;
  return CLI::CheckedTransformer(names, CLI::ignore_case, CLI::ignore_space)
      .description("{" + list + "}");
}

// --series UID, repeatable, into `series` (planning::VolumeReadOptions::dicom_series), for every
// command that reads a scan which may be a DICOM folder.
inline CLI::Option* add_series_option(CLI::App* cmd, std::vector<std::string>& series) {
  return cmd->add_option(
      "--series", series,
      "DICOM series to read, by its SeriesInstanceUID (0020,000E), where a DICOM folder given as "
      "a scan holds several series (a scout beside the CT, a second reconstruction, another "
      "phase). Such a folder is refused, its series listed with their slice counts and "
      "descriptions, until one is chosen here. Repeatable: one UID per such folder (UIDs are "
      "unique, so each folder takes the one of its own). Files and folders of one series need "
      "none");
}

// A number option that must be finite (CLI11 reads "nan" and "inf" as numbers); `positive`: > 0.
inline CLI::Validator finite_number(bool positive = false) {
  return CLI::Validator(
      [positive](std::string& text) -> std::string {
        char* end = nullptr;
        const double v = std::strtod(text.c_str(), &end);
        if (end == text.c_str() || *end != '\0') return "expected a number, got '" + text + "'";
        if (!std::isfinite(v)) return "expected a finite number, got '" + text + "'";
        if (positive && !(v > 0.0)) return "expected a number > 0, got '" + text + "'";
        return {};
      },
      positive ? "NUMBER > 0" : "NUMBER", positive ? "positive finite" : "finite");
}

// A list of safety classes (any of safe,medium,dangerous), checked when the option is read so
// that the message names the option.
CLI::Validator safety_class_list();

// A number option within [lo, hi] (NaN and infinities refused; CLI11's own ranges let NaN pass
// and print their bounds in full); `integer`: a whole number.
inline CLI::Validator in_range(double lo, double hi, bool integer = false) {
  const auto shown = [](double v) {
    std::ostringstream s;
    s << v;
    return s.str();
  };
  const std::string range = shown(lo) + " to " + shown(hi);
  return CLI::Validator(
      [=](std::string& text) -> std::string {
        char* end = nullptr;
        const double v = std::strtod(text.c_str(), &end);
        if (end == text.c_str() || *end != '\0') return "expected a number, got '" + text + "'";
        if (!(v >= lo && v <= hi)) return "'" + text + "' is not a number from " + range;
        if (integer && v != std::floor(v)) return "expected a whole number, got '" + text + "'";
        return {};
      },
      (integer ? "INT in " : "NUMBER in ") + range);
}

// The tag detector's settings (--decimate, --refine-edges, --sharpening, --blur, --max-hamming,
// --detector-threads) into `o`, on every command that finds marker boards in images. The family is
// each board's own (boards.json "family").
void add_detector_options(CLI::App* cmd, tracking::DetectorOptions& o);

}  // namespace crepuscular::apps
