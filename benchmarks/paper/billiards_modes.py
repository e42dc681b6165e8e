"""Ground truth for billiards: every task plan that pockets the target ball.

Sweeps a fine grid of cue velocities over the task's velocity box in MuJoCo C
(`mujoco.rollout`, all cores, the scene's own solver settings), decodes each
shot exactly as `mjstamp solve` decodes plans, and lists every successful task
plan with the share of the box it occupies. `mjstamp solve billiards` reports
its coverage against this list (task plans occupying at least 0.1% of the box).

Usage: python benchmarks/paper/billiards_modes.py [--grid 200] [--json]
"""

from __future__ import annotations

import argparse
import json
import time


def main() -> None:
    """Runs the sweep and prints the modes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=int, default=200, help="points per velocity axis")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--no-cache", action="store_true", help="recompute, ignore the cache")
    args = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    from mjstamp import modes, registry

    task, _ = registry.load("billiards")
    t0 = time.perf_counter()
    result = modes.sweep(task, grid=args.grid, cache=not args.no_cache, progress=not args.json)
    result = {"benchmark": "billiards_modes", "sweep_s": time.perf_counter() - t0, **result}
    result["feasible_at_min_share"] = [
        m["task_plan"] for m in result["modes"] if m["share"] >= modes.MIN_SHARE
    ]
    result["codes"] = sorted({m["code"] for m in result["modes"]})
    if args.json:
        print(json.dumps(result))
        return
    print(f"{result['shots']} shots over {result['box_low']}..{result['box_high']} "
          f"({result['sweep_s']:.1f} s); {result['success_share']:.2%} pocket the target")
    for m in result["modes"]:
        flag = "*" if m["share"] >= modes.MIN_SHARE else " "
        print(f" {flag} {m['task_plan']:<14} {m['count']:6d} shots  {m['share']:.3%}")
    print(f"* = occupies >= {modes.MIN_SHARE:.1%} of the box; codes: {', '.join(result['codes'])}")


if __name__ == "__main__":
    main()
