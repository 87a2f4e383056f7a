#!/usr/bin/env python3
"""Reads a timeline written with CREPUSCULAR_TRACE=FILE (foundation/trace.hpp) and prints when the
GPU had points to compute: the union of the evaluator's calls, the gaps between them, how long 0, 1
or 2 calls were in flight, and the breathing driver's events (phase starts, waits, folds).
Usage: bench/timeline.py FILE [--steps] [--events]   (the last run in FILE)."""
import collections
import sys


def main():
    runs, run = [], []
    for line in open(sys.argv[1]):
        if line.strip() == "---":
            runs.append(run)
            run = []
        elif line.strip():
            t, p, w, n = line.split()
            run.append((float(t), int(p), w, int(n)))
    events = run or runs[-1]
    calls, open_calls = [], collections.defaultdict(list)
    for t, p, w, n in events:
        if w == "eval_begin":
            open_calls[(p, n)].append(t)
        elif w == "eval_end":
            calls.append((open_calls[(p, n)].pop(), t, p, n))
    calls.sort()
    busy, gaps, cur = 0.0, [], None
    for a, b, _, _ in calls:
        if cur is None:
            cur = [a, b]
        elif a <= cur[1]:
            cur[1] = max(cur[1], b)
        else:
            busy += cur[1] - cur[0]
            gaps.append((cur[1], a))
            cur = [a, b]
    if cur:
        busy += cur[1] - cur[0]
    end = max(t for t, _, _, _ in events)
    if calls:
        print(f"end {end:.2f} s; points computed from {calls[0][0]:.2f} to {calls[-1][1]:.2f} s, "
              f"calls in flight {busy:.2f} s, {sum(c[3] for c in calls) / 1e6:.2f} M points")
    else:
        print(f"end {end:.2f} s; no evaluator calls (exact mode)")
    print("gaps over 0.1 s:", [(round(g0, 2), round(g1 - g0, 2)) for g0, g1 in gaps if g1 - g0 > 0.1])
    edges = sorted([(a, 1) for a, _, _, _ in calls] + [(b, -1) for _, b, _, _ in calls])
    inflight, level, last = collections.Counter(), 0, 0.0
    for t, d in edges:
        inflight[level] += t - last
        level, last = level + d, t
    inflight[0] += end - last
    print("seconds with k calls in flight:", {k: round(v, 2) for k, v in sorted(inflight.items())})
    if "--steps" in sys.argv:
        # Per phase: when it started, computed and was folded; its sampler's steps (seconds).
        marks = collections.defaultdict(dict)
        steps = collections.defaultdict(collections.Counter)
        points = collections.defaultdict(lambda: [0.0, 0])
        for t, p, w, n in events:
            if w.startswith("sampler_"):
                steps[p][w[len("sampler_"):]] += n / 1e6
            elif w not in ("eval_begin", "eval_end"):
                marks[p].setdefault(w, t)
        for a, b, p, n in calls:
            points[p][0] += b - a
            points[p][1] += n
        names = sorted({w for c in steps.values() for w in c})
        columns = ("start", "compute_begin", "comb_wait_end", "compute_end", "finish_begin",
                   "coverage_applied", "folded", "fold_done", "checked", "finish_end")
        print("phase " + " ".join(columns) + " | calls_s M_points | " + " ".join(names))
        for p in sorted(k for k in marks if k >= 0):
            m = marks[p]
            cols = " ".join(f"{m.get(w, float('nan')):6.2f}" for w in columns)
            print(f"{p:3d} {cols} | {points[p][0]:5.2f} {points[p][1] / 1e6:5.2f} | "
                  + " ".join(f"{steps[p][w]:5.2f}" for w in names))
        # The plan's own steps (the reads before, the writes, area safety and finishes after).
        plan = {w: t for t, p, w, _ in events if p < 0 and w not in ("eval_begin", "eval_end")}
        print("plan:", " ".join(f"{w} {t:.2f}" for w, t in sorted(plan.items(), key=lambda e: e[1])))
    if "--events" in sys.argv:
        for t, p, w, _ in events:
            if w not in ("eval_begin", "eval_end"):
                print(f"{t:8.2f} {p:3d} {w}")


if __name__ == "__main__":
    main()
