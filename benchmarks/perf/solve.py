"""Wall time of `mjstamp solve`: billiards (cold and warm), and pushing for K = 1..5.

Billiards (`--task billiards`, the default):

Runs the default solve in two fresh processes sharing empty cache folders: the
first (cold) fills JAX's persistent compilation cache and mjstamp's trace
cache, the second (warm) reuses them. Reports each process's wall time and the
solve's own `wall_time_s`, the results of the warm run (distinct verified wall
codes, verified fraction, coverage), and the share of the warm solve spent in
rollouts and their gradients: the time of one batched log-posterior-with-
Jacobian evaluation (the rollouts, their tangents and the costs) times the
number of STAMP iterations, over the solve's wall time.

Target on a 2-core CPU: warm wall time <= 60 s.

With `--devices 1 2` (the default) each particle count is solved cold and
warm once per device count (`mjstamp solve --devices K`, particles sharded
over K host devices, `mjstamp.parallel`), and the output carries
`shard_speedup` = warm STAMP seconds on 1 device / on the most devices, the
process CPU share during STAMP (`stamp_cpu_share`: 2.0 keeps two cores busy),
the compiles each solve did (`compiles`: count and seconds of those >= 0.5 s,
the largest by function; `cold_rollout_compiles`: how many distinct functions
that roll the scene out the cold solve compiled), and the median iteration times per phase (the
profile that says where a ratio below target comes from).

Pushing (`--task pushing --max-pushes 1 2 3 4 5`): the default solve for each
K, one process each, using the user's persistent caches (a K met for the
first time compiles). Reports each process's wall time, the solve's
`wall_time_s`, the first and median iteration times per phase, and
`stamp_steady_s` = SVGD iterations × median SVGD iteration + SGD iterations
× median SGD iteration: STAMP's time without compiling, which is what the
paper's Table III compares across K (runtime nearly flat in K on a GPU).
The ratio time(K=5) / time(K=1) is given for both.

Usage: python benchmarks/perf/solve.py [--json] [--particles N ...] [--devices K ...]
       python benchmarks/perf/solve.py --task pushing [--max-pushes 1 2 3 4 5] [--json]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import save_json  # noqa: E402

VERBOSE = False  # --verbose: the solves' status lines go to this process's stderr


def _run_solve(cache: str | None, extra: list[str], task: str = "billiards"):
    env = dict(os.environ)
    if cache is not None:
        env.update(JAX_COMPILATION_CACHE_DIR=os.path.join(cache, "jax"),
                   MJSTAMP_TRACE_CACHE=os.path.join(cache, "trace"))
    cmd = [sys.executable, "-m", "mjstamp.cli", "solve", task, "--json",
           *([] if VERBOSE else ["--quiet"]), *extra]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, env=env, stdout=subprocess.PIPE,
                         stderr=None if VERBOSE else subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        sys.exit(f"benchmarks/perf/solve.py: {' '.join(cmd[2:])} exited {out.returncode}:\n"
                 f"{(out.stderr or '')[-3000:]}")
    return wall, json.loads(out.stdout.strip().splitlines()[-1])


@functools.cache
def _device() -> dict:
    """The device the solves run on, asked in a child process.

    N.B. not in this one: JAX would hold the GPU (and its memory) while the
    solves run in their own processes.
    """
    code = ("import jax; d = jax.devices()[0]; "
            "print(d, '|', d.device_kind, '|', jax.device_count(), '|', jax.__version__)")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                         text=True).stdout.strip().splitlines()[-1]
    device, kind, count, version = (x.strip() for x in out.split("|"))
    return {"device": device, "device_kind": kind, "device_count": int(count),
            "jax": version}


def _rollout_seconds_per_iteration(particles: int) -> tuple[float, float]:
    """Seconds per batched log posterior with Jacobians (as in an SVGD step)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from mjstamp import registry

    problem = registry.load("billiards", particles=particles)[0].build()
    theta = problem.init(jax.random.key(0), particles)

    def score(t):
        """Log ρ (n,) and its n gradients from one pullback (an SGD step's work)."""
        logp, pullback = jax.vjp(lambda p: problem.logdensity(p)[0], t)
        return logp, pullback(jax.numpy.ones_like(logp))[0]

    def score_and_features(t):
        """Log ρ, ψ and their Jacobians in forward mode (d = 2 tangents): an SVGD step's work."""
        n, d = t.shape
        tangents = jax.numpy.broadcast_to(jax.numpy.eye(d)[:, None, :], (d, n, d))
        return jax.vmap(lambda v: jax.jvp(problem.logdensity, (t,), (v,)))(tangents)

    svgd_eval = jax.jit(score_and_features)
    sgd_eval = jax.jit(score)
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


