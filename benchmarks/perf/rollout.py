"""Rollout speed of the billiards scene: MJX forward and value-and-grad vs MuJoCo C.

Prints one JSON object (with --json) holding, for N = 1, 64, 256, 1024 particles:
µs per particle-step of an MJX forward rollout, of an MJX value-and-grad rollout
(reverse mode, and forward mode with d = 2 tangents as a solve runs at d <= 2),
and of MuJoCo C stepping the same scene (`mujoco.rollout`, all cores) measured in
the same run, with the ratios MJX / C (the figure that counts on a noisy, shared
machine). It also times two fresh processes that build and run the
value-and-grad rollout: one with empty caches (cold) and one reusing them
(warm): JAX's persistent compilation cache and mjstamp's trace cache
(`mjstamp.tracecache`). The issue's target is warm start-to-first-result within
10 s.

With `--devices K` (K host devices, one per core) the value-and-grad and
forward rollouts are sharded over the particles (`mjstamp.parallel`), as a
solve shards them; MuJoCo C uses every core either way.

Usage: python benchmarks/perf/rollout.py [--json] [--horizon 200] [--repeats 5] [--devices K]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

PARTICLES = (1, 64, 256, 1024)


def _setup(cache_dir: str | None):
    import jax

    jax.config.update("jax_enable_x64", True)
    if cache_dir:
        # Both caches: compiled executables (JAX) and traced functions (mjstamp).
        jax.config.update("jax_compilation_cache_dir", cache_dir)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        os.environ["MJSTAMP_TRACE_CACHE"] = os.path.join(cache_dir, "trace")
    return jax


def _functions(scene, horizon, example=None, devices=1):
    """Forward and value-and-grad rollouts; with `example`, via the trace cache."""
    import jax
    import jax.numpy as jnp

    from mjstamp import parallel
    from mjstamp.tracecache import cached_jit

    rollout = scene.rollout_fn(horizon, fields=("qpos",))
    dofs = [scene.dof_adr("cue_x"), scene.dof_adr("cue_y")]

    def one_shard(qv):  # (n, nq + 2): initial positions and cue velocities side by side
        qpos0, v = qv[:, :scene.m.nq], qv[:, scene.m.nq:]
        qvel0 = jnp.zeros((v.shape[0], scene.m.nv), v.dtype).at[:, dofs].set(v)
        return rollout(qpos0, qvel0)["qpos"]

    sharded = parallel.shard_particles(one_shard, devices)

    def final_qpos(qpos0, v):
        return sharded(jnp.concatenate([qpos0, v], axis=1))

    loss = lambda q, v: jnp.sum(final_qpos(q, v)[:, -1] ** 2)  # noqa: E731
    value_and_grad = jax.value_and_grad(loss, argnums=1)
    if example is not None:
        key = f"benchmark-rollout billiards horizon={horizon}"
        return None, cached_jit(value_and_grad, key, *example)
    return jax.jit(final_qpos), jax.jit(value_and_grad), jax.jit(_forward_mode(final_qpos))


def _forward_mode(final_qpos):
    """Per-particle values and gradients carrying d = 2 tangents through the rollout.

    What a solve runs at d <= 2 (`svgd.build_evaluate`, 'auto'): each particle's
    loss ‖q_T‖² and its gradient in v, from one pass with two tangents, by the
    solve's own `value_and_batched_jacobian`.
    """
    import jax.numpy as jnp

    from mjstamp.svgd._jacobian import value_and_batched_jacobian

    def value_and_grads(q, v):
        def per_particle(x):
            return jnp.sum(final_qpos(q, x)[:, -1] ** 2, axis=1, keepdims=True)

        return value_and_batched_jacobian(per_particle, v, "fwd")

    return value_and_grads


def _inputs(scene, n, seed=0):
    import numpy as np

    rng = np.random.default_rng(seed)
    qpos0, _ = scene.initial_state()
    return np.tile(qpos0, (n, 1)), rng.uniform(-3, 3, (n, 2))


def _time(fn, repeats):
    import jax

    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        samples.append(time.perf_counter() - t0)
    samples.sort()
    return samples[len(samples) // 2]


def _mujoco_c(scene, n, horizon, repeats):
    """µs per particle-step of MuJoCo C (scene's gradient model), all cores."""
    import mujoco
    import mujoco.rollout
    import numpy as np

    m = scene.m_grad
    qpos0, v = _inputs(scene, n)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    d = mujoco.MjData(m)
    state0 = np.empty((n, mujoco.mj_stateSize(m, spec)))
    for i in range(n):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = qpos0[i]
        d.qvel[[scene.dof_adr("cue_x"), scene.dof_adr("cue_y")]] = v[i]
        mujoco.mj_getState(m, d, state0[i], spec)
    datas = [mujoco.MjData(m) for _ in range(os.cpu_count() or 1)]
    ctrl = np.zeros((n, horizon, m.nu))

    def run():
        return mujoco.rollout.rollout(m, datas, state0, ctrl, nstep=horizon)

    run()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        samples.append(time.perf_counter() - t0)
    samples.sort()
    return samples[len(samples) // 2] / (n * horizon) * 1e6


def probe(cache_dir: str, horizon: int) -> None:
    """Child process: time from start to the first value-and-grad result."""
    t0 = time.perf_counter()
    _setup(cache_dir)
    from mjstamp.scenes import Scene

    scene = Scene.shipped("billiards")
    qpos0, v = _inputs(scene, 64)
    _, value_and_grad = _functions(scene, horizon, example=(qpos0, v))
    import jax

    jax.block_until_ready(value_and_grad(qpos0, v))
    print(json.dumps({"start_to_first_result_s": time.perf_counter() - t0}))


def _spawn_probe(cache_dir: str, horizon: int) -> float:
    # N.B. wall time of the whole child, interpreter start and imports included.
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, __file__, "--probe", cache_dir, "--horizon", str(horizon)],
        check=True,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    json.loads(out.stdout.strip().splitlines()[-1])
    return wall


def main() -> None:
    """Runs the benchmark and prints its figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--horizon", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--particles", type=int, nargs="*", default=list(PARTICLES))
    parser.add_argument("--probe", metavar="CACHE_DIR", help=argparse.SUPPRESS)
    parser.add_argument("--skip-compile", action="store_true", help="no cold/warm probes")
    parser.add_argument("--devices", type=int, default=1,
                        help="host devices to shard the MJX rollouts over")
    args = parser.parse_args()
    if args.probe:
        probe(args.probe, args.horizon)
        return

    if args.devices > 1:
        from mjstamp.parallel import request_host_devices

        request_host_devices(args.devices)
    jax = _setup(None)
    from mjstamp.scenes import Scene

    scene = Scene.shipped("billiards")
    forward, value_and_grad, fwd_grad = _functions(scene, args.horizon, devices=args.devices)
    T = args.horizon
    rows = []
    for n in args.particles:
        qpos0, v = _inputs(scene, n)
        t0 = time.perf_counter()
        jax.block_until_ready(value_and_grad(qpos0, v))
        compile_vg = time.perf_counter() - t0
        jax.block_until_ready(forward(qpos0, v))
        fwd = _time(lambda q=qpos0, v=v: forward(q, v), args.repeats) / (n * T) * 1e6
        vg = _time(lambda q=qpos0, v=v: value_and_grad(q, v), args.repeats) / (n * T) * 1e6
        jax.block_until_ready(fwd_grad(qpos0, v))
        vgf = _time(lambda q=qpos0, v=v: fwd_grad(q, v), args.repeats) / (n * T) * 1e6
        c = _mujoco_c(scene, n, T, args.repeats)
        rows.append({
            "particles": n,
            "mjx_forward_us_per_particle_step": fwd,
            "mjx_value_and_grad_us_per_particle_step": vg,
            "mujoco_c_us_per_particle_step": c,
            "forward_over_c": fwd / c,
            "value_and_grad_over_c": vg / c,
            # Forward mode (2 tangents), as a solve differentiates at d <= 2.
            "mjx_value_and_grad_fwd_us_per_particle_step": vgf,
            "value_and_grad_fwd_over_c": vgf / c,
            "first_call_s": compile_vg,
        })
        if not args.json:
            print(f"N={n:5d}  fwd {fwd:8.2f} us  v&g {vg:8.2f} us  v&g fwd-mode {vgf:8.2f} us"
                  f"  C {c:6.3f} us  (fwd/C {fwd / c:6.1f}, v&g/C {vg / c:6.1f}, "
                  f"fwd-mode/C {vgf / c:6.1f})", flush=True)

    result = {
        "benchmark": "rollout",
        "scene": "billiards",
        "horizon": T,
        "precision": scene.precision,
        "device": str(jax.devices()[0]),
        "devices": args.devices,
        "machine": f"{platform.machine()} {os.cpu_count()} cpus",
        "rows": rows,
    }
    if not args.skip_compile:
        with tempfile.TemporaryDirectory() as cache:
            cold = _spawn_probe(cache, T)
            warm = _spawn_probe(cache, T)
        result["compile"] = {
            "cold_process_start_to_first_result_s": cold,
            "warm_cache_process_start_to_first_result_s": warm,
            "target_warm_s": 10.0,
        }
        if not args.json:
            print(f"process start to first value-and-grad: cold {cold:.1f} s, "
                  f"warm cache {warm:.1f} s")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
