"""The price of faithful physics: µs per particle-step before and after calibration.

For billiards, pushing (K = 2) and every scene of the suite, this draws the
particles a default solve starts from (`seeding.seed_particles`), calibrates
the gradient model on them as `solve` does, and times one value-and-grad of
the task's batched log posterior (the SVGD phase's driving computation: one
rollout, one pullback) with the one-iteration unrolled model ("before", what
every solve used until issue 10) and with the calibrated one ("after"), in
alternation in one process (ratios survive a shared machine's load). It also
reports each model's divergence from the scene's own physics on those
particles (MJX rollouts against MuJoCo C with the scene's solver).

With --collisions it prices MuJoCo C's colliders, ported (`mjstamp.scenes.
contacts`), against MJX's own on the same calibrated model and particles.

Usage: python benchmarks/perf/fidelity_price.py [--tasks billiards,pushing,rolling_ball,...]
       [--particles 128] [--repeats 5] [--collisions] [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import load_task as _task  # noqa: E402


def _timed(problem, theta, repeats: int):
    """Compiles value-and-grad of Σ log ρ; returns (fn, compile s)."""
    import jax
    import jax.numpy as jnp

    def total(th):
        logp = problem.logdensity(th)[0]
        return jnp.sum(jnp.where(jnp.isfinite(logp), logp, 0.0))

    fn = jax.jit(jax.value_and_grad(total))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(theta))
    return fn, time.perf_counter() - t0


def _us_per_particle_step(fns: dict, theta_j, repeats: int, steps: int) -> dict[str, float]:
    """{"us_per_particle_step_KEY": median µs} of each compiled fn, timed in turns."""
    import jax

    times = {key: [] for key in fns}
    for _ in range(repeats):
        for key, fn in fns.items():  # alternate: all see the same load
            t0 = time.perf_counter()
            jax.block_until_ready(fn(theta_j))
            times[key].append(time.perf_counter() - t0)
    return {f"us_per_particle_step_{key}": float(np.median(times[key]) / steps * 1e6)
            for key in fns}


def measure(name: str, *, particles: int, repeats: int, seed: int = 0) -> dict:
    """One task's row: before/after µs per particle-step and divergence."""
    import jax
    import jax.numpy as jnp

    from mjstamp import seeding
    from mjstamp.solver import SolveConfig, calibrate, mjx_divergence

    task = _task(name).build()
    theta, _ = seeding.seed_particles(task, jax.random.key(seed), particles)
    calibrated, cal = calibrate(task, theta, SolveConfig(calibration={"allow_unfaithful": True}))
    before = task.on_scene(task.scene.with_grad_options(gradient="unrolled", iterations=1,
                                                         ls_iterations=4))
    models = {"before": before, "after": calibrated}
    theta_j = jnp.asarray(theta, task.scene.dtype)
    fns, row = {}, {"task": name, "particles": particles, "horizon": task.horizon,
                    "gradient_after": cal.after.gradient, "iterations_after": cal.after.iterations}
    for key, t in models.items():
        fns[key], row[f"compile_{key}_s"] = _timed(t, theta_j, repeats)
        rollout = t.scene.rollout_fn(t.horizon, fields=("qpos",))
        qpos = np.asarray(rollout(*t.inputs(theta_j))["qpos"])
        div = mjx_divergence(t, theta, qpos)
        row[f"divergence_{key}_p95_m"] = float(np.percentile(div, 95))
    row.update(_us_per_particle_step(fns, theta_j, repeats, particles * task.horizon))
    row["price"] = row["us_per_particle_step_after"] / row["us_per_particle_step_before"]
    return row


def measure_collisions(name: str, *, particles: int, repeats: int, seed: int = 0) -> dict:
    """One task's row: µs per particle-step with MJX's own colliders and with C's ported.

    Both on the calibrated gradient model, value-and-grad of Σ log ρ, timed in
    alternation; each model's divergence from C on the same particles.
    """
    import jax
    import jax.numpy as jnp

    from mjstamp import colliders, seeding
    from mjstamp.solver import SolveConfig, calibrate, mjx_divergence

    task = _task(name).build()
    theta, _ = seeding.seed_particles(task, jax.random.key(seed), particles)
    ported, cal = calibrate(task, theta, SolveConfig(calibration={"allow_unfaithful": True}))
    theta_j = jnp.asarray(theta, task.scene.dtype)
    row = {"task": name, "particles": particles, "horizon": task.horizon,
           "gradient": cal.after.gradient,
           "approximate_pairs_mjx": len(_approximate(ported, mjx_own=True))}
    fns = {}
    for key in ("mjx", "ported"):
        # N.B. a fresh Scene per table: the table is read when a rollout is traced, and
        # a Scene memoises its compiled rollouts.
        scene = ported.scene.fresh()
        t = ported.on_scene(scene)
        block = colliders.mjx_own() if key == "mjx" else contextlib.nullcontext()
        try:
            with block:
                fns[key], row[f"compile_{key}_s"] = _timed(t, theta_j, repeats)
                rollout = t.scene.rollout_fn(t.horizon, fields=("qpos",))
                qpos = np.asarray(rollout(*t.inputs(theta_j))["qpos"])
        except NotImplementedError as e:  # MJX has no function for a pair of the scene
            row[f"us_per_particle_step_{key}"] = None
            row[f"error_{key}"] = str(e)
            continue
        row[f"divergence_{key}_p95_m"] = float(np.percentile(mjx_divergence(t, theta, qpos), 95))
    row.update(_us_per_particle_step(fns, theta_j, repeats, particles * task.horizon))
    if len(fns) == 2:
        row["price"] = row["us_per_particle_step_ported"] / row["us_per_particle_step_mjx"]
    return row


def _approximate(problem, *, mjx_own: bool) -> list:
    from mjstamp import colliders

    with colliders.mjx_own() if mjx_own else contextlib.nullcontext():
        return colliders.approximate_pairs(problem.scene.m)


def main() -> None:
    """Command line: measure each task, print a row each or one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="billiards,pushing")
    parser.add_argument("--particles", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--collisions", action="store_true",
                        help="price of C's ported colliders against MJX's own, both on the "
                             "calibrated model, instead of the calibration's price")
    args = parser.parse_args()
    import mjstamp

    mjstamp.configure()
    rows = []
    for name in args.tasks.split(","):
        print(f"[price] {name}", file=sys.stderr, flush=True)
        if args.collisions:
            rows.append(measure_collisions(name, particles=args.particles,
                                           repeats=args.repeats))
            if not args.json:
                r = rows[-1]
                print(f"{name:<16} " + "  ".join(
                    f"{k} {r.get(f'us_per_particle_step_{k}') or float('nan'):7.1f} us (div "
                    f"{r.get(f'divergence_{k}_p95_m', float('nan')):.2g} m)"
                    for k in ("mjx", "ported")) + f"  price {r.get('price', float('nan')):.2f}x",
                    flush=True)
            continue
        rows.append(measure(name, particles=args.particles, repeats=args.repeats))
        if not args.json:
            r = rows[-1]
            print(f"{name:<16} before {r['us_per_particle_step_before']:7.1f} us "
                  f"(div {r['divergence_before_p95_m']:.2g} m)  after "
                  f"{r['us_per_particle_step_after']:7.1f} us ({r['gradient_after']}, div "
                  f"{r['divergence_after_p95_m']:.2g} m)  price {r['price']:.2f}x", flush=True)
    if args.json:
        print(json.dumps({"benchmark": "fidelity_price", "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
