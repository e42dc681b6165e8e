"""Ground truth of the scene suite: every successful task plan and its share of θ's box.

For each suite scene, shots over the task's box are replayed in MuJoCo C with
the scene's own solver settings (`mujoco.rollout`, all cores) and decoded
exactly as solved plans are (`verify.decode(task, verify.simulate_c(task, θ), θ)`).
Boxes of at most 3 coordinates are swept on a regular grid (`modes.sweep`),
larger ones by seeded uniform Monte Carlo (`modes.monte_carlo`). Either way
about `SHOTS` = 10⁵ shots, so a task plan occupying 0.1% of the box is seen
about 100 times (share ± 10%). Results are cached on disk
(~/.cache/mjstamp/modes), keyed by the declaration, the compiled model and a
hash of the suite's code.

Usage: python examples/suite/ground_truth.py [--scenes a,b] [--shots N] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

SHOTS = 100_000


def ground_truth(name: str, task=None, *, shots: int = SHOTS, seed: int = 0,
                 progress: bool | None = None, cache: bool = True) -> dict:
    """The modes of one suite scene (see the module docstring).

    Args:
      name: suite scene name.
      task: its `Task`, if already built (else `SUITE[name]()`).
      shots: about how many shots (a grid rounds up to a whole number per axis).
      seed: seeds the Monte Carlo draws (grids ignore it).
      progress: tqdm bar; None shows it on a terminal.
      cache: read and write the on-disk cache.

    Returns:
      `modes.sweep` / `modes.monte_carlo`'s result.
    """
    from suite.tasks import SUITE, source_salt

    from mjstamp import modes

    task = SUITE[name]() if task is None else task
    salt = source_salt(name)
    if modes.supports_sweep(task):
        grid = math.ceil(shots ** (1.0 / task.dim) - 1e-9)
        return modes.sweep(task, grid=grid, chunk=1024, progress=progress, cache=cache,
                           salt=salt)
    return modes.monte_carlo(task, shots=shots, seed=seed, chunk=1024, progress=progress,
                             cache=cache, salt=salt)


def format_modes(result: dict, min_share: float) -> str:
    """The ground-truth table of one scene, as text."""
    how = (f"grid {result['grid']}^{len(result['box_low'])}" if result.get("grid")
           else f"uniform, seed {result['seed']}")
    lines = [f"{result['task']}: {result['shots']} shots ({how}); "
             f"{result['success_share']:.2%} succeed"]
    for m in result["modes"]:
        flag = "*" if m["share"] >= min_share else " "
        lines.append(f" {flag} {m['task_plan']:<22} {m['count']:7d} shots  {m['share']:.3%}")
    lines.append(f"* = occupies >= {min_share:.1%} of the box")
    return "\n".join(lines)


def main() -> None:
    """Computes (or reads from the cache) and prints the ground truth of the suite."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="", help="comma-separated names (default: all)")
    parser.add_argument("--shots", type=int, default=SHOTS)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--no-cache", action="store_true", help="recompute, ignore the cache")
    args = parser.parse_args()

    import mjstamp

    mjstamp.configure()
    from suite.tasks import SUITE

    from mjstamp import modes

    names = [s for s in args.scenes.split(",") if s] or list(SUITE)
    unknown = [s for s in names if s not in SUITE]
    if unknown:
        raise SystemExit(f"unknown scene {unknown[0]!r}; valid: {', '.join(SUITE)}")
    out = []
    for name in names:
        t0 = time.perf_counter()
        result = ground_truth(name, shots=args.shots, cache=not args.no_cache,
                              progress=None if not args.json else False)
        result = {**result, "wall_s": time.perf_counter() - t0}
        out.append(result)
        if not args.json:
            print(format_modes(result, modes.MIN_SHARE), flush=True)
            print(f"({result.get('compute_s', 0.0):.0f} s to compute, {result['wall_s']:.1f} s "
                  "this run)\n", flush=True)
    if args.json:
        print(json.dumps({"benchmark": "scene_suite_ground_truth", "scenes": out}))


if __name__ == "__main__":
    main()
