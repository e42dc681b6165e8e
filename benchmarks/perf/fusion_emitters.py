"""XLA's CPU fusion emitters on and off: compile seconds and µs per particle-step, per task.

For each task (billiards, pushing K = 2, the suite's scenes, the Jaco), a child
process per setting (`--xla_cpu_use_fusion_emitters=true|false`: the flag is
read once, when JAX starts) builds the task, draws the particles a solve
screens (`seeding.seed_particles`, seed 0), and times value-and-gradient of the
batched log posterior, STAMP's driving computation: its compile seconds and
the median of `--repeats` calls after it, per particle-step. The two settings
of a task run one after the other, so they see about the same load; the value
and the gradient's norm are reported for both (equal to rounding, or where a
chaotic rollout amplifies the last bits, close).

`mjstamp.configure` turns the emitters off (its docstring says why); this is
the measurement behind that default.

Usage: python benchmarks/perf/fusion_emitters.py [--tasks billiards,jaco,...]
       [--particles 32] [--repeats 3] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

FLAG = "--xla_cpu_use_fusion_emitters"
ALL = ("billiards,pushing,rolling_ball,pachinko,arm_strike,pendulum_bells,pusher,bank_shot,"
       "wedges,crate_ledge,cans,jaco")


def measure(name: str, particles: int, repeats: int) -> dict:
    """In this process (its XLA flags as given): one task's compile s and µs per particle-step."""
    import mjstamp

    mjstamp.configure(precision="float64", compilation_cache=False)
    import jax
    import jax.numpy as jnp
    import numpy as np

    import mjstamp.tasks.jaco  # noqa: F401 - registers "jaco"
    from benchmarks.common import load_task
    from mjstamp import seeding

    task = load_task(name).build()
    theta, _ = seeding.seed_particles(task, jax.random.key(0), particles)
    theta = jnp.asarray(theta, task.scene.dtype)

    def total(th):
        logp = task.logdensity(th)[0]
        return jnp.sum(jnp.where(jnp.isfinite(logp), logp, 0.0))

    fn = jax.jit(jax.value_and_grad(total))
    t0 = time.perf_counter()
    value, grad = jax.block_until_ready(fn(theta))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(theta))
        times.append(time.perf_counter() - t0)
    return {"compile_s": compile_s,
            "us_per_particle_step": float(np.median(times)) / (particles * task.horizon) * 1e6,
            "value": float(value), "grad_norm": float(jnp.linalg.norm(grad)),
            "xla_flags": os.environ.get("XLA_FLAGS", "")}


def _child(name: str, on: bool, particles: int, repeats: int) -> dict:
    env = {**os.environ, "XLA_FLAGS": f"{FLAG}={'true' if on else 'false'}"}
    code = (f"import json, sys; sys.path.insert(0, {str(Path(__file__).resolve().parents[2])!r}); "
            "from benchmarks.perf.fusion_emitters import measure; "
            f"print(json.dumps(measure({name!r}, {particles}, {repeats})))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if out.returncode:
        return {"error": (out.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    """Command line: each task with the emitters on, then off; a row each or one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default=ALL)
    parser.add_argument("--particles", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows = {}
    for name in args.tasks.split(","):
        on = _child(name, True, args.particles, args.repeats)
        off = _child(name, False, args.particles, args.repeats)
        row = {"on": on, "off": off}
        if "error" not in on and "error" not in off:
            row["speedup"] = on["us_per_particle_step"] / off["us_per_particle_step"]
            row["compile_speedup"] = on["compile_s"] / off["compile_s"]
        rows[name] = row
        if not args.json:
            print(name, json.dumps(row), flush=True)
    if args.json:
        print(json.dumps({"particles": args.particles, "repeats": args.repeats,
                          "cpu_count": os.cpu_count(), "tasks": rows}, indent=1))


if __name__ == "__main__":
    main()