def _pushing(max_pushes: list[int], as_json: bool) -> dict:
    rows = []
    for k in max_pushes:
        wall, out = _run_solve(None, ["--max-pushes", str(k)], task="pushing")
        it = out["iteration_seconds"]
        iters = out["stamp"]
        steady = iters["svgd_iters"] * it["svgd_median"] + iters["sgd_iters"] * it["sgd_median"]
        row = {
            "max_pushes": k,
            "dimension": 7 * k,
            "horizon": out["config"]["task"]["max_pushes"] * (
                out["config"]["task"]["approach_steps"] + out["config"]["task"]["push_steps"])
            + out["config"]["task"]["settle_steps"],
            "particles": out["particles"],
            "process_wall_s": wall,
            "solve_wall_time_s": out["wall_time_s"],
            "timings": out["timings"],
            "iteration_seconds": it,
            "svgd_iters": iters["svgd_iters"],
            "sgd_iters": iters["sgd_iters"],
            "stamp_steady_s": steady,
            "returned_plans": out["returned_plans"],
            "verified_fraction": out["verified_fraction"],
            "distinct_verified_task_plans": out["distinct_verified_task_plans"],
            "task_plans": [r["task_plan"] for r in out["task_plans"]],
        }
        rows.append(row)
        if not as_json:
            print(json.dumps(row, indent=1), flush=True)
    by_k = {r["max_pushes"]: r for r in rows}
    ratios = {}
    if 1 in by_k and 5 in by_k:
        ratios = {
            "stamp_steady_s_k5_over_k1": by_k[5]["stamp_steady_s"] / by_k[1]["stamp_steady_s"],
            "solve_wall_time_s_k5_over_k1": (by_k[5]["solve_wall_time_s"]
                                             / by_k[1]["solve_wall_time_s"]),
        }
    return {"rows": rows, **ratios}


def _billiards_row(n: int | None, k: int, profile: bool = True) -> dict:
    """Cold and warm default billiards solves with `n` particles over `k` devices.

    `profile=False` leaves out the in-process timing of one batched evaluation
    (two more compiles: minutes on a GPU), and with it the rollout share.
    """
    extra = ([] if n is None else ["--particles", str(n)]) + ["--devices", str(k)]
    with tempfile.TemporaryDirectory() as cache:
        cold_wall, cold = _run_solve(cache, extra)
        warm_wall, warm = _run_solve(cache, extra)
    particles = warm["particles"]
    iters = warm["stamp"]
    svgd_s = sgd_s = share = None
    if profile:
        svgd_s, sgd_s = _rollout_seconds_per_iteration(particles)
        rollout_s = iters["svgd_iters"] * svgd_s + iters["sgd_iters"] * sgd_s
        share = rollout_s / warm["wall_time_s"]
    return {
        "requested_particles": n,
        "particles": particles,
        "devices": k,
        "cold_process_wall_s": cold_wall,
        "cold_solve_wall_time_s": cold["wall_time_s"],
        "cold_compiles": cold.get("compiles"),
        # The compiled functions that roll the scene out, in the cold solve (issue 12: <= 2).
        "cold_rollout_compiles": len((cold.get("compiles") or {}).get("rollouts", [])),
        "warm_process_wall_s": warm_wall,
        "warm_solve_wall_time_s": warm["wall_time_s"],
        "warm_timings": warm["timings"],
        "warm_compiles": warm.get("compiles"),
        "warm_iteration_seconds": warm["iteration_seconds"],
        "stamp_cpu_share": warm["timings"].get("stamp_cpu_share"),
        "svgd_iters": iters["svgd_iters"],
        "sgd_iters": iters["sgd_iters"],
        "rollout_and_gradient_s_per_svgd_iter": svgd_s,
        "rollout_and_gradient_s_per_sgd_iter": sgd_s,
        "rollout_and_gradient_share": share,
        "distinct_verified_codes": warm["distinct_verified_codes"],
        "distinct_verified_task_plans": warm["distinct_verified_task_plans"],
        "verified_plans": warm["verified_plans"],
        "verified_fraction": warm["verified_fraction"],
        "coverage": warm.get("coverage"),
        "target_warm_s": 60.0,
    }


