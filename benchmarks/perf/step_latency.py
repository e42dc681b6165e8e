"""Latency of one STAMP iteration's device work on billiards, by particle count.

Times, in this process and on JAX's default device, the compiled SVGD step
and SGD step that a billiards solve runs (the rollouts with their forward-mode
Jacobians, the kernel, the optimizer), and a forward-only rollout, for each
particle count: the median of `--repeats` calls after one untimed call, and the
compile seconds. On a GPU the figures hardly move with the particle count: a
step is a chain of small kernels over the 150-step horizon, so its latency,
not its arithmetic, sets STAMP's time (issue 12's time(800) / time(100)).

Run it under different `XLA_FLAGS` to compare compiler settings (for example
`--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL`, which records the
rollout's loops into CUDA graphs); `--precision float32` compares precisions.

Usage: python -m benchmarks.perf.step_latency [--particles 100 800] [--repeats 10]
           [--precision float64|float32] [--label NAME] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time


def _timed(fn, *args, repeats: int) -> tuple[float, float]:
    """(first call's seconds, median seconds of `repeats` calls after it)."""
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        samples.append(time.perf_counter() - t0)
    return first, statistics.median(samples)


def _row(n: int, repeats: int) -> dict:
    import jax
    import optax

    from mjstamp import registry, svgd

    problem = registry.load("billiards", particles=n)[0].build()
    theta = problem.init(jax.random.key(0), n)
    key = jax.random.key(1)
    svgd_step = jax.jit(svgd.build_svgd_step(problem.logdensity, problem.kernel,
                                             optax.adam(0.01), jacobian="fwd"))
    sgd_step = jax.jit(svgd.build_sgd_step(problem.logdensity, optax.adam(0.01),
                                           jacobian="fwd"))
    forward = jax.jit(lambda th: problem.evaluate(th, hard=True)[0].traj["qpos"])
    state = svgd.init(theta, optax.adam(0.01))
    row = {"particles": n, "horizon": problem.horizon}
    for name, fn, args in (("svgd_step", svgd_step, (state, key)),
                           ("sgd_step", sgd_step, (state, key)),
                           ("forward", forward, (theta,))):
        first, median = _timed(fn, *args, repeats=repeats)
        row[f"{name}_first_s"] = first
        row[f"{name}_s"] = median
        row[f"{name}_us_per_particle_step"] = 1e6 * median / (n * problem.horizon)
    return row


def main() -> None:
    """Runs the benchmark and prints its figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, nargs="*", default=[100, 800])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--precision", choices=("float64", "float32"), default="float64")
    parser.add_argument("--label", default="", help="a name for this run's settings")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    import mjstamp

    mjstamp.configure(precision=args.precision, compilation_cache=False)
    import jax

    rows = []
    for n in args.particles:
        rows.append(_row(n, args.repeats))
        if not args.json:
            print(json.dumps(rows[-1]), flush=True)
    result = {"benchmark": "step_latency", "task": "billiards", "label": args.label,
              "device": str(jax.devices()[0]), "device_kind": jax.devices()[0].device_kind,
              "jax": jax.__version__, "precision": args.precision,
              "xla_flags": os.environ.get("XLA_FLAGS", ""), "rows": rows}
    if len(rows) > 1:
        lo, hi = min(rows, key=lambda r: r["particles"]), max(rows, key=lambda r: r["particles"])
        result["svgd_step_ratio"] = hi["svgd_step_s"] / lo["svgd_step_s"]
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
