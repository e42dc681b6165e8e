"""Particles that do their job (issue 11): billiards and pushing K = 2 over seeds.

For each task and seed, a default solve (`mjstamp.solve` with the
task's registered settings, plus any `--set`) and, with `--compare KEY=VALUE`,
the same solve with that setting changed. Reported per solve: the share of
particles that end as verified plans, distinct verified task plans (billiards:
against the ground-truth sweep, `modes.sweep`, with the ones missed), the mean
and median cost at the start, after SVGD and at the end, and the SVGD phase's
share of the decrease of the mean (`SolveResult.loss`).

Targets: billiards, all 16 ground-truth task plans verified at seeds 0-2 and
>= 30% of the particles verified; pushing K = 2, the SVGD phase makes >= 1/3 of
the decrease of the mean cost and >= 6 verified push sequences at seeds 0-2.

Usage: python -m benchmarks.studies.particles [--tasks billiards pushing] [--seeds 3]
           [--set KEY=VALUE ...] [--compare KEY=VALUE ...] [--devices N] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import TASKS, add_devices_argument, add_tasks_argument  # noqa: E402

TARGET_SHARE = 0.3
TARGET_SVGD_SHARE = 1 / 3
TARGET_PUSH_SEQUENCES = 6


def _solve_row(name: str, overrides: dict, seed: int, truth: list[str] | None) -> dict:
    from mjstamp import registry, solve

    task, config = registry.load(name, **overrides)
    started = time.perf_counter()
    result = solve(task, config, seed=seed, progress=False)
    summary = result.summary()
    found = sorted({row["task_plan"] for row in summary["task_plans"] if row["verified"]})
    row = {
        "seed": seed, "wall_s": time.perf_counter() - started,
        "verified_particle_share": summary["verified_particle_share"],
        "verified_plans": summary["verified_plans"],
        "distinct_verified_task_plans": summary["distinct_verified_task_plans"],
        "task_plans": found, "loss": summary["loss"],
        "svgd_iters": summary["stamp"]["svgd_iters"], "sgd_iters": summary["stamp"]["sgd_iters"],
        "backtracked": int(result.diagnostics.backtracked.sum()),
        "kept_from_earlier": summary["kept_from_earlier"],
    }
    if truth is not None:
        row["ground_truth_found"] = len(set(found) & set(truth))
        row["ground_truth_missed"] = sorted(set(truth) - set(found))
    return row


def _targets(name: str, rows: list[dict]) -> dict:
    if name == "billiards":
        return {"all_ground_truth": all(not r["ground_truth_missed"] for r in rows),
                "verified_particle_share": all(r["verified_particle_share"] >= TARGET_SHARE
                                               for r in rows)}
    shares = [r["loss"]["svgd_share"] for r in rows]
    return {"svgd_share": all(s is not None and s >= TARGET_SVGD_SHARE for s in shares),
            "push_sequences": all(r["distinct_verified_task_plans"] >= TARGET_PUSH_SEQUENCES
                                  for r in rows)}


def main(argv: list[str] | None = None) -> int:
    """Runs the solves; prints a line per solve (or one JSON object)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_tasks_argument(parser)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a solve or task setting for every solve")
    parser.add_argument("--compare", action="append", default=[], metavar="KEY=VALUE",
                        help="also solve with this setting changed (e.g. stamp.backtrack=false)")
    add_devices_argument(parser)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds={args.seeds} must be >= 1")

    import mjstamp
    from mjstamp.parallel import host_device_count

    devices = args.devices or host_device_count("auto")  # one per core, at most 8
    mjstamp.configure(devices=devices, strict_devices=False)
    from mjstamp import modes, registry
    from mjstamp.cli import settings

    out: dict = {"benchmark": "particles", "devices": devices, "seeds": args.seeds,
                 "set": args.set, "compare": args.compare}
    for name in args.tasks:
        base = {**TASKS[name], **settings.parse_overrides(name, args.set)}
        variants = {"default": base}
        if args.compare:
            variants["compare"] = {**base, **settings.parse_overrides(name, args.compare)}
        truth = None
        if name == "billiards":
            task, _ = registry.load(name, **base)
            truth = [m["task_plan"] for m in modes.sweep(task, progress=False)["modes"]]
        out[name] = {}
        for label, overrides in variants.items():
            rows = []
            for seed in range(args.seeds):
                rows.append(_solve_row(name, overrides, seed, truth))
                r = rows[-1]
                print(f"[particles] {name} {label} seed {seed}: "
                      f"{r['verified_particle_share']:.0%} of particles verified, "
                      f"{r['distinct_verified_task_plans']} task plans, SVGD share "
                      f"{r['loss']['svgd_share']}, {r['wall_s']:.0f} s", file=sys.stderr,
                      flush=True)
            out[name][label] = {"rows": rows, "targets": _targets(name, rows)}
    if args.json:
        print(json.dumps(out))
    else:
        for name in args.tasks:
            for label, block in out[name].items():
                print(f"{name} {label}: targets {block['targets']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
