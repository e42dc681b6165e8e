"""Wall time of `mjstamp solve billiards`: cold process, warm caches, rollout share.

Runs the default solve in two fresh processes sharing empty cache folders: the
first (cold) fills JAX's persistent compilation cache and mjstamp's trace
cache, the second (warm) reuses them. Reports each process's wall time and the
solve's own `wall_time_s`, the results of the warm run (distinct verified wall
codes, verified fraction, coverage), and the share of the warm solve spent in
rollouts and their gradients: the time of one batched log-posterior-with-
Jacobian evaluation (the rollouts, their tangents and the costs) times the
number of STAMP iterations, over the solve's wall time.

Target on a 2-core CPU: warm wall time <= 60 s.

Usage: python benchmarks/solve.py [--json] [--particles N ...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time


def _run_solve(cache: str, extra: list[str]) -> tuple[float, dict]:
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=os.path.join(cache, "jax"),
               MJSTAMP_TRACE_CACHE=os.path.join(cache, "trace"))
    cmd = [sys.executable, "-m", "mjstamp.cli", "solve", "billiards", "--json", "--quiet",
           *extra]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    return wall, json.loads(out.stdout.strip().splitlines()[-1])


def _rollout_seconds_per_iteration(particles: int) -> tuple[float, float]:
    """Seconds per batched log posterior with Jacobians (as in an SVGD step)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from mjstamp import tasks
    from mjstamp.svgd.steps import _logp_and_score, _logp_score_features

    task, _ = tasks.load("billiards", particles=particles)
    theta = task.initial_particles(jax.random.key(0), particles)
    svgd_eval = jax.jit(lambda t: _logp_score_features(task.log_posterior, t, "auto"))
    sgd_eval = jax.jit(lambda t: _logp_and_score(task.log_posterior, t))
    out = []
    for fn in (svgd_eval, sgd_eval):
        jax.block_until_ready(fn(theta))
        samples = []
        for _ in range(3):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(theta))
            samples.append(time.perf_counter() - t0)
        out.append(sorted(samples)[1])
    return out[0], out[1]


def main() -> None:
    """Runs the benchmark and prints its figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--particles", type=int, nargs="*", default=[None],
                        help="particle counts (default: the task's default)")
    args = parser.parse_args()
    rows = []
    for n in args.particles:
        extra = [] if n is None else ["--particles", str(n)]
        with tempfile.TemporaryDirectory() as cache:
            cold_wall, cold = _run_solve(cache, extra)
            warm_wall, warm = _run_solve(cache, extra)
        particles = warm["particles"]
        svgd_s, sgd_s = _rollout_seconds_per_iteration(particles)
        iters = warm["stamp"]
        rollout_s = iters["svgd_iters"] * svgd_s + iters["sgd_iters"] * sgd_s
        row = {
            "particles": particles,
            "cold_process_wall_s": cold_wall,
            "cold_solve_wall_time_s": cold["wall_time_s"],
            "warm_process_wall_s": warm_wall,
            "warm_solve_wall_time_s": warm["wall_time_s"],
            "warm_timings": warm["timings"],
            "svgd_iters": iters["svgd_iters"],
            "sgd_iters": iters["sgd_iters"],
            "rollout_and_gradient_s_per_svgd_iter": svgd_s,
            "rollout_and_gradient_s_per_sgd_iter": sgd_s,
            "rollout_and_gradient_share": rollout_s / warm["wall_time_s"],
            "distinct_verified_codes": warm["distinct_verified_codes"],
            "distinct_verified_task_plans": warm["distinct_verified_task_plans"],
            "verified_fraction": warm["verified_fraction"],
            "coverage": warm.get("coverage"),
            "target_warm_s": 60.0,
        }
        rows.append(row)
        if not args.json:
            print(json.dumps(row, indent=1), flush=True)
    import jax

    result = {"benchmark": "solve", "task": "billiards", "device": str(jax.devices()[0]),
              "cpus": os.cpu_count(), "rows": rows}
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
