"""Table I (paper Q2): STAMP against sequential TAMP baselines and a sampling peer.

For billiards and pushing (K = 2), each seed's default STAMP solve sets N, the
distinct verified task plans it found, and its wall time; `enumerate`
(PDDLStream's reduction), `blocking` (Diverse LGP's) and `cem` then run until
each has verified N distinct task plans in MuJoCo C, or its cap is spent
(`mjstamp.baselines`; their settings are written down there). A warm-up run
of every method comes first, so no first seed pays compiles. Runtime: mean ±
std over seeds of the time to N (the cap where N was not reached, marked
'>'); factor: runtime over STAMP's, std propagated.

Paper (one GPU): billiards, STAMP 24x faster than PDDLStream and 104x than
Diverse LGP; pushing, 30x and 13x.

Usage: python -m benchmarks.paper.table1 [--tasks billiards pushing] [--seeds 3] [--cap 600]
           [--methods stamp,enumerate,blocking,cem] [--set KEY=VALUE ...] [--json]
JSON: {task: {method: {runtime_mean_s, runtime_std_s, factor, factor_std,
       distinct_verified, reached, ...}}}
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import TASKS, add_devices_argument, add_tasks_argument  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Runs the comparison for each task; prints the tables (or JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_tasks_argument(parser)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--cap", type=float, default=600.0, help="seconds per baseline and seed")
    parser.add_argument("--methods", default="stamp,enumerate,blocking,cem")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a solve or task setting for every task (e.g. particles=8)")
    add_devices_argument(parser)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)

    import mjstamp
    from mjstamp.parallel import host_device_count

    devices = args.devices or host_device_count("auto")  # one per core, at most 8
    mjstamp.configure(devices=devices, strict_devices=False)
    from mjstamp import registry
    from mjstamp.baselines.compare import compare, format_table, parse_methods
    from mjstamp.cli import settings
    from mjstamp.progress import Progress

    methods = parse_methods(args.methods)
    out = {}
    for name in args.tasks:
        overrides = {**TASKS[name], **settings.parse_overrides(name, args.set), "devices": None}
        rows = compare(lambda n=name, o=overrides: registry.load(n, **o), methods=methods,
                       seeds=args.seeds, cap_s=args.cap,
                       progress=Progress(True, f"table1 {name}"))
        out[name] = rows
        if not args.json:
            print(format_table(name, rows), flush=True)
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
