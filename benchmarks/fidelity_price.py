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

Usage: python benchmarks/fidelity_price.py [--tasks billiards,pushing,rolling_ball,...]
       [--particles 128] [--repeats 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _task(name: str):
    from mjstamp import tasks

    if name in tasks.names():
        return tasks.load(name)[0]
    from suite.tasks import SUITE

    return SUITE[name]()


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


def measure(name: str, *, particles: int, repeats: int, seed: int = 0) -> dict:
    """One task's row: before/after µs per particle-step and divergence."""
    import jax
    import jax.numpy as jnp

    from mjstamp import seeding
    from mjstamp.solve import SolveConfig, calibrate, mjx_divergence

    task = _task(name).build()
    theta, _ = seeding.seed_particles(task, jax.random.key(seed), particles)
    calibrated, cal = calibrate(task, theta, SolveConfig(allow_unfaithful=True))
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
    times = {key: [] for key in models}
    for _ in range(repeats):
        for key, fn in fns.items():  # alternate: both see the same load
            t0 = time.perf_counter()
            jax.block_until_ready(fn(theta_j))
            times[key].append(time.perf_counter() - t0)
    steps = particles * task.horizon
    for key in models:
        row[f"us_per_particle_step_{key}"] = float(np.median(times[key]) / steps * 1e6)
    row["price"] = row["us_per_particle_step_after"] / row["us_per_particle_step_before"]
    return row


def main() -> None:
    """Command line: measure each task, print a row each or one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="billiards,pushing")
    parser.add_argument("--particles", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    from mjstamp.cli import configure_jax

    configure_jax()
    rows = []
    for name in args.tasks.split(","):
        print(f"[price] {name}", file=sys.stderr, flush=True)
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
