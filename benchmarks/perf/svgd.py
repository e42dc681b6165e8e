"""Time per SVGD step: mjstamp against blackjax on the same log density.

Both run one SVGD step with an RBF kernel of fixed bandwidth and plain SGD
(`optax.sgd`), jit-compiled, on the same target and particles; timings
alternate between the two within each repeat so machine noise hits both, and
the median over repeats is reported. ratio = blackjax time / mjstamp time (> 1:
mjstamp is faster).

Usage:
  python benchmarks/perf/svgd.py            # table
  python benchmarks/perf/svgd.py --json     # JSON on stdout
  python benchmarks/perf/svgd.py --sizes 100x2 400x16 --repeats 9
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from blackjax.vi import svgd as blackjax_svgd

from mjstamp.svgd import build_svgd_step, init, rbf

DEFAULT_SIZES = [(n, d) for n in (100, 400, 1000) for d in (2, 16, 40)]


def make_target(d: int, key: jax.Array):
    """A tilted, anisotropic Gaussian in d dimensions: log p(x) (unnormalised)."""
    k1, k2 = jax.random.split(key)
    a = jax.random.normal(k1, (d, d)) / jnp.sqrt(d) + jnp.eye(d)
    mu = jax.random.normal(k2, (d,))

    def logp(x):  # one particle, (d,) -> ()
        r = a @ (x - mu)
        return -0.5 * jnp.dot(r, r) + 0.1 * jnp.sum(jnp.log1p(x**2))

    return logp


def _time_loop(step, state, steps: int) -> float:
    start = time.perf_counter()
    for _ in range(steps):
        state = step(state)
    jax.block_until_ready(state)
    return (time.perf_counter() - start) / steps


def bench(n: int, d: int, *, repeats: int, steps: int, learning_rate: float = 1e-2):
    """Times one SVGD step of both libraries at n particles in d dimensions."""
    key = jax.random.key(n * 1000 + d)
    k_target, k_init = jax.random.split(key)
    logp = make_target(d, k_target)
    particles = 2.0 * jax.random.normal(k_init, (n, d))
    length_scale = float(d)  # blackjax: k = exp(-‖Δ‖² / length_scale)
    optimizer = optax.sgd(learning_rate)

    bj_kernel = blackjax_svgd.build_kernel(optimizer)
    grad_logp = jax.grad(logp)
    bj_step = jax.jit(lambda s: bj_kernel(s, grad_logp, blackjax_svgd.rbf_kernel))
    bj_state = blackjax_svgd.init(particles, {"length_scale": length_scale}, optimizer)

    # mjstamp: same kernel with bandwidth s = √length_scale, batched log density.
    mj_raw = build_svgd_step(
        lambda x: (jax.vmap(logp)(x), jnp.zeros((x.shape[0], 0), x.dtype)),  # (logp, no aux)
        rbf(bandwidth=length_scale**0.5), optimizer,
    )
    mj_step = jax.jit(lambda s: mj_raw(s, None)[0])
    mj_state = init(particles, optimizer)

    # Compile, and check that one step agrees.
    diff = float(
        jnp.max(jnp.abs(mj_step(mj_state).particles - bj_step(bj_state).particles))
    )
    _time_loop(mj_step, mj_state, 3)
    _time_loop(bj_step, bj_state, 3)
    mj_times, bj_times = [], []
    for _ in range(repeats):
        mj_times.append(_time_loop(mj_step, mj_state, steps))
        bj_times.append(_time_loop(bj_step, bj_state, steps))
    mj, bj = statistics.median(mj_times), statistics.median(bj_times)
    return {
        "n": n,
        "d": d,
        "mjstamp_s_per_step": mj,
        "blackjax_s_per_step": bj,
        "ratio": bj / mj,
        "max_abs_diff_one_step": diff,
    }


def main(argv=None) -> int:
    """Runs the benchmark over the sizes and prints a table or JSON; returns 0."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON to stdout")
    parser.add_argument("--repeats", type=int, default=7, help="timed repeats per size")
    parser.add_argument(
        "--steps", type=int, default=0, help="steps per repeat (0: about 0.1 s worth)"
    )
    parser.add_argument(
        "--sizes", nargs="*", default=None, help="NxD pairs, e.g. 100x2 1000x40"
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    sizes = (
        DEFAULT_SIZES
        if not args.sizes
        else [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes]
    )
    results = []
    for n, d in sizes:
        steps = args.steps or max(3, int(30_000 / max(n * n * d / 1e4, 1)))
        steps = min(steps, 200)
        row = bench(n, d, repeats=args.repeats, steps=steps)
        row["steps_per_repeat"] = steps
        results.append(row)
        # With --json the table goes to stderr, so stdout stays pure JSON.
        print(
            f"n={n:5d} d={d:3d}  "
            f"mjstamp {row['mjstamp_s_per_step'] * 1e3:8.3f} ms  "
            f"blackjax {row['blackjax_s_per_step'] * 1e3:8.3f} ms  "
            f"ratio {row['ratio']:6.2f}  |Δ|={row['max_abs_diff_one_step']:.1e}",
            file=sys.stderr if args.json else sys.stdout,
        )
    report = {
        "benchmark": "svgd_step",
        "kernel": "rbf, fixed bandwidth",
        "optimizer": "optax.sgd(1e-2)",
        "device": str(jax.devices()[0]),
        "platform": platform.platform(),
        "cpu_count": __import__("os").cpu_count(),
        "jax": jax.__version__,
        "repeats": args.repeats,
        "statistic": "median over repeats",
        "results": results,
        "min_ratio": min(r["ratio"] for r in results),
    }
    if args.json:
        json.dump(report, sys.stdout, indent=2)
        print()
    else:
        print(f"min ratio (blackjax / mjstamp): {report['min_ratio']:.2f}")
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    raise SystemExit(main())
