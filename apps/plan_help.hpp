// What `crepuscular plan --help` teaches before the options.
#pragma once

namespace crepuscular::apps {

inline constexpr const char* kPlanHelp =
      "Compute the path safety volume around a tumor.\n"
      "For every point in a ball around the tumor, all straight paths from that point to the\n"
      "tumor surface are traced through the blocking volume (risk per mm), and summarised as:\n"
      "  svv   surface visibility value: % of the visible tumor surface reachable with a line\n"
      "        integral of blocking <= eps (high = safe)\n"
      "  isbv  integral surface blocking value: sum of line integrals to the visible surface\n"
      "  ivbv  integral volume blocking value: line integrals weighted by tumor chord length\n"
      "  bvv   blocker volume value: blocking weighted by the volume each sample stands for\n"
      "        (isbv, ivbv, bvv: low = safe)\n"
      "Blocking comes from label maps and vulnerability tables (--labels, repeatable, with\n"
      "--vulnerability or --preset or a table per map), a ready blocking volume (--blocking), or\n"
      "CT thresholds (--ct alone). Voxels of the region of interest outside the scan (the\n"
      "inputs' grids) are UNKNOWN: no value, 2 in roi.nii.gz, never shown as safe.\n"
      "Writes PLAN_DIR/blocking.nii.gz, PLAN_DIR/path_safety_<value>.nii.gz (float32, LPS,\n"
      "NaN outside the region of interest; open in 3D Slicer), PLAN_DIR/area_safety.vtk (the\n"
      "safe access regions around the tumor and their leeway, for the first value; a model in\n"
      "3D Slicer or ParaView) and PLAN_DIR/plan.json.\n"
      "Examples:\n"
      "  crepuscular phantom --out data && crepuscular plan --labels data/labels.nii.gz \\\n"
      "      --tumor data/tumor.nii.gz --preset phantom --out plan\n"
      "  crepuscular plan --labels seg_total.nii.gz:totalsegmentator \\\n"
      "      --labels seg_vessels.nii.gz:totalsegmentator_liver_vessels \\\n"
      "      --tumor seg_vessels.nii.gz:2 --lesion 1 --ct ct.nii.gz --mode fast --out plan\n"
      "Breathing (--phases phases.json): the liver moves with breathing, so a path safe in the\n"
      "planning scan's phase may cross a vessel in another. Each phase is planned on one grid\n"
      "(centred on the mean tumor centroid) and the phases combined: a voxel is safe only if it\n"
      "is safe in every phase (svv the minimum, the others the maximum), unknown if unknown in\n"
      "any. plan.json \"breathing\" lists per-phase statistics and the share of the region whose\n"
      "class changes over the cycle; --per-phase also writes each phase's volumes.\n"
      "  crepuscular phantom --phases 10 --out cycle && \\\n"
      "      crepuscular plan --phases cycle/phases.json --mode fast --per-phase --out plan";

}  // namespace crepuscular::apps
