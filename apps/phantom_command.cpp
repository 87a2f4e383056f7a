// `crepuscular phantom`: writes the built-in phantom abdomen (CT, labels, tumor, vulnerability
// table), the default demo data.
#include "apps/commands.hpp"
#include "pipelines/phantom.hpp"

namespace crepuscular::apps {

void add_phantom_command(CLI::App& app) {
  auto out = std::make_shared<std::string>();
  auto options = std::make_shared<planning::PhantomOptions>();
  auto phases = std::make_shared<int>(0);
  auto four_d = std::make_shared<bool>(false);
  CLI::App* cmd = app.add_subcommand(
      "phantom",
      "Generate the built-in phantom, the default demo data: a procedural abdomen in LPS mm\n"
      "(about 360 x 260 x 240 mm, centred on (0,0,0)) with skin and fat, the muscle wall, back\n"
      "muscles and psoas, ribs and spine, aorta and vena cava, lungs above the diaphragm, a liver\n"
      "in the patient's right upper abdomen with a random branching vessel tree, kidneys, spleen,\n"
      "gallbladder, bowel loops with gas, and a 25 mm tumor in the lateral right liver lobe that\n"
      "has both safe (lateral) and unsafe (vessels, vena cava, ribs, spine) straight approaches.\n"
      "\n"
      "Writes into DIR (created if missing):\n"
      "  ct.nii.gz           CT values in HU (int16), with mild noise\n"
      "  labels.nii.gz       label map (uint8): 0 air, 1 fat, 2 muscle, 3 bone, 4 aorta,\n"
      "                      5 vena cava, 6 liver (tumor included), 7 liver vessels, 8 kidneys,\n"
      "                      9 lungs, 10 bowel, 11 spleen, 12 gallbladder\n"
      "  tumor.nii.gz        tumor mask (uint8, 0/1)\n"
      "  vulnerability.json  the vulnerability table of these labels (same as --preset phantom)\n"
      "\n"
      "The same --spacing and --seed always give the same files; the geometry is defined in mm,\n"
      "so it looks the same at any spacing. Next step:\n"
      "  crepuscular plan --labels DIR/labels.nii.gz --tumor DIR/tumor.nii.gz --preset phantom\n"
      "\n"
      "Breathing (--phases N): writes N phases of one breathing cycle instead, phase 0 at\n"
      "end-exhale (the phantom above) and phase N/2 at end-inhale:\n"
      "  phaseKK/{ct,labels,tumor}.nii.gz, vulnerability.json, phases.json (the list plan reads)\n"
      "The diaphragm, liver, its vessels, the tumor and the other organs below the diaphragm move\n"
      "caudally by up to --amplitude mm at the dome, with an anterior component of 0.35 mm per mm,\n"
      "fading with the distance from the diaphragm (the tumor moves about 7 mm at 12 mm); skin,\n"
      "body wall, ribs, spine, aorta and vena cava stay. Next step:\n"
      "  crepuscular plan --phases DIR/phases.json --out PLAN --mode fast\n"
      "With --four-d also {ct,labels,tumor}_4d.nii.gz: the phases along the 4th axis, as a 4D CT\n"
      "and its segmentation come from a scanner; plan reads them as well:\n"
      "  crepuscular plan --labels DIR/labels_4d.nii.gz --tumor DIR/tumor_4d.nii.gz \\\n"
      "      --preset phantom --out PLAN --mode fast");
  cmd->add_option("--out", *out, "Output folder (DIR)")->required();
  cmd->add_option("--spacing", options->spacing_mm,
                  "Isotropic voxel size in mm, 0.3 to 10 (1 mm: ~22 M voxels)")
      ->capture_default_str();
  cmd->add_option("--seed", options->seed,
                  "Random seed: changes the liver vessel tree, the bowel and the CT noise")
      ->capture_default_str()
      ->check(in_range(0, 4294967295.0, true));
  cmd->add_option("--phases", *phases,
                  "Breathing phases of one cycle, 2 to 50 (default: none, a phantom at rest; 10 "
                  "is the usual 4D CT)")
      ->check(in_range(2, 50, true));
  cmd->add_option("--amplitude", options->amplitude_mm,
                  "Breathing: cranio-caudal motion of the diaphragm's dome at end-inhale, mm "
                  "(5-7 with abdominal compression, 15-20 free breathing)")
      ->capture_default_str()
      ->check(in_range(0, planning::kMaxBreathingAmplitudeMm));
  cmd->add_flag("--four-d", *four_d,
                "Breathing: also write the phases as 4D NIfTI files (ct_4d, labels_4d, tumor_4d)")
      ->needs("--phases");
  auto overwrite = std::make_shared<bool>(false);
  add_overwrite_flag(cmd, *overwrite);
  cmd->callback([out, options, phases, four_d, overwrite] {
    claim_run_paths({"phantom", {}, {{"--out", *out, OutputKind::kFolder}}, *overwrite});
    if (*phases > 0) {
      pipelines::run_breathing_phantom(*options, *phases, *out, *four_d);
    } else {
      pipelines::run_phantom(*options, *out);
    }
  });
}

}  // namespace crepuscular::apps
