"""Tables II and III (paper Q3): STAMP's runtime against particle count and dimensionality.

Table II (`--table 2`, the default): the default solve of billiards and of
pushing with at most one push (K = 1) with 100, 200, 400 and 800 particles.
Table III (`--table 3`): pushing with K = 1..5 pushes (θ's dimension grows
with K), default particles. Each setting is solved once untimed first (its
compiles and caches: a particle count or K is a new shape), then once per
seed; the runtime is the solve's own wall time (screen, calibration, STAMP,
verification), mean ± std over seeds, in the paper's layout.

Paper (one GPU, 10 seeds): Table II billiards 26.1 s (100 particles) to 33.5 s
(800), pushing 149.7 to 174 s; Table III 168.7 s (K = 1) to 178.3 s (K = 5).

Usage: python -m benchmarks.paper.table2 [--table 2|3] [--tasks billiards pushing]
           [--particles 100 200 400 800] [--max-pushes 1 2 3 4 5] [--seeds 3]
           [--set KEY=VALUE ...] [--save FILE] [--json]
JSON: {"table": 2, "rows": [{"task", "particles", "max_pushes", "dimension",
       "runtime_mean_s", "runtime_std_s", "runtime_s", "distinct_verified_task_plans"}]}
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import add_devices_argument, save_json  # noqa: E402


def _row(name: str, overrides: dict, seeds: int, say) -> dict:
    """One setting: an untimed warm-up solve, then one timed solve per seed."""
    from mjstamp import registry, solve

    task, config = registry.load(name, **overrides)
    say(f"{name} {overrides}: warm-up solve (compiles)")
    solve(task, config, seed=0, progress=False)
    times, found = [], []
    for seed in range(seeds):
        summary = solve(task, config, seed=seed, progress=False).summary()
        times.append(summary["wall_time_s"])
        found.append(summary["distinct_verified_task_plans"])
        say(f"{name} {overrides} seed {seed}: {times[-1]:.1f} s, {found[-1]} task plans")
    problem = task.build()
    return {"task": name, "particles": summary["particles"],
            "max_pushes": overrides.get("max_pushes"), "dimension": problem.dim,
            "runtime_mean_s": float(np.mean(times)), "runtime_std_s": float(np.std(times)),
            "runtime_s": times, "distinct_verified_task_plans": found}


def format_table(table: int, rows: list[dict]) -> str:
    """The paper's layout of Table II (runtime by particle count) or III (by K)."""
    def cell(r):
        return f"{r['runtime_mean_s']:.1f} ± {r['runtime_std_s']:.1f}"

    if table == 3:
        lines = ["RUNTIME OF STAMP VARYING THE PARTICLE DIMENSIONALITY FOR BLOCK-PUSHING",
                 f"{'Max. Push Count':<16}{'Dimensionality':<16}Runtime (s)"]
        lines += [f"{r['max_pushes']:<16}{r['dimension']:<16}{cell(r)}" for r in rows]
        return "\n".join(lines)
    tasks = list(dict.fromkeys(r["task"] for r in rows))
    counts = sorted({r["particles"] for r in rows})
    lines = ["RUNTIME OF STAMP VARYING THE NUMBER OF PARTICLES",
             f"{'Particle Count':<16}" + "".join(f"{t + ' (s)':<18}" for t in tasks)]
    for n in counts:
        by_task = {r["task"]: r for r in rows if r["particles"] == n}
        lines.append(f"{n:<16}" + "".join(
            f"{cell(by_task[t]) if t in by_task else '-':<18}" for t in tasks))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Runs Table II or III; prints it (or JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--table", type=int, choices=(2, 3), default=2)
    parser.add_argument("--tasks", nargs="*", choices=("billiards", "pushing"),
                        default=["billiards", "pushing"], help="Table II's tasks")
    parser.add_argument("--particles", type=int, nargs="*", default=[100, 200, 400, 800])
    parser.add_argument("--max-pushes", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    add_devices_argument(parser)
    parser.add_argument("--save", metavar="FILE",
                        help="write the JSON so far to FILE after every row (a long run "
                             "keeps what it measured)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds {args.seeds} must be >= 1")

    import mjstamp
    from mjstamp.parallel import host_device_count

    mjstamp.configure(devices=args.devices or host_device_count("auto"),  # one per core, at most 8
                      strict_devices=False)
    from mjstamp.cli import settings

    def say(msg):
        print(f"[table{args.table}] {msg}", file=sys.stderr, flush=True)

    import jax

    rows = []
    result = {"table": args.table, "devices": len(jax.devices()),
              "device_kind": jax.devices()[0].platform, "cpus": os.cpu_count(),
              "jax": jax.__version__, "seeds": args.seeds, "rows": rows}

    def add(row: dict) -> None:
        rows.append(row)
        if args.save:
            save_json(args.save, result)

    if args.table == 2:
        for name in args.tasks:
            for n in args.particles:
                extra = {"max_pushes": 1} if name == "pushing" else {}
                overrides = {**extra, **settings.parse_overrides(name, args.set), "particles": n}
                add(_row(name, overrides, args.seeds, say))
    else:
        for k in args.max_pushes:
            overrides = {**settings.parse_overrides("pushing", args.set), "max_pushes": k}
            add(_row("pushing", overrides, args.seeds, say))
    if args.json:
        print(json.dumps(result))
    else:
        print(format_table(args.table, rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