def main() -> None:
    """Runs the benchmark and prints its figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--task", choices=("billiards", "pushing"), default="billiards")
    parser.add_argument("--particles", type=int, nargs="*", default=[None],
                        help="billiards: particle counts (default: the task's default)")
    parser.add_argument("--max-pushes", type=int, nargs="*", default=[1, 2, 3, 4, 5],
                        help="pushing: values of K")
    parser.add_argument("--devices", type=int, nargs="*", default=[1, 2],
                        help="billiards: device counts to shard the particles over")
    parser.add_argument("--no-profile", action="store_true",
                        help="billiards: skip the in-process rollout timing (its compiles)")
    parser.add_argument("--save", metavar="FILE",
                        help="billiards: write the JSON so far to FILE after every row")
    parser.add_argument("--verbose", action="store_true",
                        help="the solves' status lines on stderr (where a long run stands)")
    args = parser.parse_args()
    global VERBOSE
    VERBOSE = args.verbose
    if args.task == "pushing":
        result = {"benchmark": "solve", "task": "pushing", **_device(),
                  "cpus": os.cpu_count(), **_pushing(args.max_pushes, args.json)}
        if args.json:
            print(json.dumps(result))
        return
    rows = []
    for n in args.particles:
        for k in args.devices:
            rows.append(_billiards_row(n, k, profile=not args.no_profile))
            if not args.json:
                print(json.dumps(rows[-1], indent=1), flush=True)
            if args.save:
                save_json(args.save, _billiards_result(rows, args.particles))
    result = _billiards_result(rows, args.particles)
    if args.json:
        print(json.dumps(result))


def _particle_scaling(rows: list[dict]) -> dict:
    """Per device count: warm solve time at the most particles over that at the fewest."""
    out = {}
    for k in sorted({r["devices"] for r in rows}):
        same = sorted((r for r in rows if r["devices"] == k), key=lambda r: r["particles"])
        if len(same) > 1:
            lo, hi = same[0], same[-1]
            out[str(k)] = {
                "particles": [lo["particles"], hi["particles"]],
                "warm_solve_ratio": hi["warm_solve_wall_time_s"] / lo["warm_solve_wall_time_s"],
                "warm_stamp_ratio": hi["warm_timings"]["stamp_s"] / lo["warm_timings"]["stamp_s"],
            }
    return out


def _billiards_result(rows: list[dict], particles: list) -> dict:
    """The benchmark's JSON for the rows measured so far."""
    speedups = {}
    for n in particles:
        same = [r for r in rows if r["requested_particles"] == n]
        one = [r for r in same if r["devices"] == 1]
        most = max(same, key=lambda r: r["devices"], default=None)
        if one and most["devices"] > 1:
            speedups[str(most["particles"])] = {
                "devices": most["devices"],
                "shard_speedup": one[0]["warm_timings"]["stamp_s"]
                / most["warm_timings"]["stamp_s"],
                "warm_solve_speedup": one[0]["warm_solve_wall_time_s"]
                / most["warm_solve_wall_time_s"],
            }
    return {"benchmark": "solve", "task": "billiards", **_device(),
            "cpus": os.cpu_count(), "rows": rows, "shard_speedup": speedups,
            "target_shard_speedup": 1.8, "particle_scaling": _particle_scaling(rows),
            "target_particle_scaling": 1.2}


if __name__ == "__main__":
    main()
