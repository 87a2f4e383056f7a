#!/usr/bin/env python3
"""One line per run of bench/ab_gpu.sh's runs.txt (LABEL, then bench_plan's JSON line).

Wall time, peak memory, points computed, the sampler's host steps summed over the phases (fill,
finest levels' gathering, refinement) and the GPU kernels' time, the plan's core time, and fast
mode's class agreement and relative L2 per value against exact.

    python3 bench/runs_summary.py OUT/runs.txt
"""
import json
import sys


def main():
    for line in open(sys.argv[1]):
        if "{" not in line:
            continue
        label, text = line.split(" ", 1)
        run = json.loads(text)
        check = run.get("fast_vs_exact") or {}
        values = [f"{check[v]['class_agreement']:.4f}/{check[v]['relative_l2']:.4f}"
                  for v in ("svv", "isbv", "ivbv", "bvv") if isinstance(check.get(v), dict)]
        cpu = run.get("cpu") or {}
        cores = (f"user {cpu['user_s']:.1f} s sys {cpu['system_s']:.1f} s" if cpu
                 else "cores n/a")
        breathing = run.get("breathing") or {}
        phases = breathing.get("phases") or []
        if phases:
            def summed(step):
                return sum(p["path_safety_phases"].get(step, 0.0) for p in phases)
            points = sum(p["points_computed_exactly"] for p in phases)
            steps = (f"fill {summed('sampler_fill'):.2f} gather {summed('sampler_finest_requests'):.2f}"
                     f" refine {summed('sampler_refine'):.2f} kernels {summed('gpu_kernels'):.2f}")
        else:
            points = check.get("points_computed_exactly")
            steps = ""
        print(f"{label:14s} {run['wall_s']:6.2f} s  {run.get('peak_rss_gib', 0):4.1f} GiB  "
              f"{points} points  {steps}  {cores}  {' '.join(values)}")


if __name__ == "__main__":
    main()
