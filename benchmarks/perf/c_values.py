"""C values with MJX step Jacobians, against MJX rollout AD: accuracy and cost (issue 28, item 5).

Gradient models of f(θ) = c₁·qpos_T + c₂·mean_t qpos_t (`scenes.check`'s
objective, c₁ and c₂ random unit vectors) on each task's own particles
(`check.task_particles`: θ uniform in the task's box, its inputs and horizon):

- `rollout-ad`: today's method, `check.py`'s `_gradients` path: reverse-mode AD
  of the MJX rollout with the gradient model `check` calibrates on these
  particles (`fidelity.calibrate`: one unrolled iteration or the implicit
  solver gradient).
- `c+jac-sweep[s]`, `c+jac-scan[s]`: the trajectory is MuJoCo C's, with the
  scene's own solver (`mujoco.rollout`, every core); each step's Jacobian comes
  from one `mjx.step` at C's state, all n·T of them in one batch
  (`benchmarks/perf/stepjac.py`), chained by a backward sweep or an associative
  scan. `s` is where the step's constraint solution comes from: `mjx` (the
  calibrated gradient model solves it at C's state, as the brief asks) or `c`
  (C's own solution, recovered from C's next velocity, with the implicit
  derivative read there: no solver loop).
- `c+vjp[s]` (extra): the same backward sweep without Jacobians, one VJP of
  `mjx.step` at C's state per step (sequential in T, as rollout AD).

Accuracy: relative error ‖g − fd‖ / max(‖g‖, ‖fd‖) per particle against central
differences of the scene's own physics (float64 MuJoCo C, eps 1e-6), median
and p95; `fd_floor_*` is the same error of eps against 10·eps, what the finite
differences themselves can resolve (a contact that starts or ends between the
two makes it large). Cost: µs per particle-step of each method's whole
gradient (C rollout included for the C methods), measured in one process with
the parts alternating, median of `--repeats`; the parts (C rollout, Jacobians,
chaining, VJP sweep, the rest) are reported too. Diagnostics:
`one_step_defect_{s}_*` (largest |qpos| difference of MJX's step from C's state
against C's next state: where MJX collides or solves differently from C) and
`rollout_divergence_p95_m` (MJX's own rollout against C's,
`fidelity.divergence` of tracked points).

GPU: no device was drawn for this measurement; `gpu` in the JSON is an
analysis from the CPU parts and the arrays' sizes (C rollouts stay on the
host's cores; the n·T Jacobians are one flat batch of independent step JVPs;
memory n·T·2nv·(2nv + nu) float64).

Usage: python benchmarks/perf/c_values.py [--scenes billiards,pushing,...] [--particles 64]
    [--repeats 3] [--batch 64] [--save]

`--save` merges each scene's row into benchmarks/results/c_values.json
(replacing that scene's row), so scenes can be measured in separate processes.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import common  # noqa: E402

RESULTS = common.RESULTS / "c_values.json"
SCENES = ("billiards", "pushing", "bank_shot", "pusher", "rolling_ball", "pachinko",
          "arm_strike")
METHODS = ("rollout-ad", "c+jac-sweep[mjx]", "c+jac-scan[mjx]", "c+vjp[mjx]",
           "c+jac-sweep[c]", "c+jac-scan[c]", "c+vjp[c]")


def _problem(name: str):
    return common.load_task(name).build()


def _timed(fn, *args):
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def _stats(prefix: str, x: np.ndarray) -> dict:
    x = np.asarray(x, float)
    return {f"{prefix}_median": float(np.median(x)), f"{prefix}_p95": float(np.percentile(x, 95)),
            f"{prefix}_max": float(np.max(x))}


def _temp_bytes(jitted, *args) -> int:
    return int(jitted.lower(*args).compile().memory_analysis().temp_size_in_bytes)


# N.B. over 80 lines: one scene's whole measurement, in the order it is reported.
def run_scene(name: str, *, particles: int, repeats: int, seed: int, fd_eps: float,
              batch: int, say) -> dict:
    """One scene's row: accuracy and cost of every method."""
    import jax
    import jax.numpy as jnp

    from benchmarks.perf import stepjac
    from mjstamp.scenes import check, fidelity

    problem = _problem(name)
    draws = check.task_particles(problem)
    scene = problem.scene
    m, T = scene.m, draws.horizon
    # The same draws as `check`: c₁, c₂, then θ, from one generator.
    rng = np.random.default_rng(seed)
    c1, c2 = rng.normal(size=(2, m.nq))
    c1, c2 = c1 / np.linalg.norm(c1), c2 / np.linalg.norm(c2)
    theta = draws.sample(rng, particles)
    inputs = tuple(np.asarray(a, np.float64) for a in draws.to_inputs(theta, np))
    say(f"{name}: calibrating the gradient model as check does")
    cal = fidelity.calibrate(scene, *inputs, progress=say)
    a = cal.after
    scene = scene.with_grad_options(**a.options())
    theta_j = jnp.asarray(theta, scene.dtype)

    # rollout-ad: check._gradients' objective and value_and_grad.
    rollout = scene.rollout_fn(T, fields=("qpos",))

    def objective(th):
        qpos = rollout(*draws.to_inputs(th, jnp))["qpos"]
        return jnp.sum(qpos[:, -1] @ c1 + qpos.mean(axis=1) @ c2)

    ad = jax.jit(jax.value_and_grad(objective))

    # C values + step Jacobians, for each source of the constraint solution.
    obj = stepjac.check_objective(c1, c2)
    jac_fn = {s: stepjac.build_step_jacobians(scene, solution=s, batch=batch)
              for s in stepjac.SOLUTIONS}
    vjp_fn = {s: stepjac.build_vjp_sweep(scene, solution=s) for s in stepjac.SOLUTIONS}

    def to_inputs(th):
        return draws.to_inputs(th, jnp)

    @jax.jit
    def cotangents(qpos, qvel, ctrl):
        traj = stepjac.Trajectory(qpos, qvel, ctrl)
        value, dqpos, dqvel = stepjac.objective_gradients(obj, traj, scene.dtype)
        return value, stepjac.tangent_cotangents(scene, traj, dqpos, dqvel)

    @jax.jit
    def finish(th, qpos0, lam0, gu):
        g_qpos0, g_qvel0 = stepjac.initial_gradients(scene, qpos0, lam0)
        return stepjac.pullback(to_inputs, th, g_qpos0, g_qvel0, gu)

    def c_traj():
        return stepjac.c_trajectory(scene, *inputs)

    say(f"{name}: compiling ({particles} x {T} steps)")
    compile_s = {}
    (_, g_ad), compile_s["rollout-ad"] = _timed(ad, theta_j)
    traj = c_traj()
    tj = tuple(jnp.asarray(x, scene.dtype) for x in traj)
    (value, G), compile_s["cotangents"] = _timed(cotangents, *tj)
    grads = {"rollout-ad": np.asarray(g_ad)}
    jac = {}
    for s in stepjac.SOLUTIONS:
        jac[s], compile_s[f"jacobians_{s}"] = _timed(jac_fn[s], traj)
        chained = {
            f"c+jac-sweep[{s}]": _timed(stepjac.chain_sweep, jac[s].A, jac[s].B, G),
            f"c+jac-scan[{s}]": _timed(stepjac.chain_scan, jac[s].A, jac[s].B, G),
            f"c+vjp[{s}]": _timed(vjp_fn[s], traj, G),
        }
        compile_s[f"chain_sweep_{s}"] = chained[f"c+jac-sweep[{s}]"][1]
        compile_s[f"chain_scan_{s}"] = chained[f"c+jac-scan[{s}]"][1]
        compile_s[f"vjp_{s}"] = chained[f"c+vjp[{s}]"][1]
        for key, ((lam0, gu), _) in chained.items():
            g, compile_s["finish"] = _timed(finish, theta_j, tj[0][:, 0], lam0, gu)
            grads[key] = np.asarray(g)

    say(f"{name}: timing, {repeats} rounds, methods alternating")
    samples: dict[str, list[float]] = {}

    def timed(part, fn, *args):
        out, dt = _timed(fn, *args)
        samples.setdefault(part, []).append(dt)
        return out

    for _ in range(repeats):
        timed("rollout-ad", ad, theta_j)
        traj = timed("c_rollout", c_traj)
        tj = tuple(jnp.asarray(x, scene.dtype) for x in traj)
        _, G = timed("cotangents", cotangents, *tj)
        for s in stepjac.SOLUTIONS:
            jac[s] = timed(f"jacobians_{s}", jac_fn[s], traj)
            timed(f"vjp_{s}", vjp_fn[s], traj, G)
        lam0, gu = timed("chain_sweep", stepjac.chain_sweep, jac["mjx"].A, jac["mjx"].B, G)
        timed("chain_scan", stepjac.chain_scan, jac["mjx"].A, jac["mjx"].B, G)
        timed("finish", finish, theta_j, tj[0][:, 0], lam0, gu)
    per = particles * T
    us = {p: float(np.median(v)) / per * 1e6 for p, v in samples.items()}
    common = us["c_rollout"] + us["cotangents"] + us["finish"]
    cost = {"rollout-ad": us["rollout-ad"]}
    for s in stepjac.SOLUTIONS:
        cost[f"c+jac-sweep[{s}]"] = common + us[f"jacobians_{s}"] + us["chain_sweep"]
        cost[f"c+jac-scan[{s}]"] = common + us[f"jacobians_{s}"] + us["chain_scan"]
        cost[f"c+vjp[{s}]"] = common + us[f"vjp_{s}"]

    say(f"{name}: central differences in MuJoCo C ({4 * draws.dim * particles} rollouts)")
    fd = check.finite_differences(scene, draws.to_inputs, theta, c1, c2, fd_eps, "scene")
    fd10 = check.finite_differences(scene, draws.to_inputs, theta, c1, c2, 10 * fd_eps, "scene")
    every = np.ones(particles, bool)
    methods = {}
    for key in METHODS:
        g = grads[key]
        finite = np.isfinite(g).all(axis=1)
        rel = check.relative_errors(g, fd, finite)
        methods[key] = {
            **(_stats("rel_err", rel) if rel.size else
               {"rel_err_median": None, "rel_err_p95": None, "rel_err_max": None}),
            "nonfinite": int((~finite).sum()),
            "us_per_particle_step": cost[key],
        }
    agree = {}
    for s in stepjac.SOLUTIONS:
        ref = grads[f"c+jac-sweep[{s}]"]
        scale = max(float(np.abs(ref).max()), 1e-300)
        for k in (f"c+jac-scan[{s}]", f"c+vjp[{s}]"):
            agree[f"{k}_vs_sweep_max_rel"] = float(np.abs(grads[k] - ref).max() / scale)
    # Diagnostics: where MJX's dynamics part from C's.
    defect = {s: stepjac.one_step_defect(scene, traj, jac[s]).max(axis=1)
              for s in stepjac.SOLUTIONS}
    qpos_mjx = np.asarray(rollout(*inputs)["qpos"], np.float64)
    div = fidelity.divergence(fidelity.tracked_points(m, qpos_mjx),
                              fidelity.tracked_points(m, traj.qpos[:, 1:]))
    chunk = min(batch, per)
    k = 2 * m.nv
    return {
        "scene": name,
        "nq": m.nq, "nv": m.nv, "nu": m.nu, "horizon": T, "dim": draws.dim,
        "particles": particles,
        "gradient_model": fidelity.describe(a.gradient, a.iterations),
        "ls_iterations": a.ls_iterations,
        "calibration_faithful": cal.faithful,
        "fd_eps": fd_eps,
        **_stats("fd_floor", check.relative_errors(fd10, fd, every)),
        "methods": methods,
        "chainings_agree": agree,
        **{key: v for s in stepjac.SOLUTIONS
           for key, v in _stats(f"one_step_defect_{s}", defect[s]).items()},
        "rollout_divergence_p95_m": float(np.percentile(div, 95)),
        "tolerance_m": cal.tolerance_m,
        "value_c_vs_mjx_max": float(np.abs(
            np.asarray(value) - (qpos_mjx[:, -1] @ c1 + qpos_mjx.mean(1) @ c2)).max()),
        "parts_us_per_particle_step": us,
        "mujoco_c_us_per_particle_step": us["c_rollout"],
        "compile_s": compile_s,
        "jacobian_batch": chunk,
        "jacobian_bytes_per_particle": T * k * (k + m.nu) * 8,
        "jacobian_temp_bytes_per_state": {
            s: _temp_bytes(jac_fn[s].jitted, *tj) / chunk for s in stepjac.SOLUTIONS},
        "rollout_ad_temp_bytes_per_particle": _temp_bytes(ad, theta_j) / particles,
    }


def _gpu_analysis(rows: list[dict]) -> dict:
    """What the measured parts imply on a GPU host; a reading, not a measurement."""
    out = {
        "measured": False,
        "why": "no device machine was drawn for this task: derived from the CPU parts, the "
               "arrays' sizes and benchmarks/results/step_latency_gpu (H200)",
        "rollout_ad": "T sequential steps, forward then backward, each a batch of n: "
                      "latency-bound at the particle counts a solve uses (H200, billiards, "
                      "T = 150: 0.140 s per value-and-grad at n = 100 and 0.129 s at n = 800, "
                      "about 0.9 ms per step; step_latency_gpu/lat_default.json)",
        "c_rollout": "stays on the host's CPU cores (mujoco.rollout): the µs per "
                     "particle-step measured here on 2 shared cores, times 2 / the host's "
                     "cores, is a floor under every C method there and grows with n·T, "
                     "while rollout AD's GPU time barely grows with n",
        "jacobians": "n·T independent mjx.step JVPs with 2nv + nu tangents, one flat batch "
                     "with no sequential dependence: throughput-bound, the shape a GPU "
                     "runs best; with solution 'c' there is no solver while_loop, so no "
                     "batch waits for its slowest state; with 'mjx' every chunk runs the "
                     "loop until its slowest state converges",
        "chain_sweep": "T sequential batched matrix-vector products of size 2nv: small, but "
                       "T dependent launches (latency-bound, as rollout AD's T steps)",
        "chain_scan": "O(log T) depth of batched (2nv)³ matrix products: a handful of "
                      "launches, about 2T matrix products of work per particle; the "
                      "fully parallel form",
        "c+vjp": "sequential in T like rollout AD, one MJX forward and backward per step "
                 "batched over n: the same latency as rollout AD on a GPU, cheapest on a "
                 "CPU",
        "memory": {},
    }
    for r in rows:
        out["memory"][r["scene"]] = {
            "jacobians_MB_per_1000_particles": r["jacobian_bytes_per_particle"] * 1e-3,
            "jacobian_temp_MB_per_1000_states": {
                s: v * 1e-3 for s, v in r["jacobian_temp_bytes_per_state"].items()},
            "rollout_ad_temp_MB_per_1000_particles":
                r["rollout_ad_temp_bytes_per_particle"] * 1e-3,
        }
    return out


def main(argv=None) -> int:
    """Runs the benchmark; prints one JSON object and optionally merges it into RESULTS."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--particles", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fd-eps", type=float, default=1e-6)
    parser.add_argument("--batch", type=int, default=64,
                        help="states per vmapped chunk of the step Jacobians")
    parser.add_argument("--save", action="store_true",
                        help=f"merge the rows into {RESULTS}, one row per scene")
    args = parser.parse_args(argv)
    import mjstamp

    mjstamp.configure(precision="float64")
    import jax

    def say(text):
        print(f"[c_values] {text}", file=sys.stderr, flush=True)

    started = time.perf_counter()
    rows = []
    for name in args.scenes.split(","):
        rows.append(run_scene(name, particles=args.particles, repeats=args.repeats,
                              seed=args.seed, fd_eps=args.fd_eps, batch=args.batch, say=say))
        say(json.dumps({k: rows[-1][k] for k in ("scene", "methods")}))
    result = {
        "benchmark": "c_values",
        "precision": "float64",
        "device": str(jax.devices()[0]),
        "machine": f"{platform.machine()} {len(os.sched_getaffinity(0))} cpus (shared)",
        "args": {k: v for k, v in vars(args).items() if k not in ("scenes", "save")},
        "scenes": rows,
        "wall_s": time.perf_counter() - started,
    }
    if args.save:
        result = _merge(result)
    result["gpu"] = _gpu_analysis(result["scenes"])
    print(json.dumps(result, indent=1))
    if args.save:
        common.save_json(RESULTS, result, indent=1, newline=True)
    return 0


def _merge(result: dict) -> dict:
    """RESULTS with this run's rows in place of the same scenes' (same settings only)."""
    try:
        old = json.loads(RESULTS.read_text())
    except (OSError, ValueError):
        return result
    def settings(args):  # N.B. particles may differ per row (each row has its own)
        return {k: v for k, v in (args or {}).items() if k != "particles"}

    if settings(old.get("args")) != settings(result["args"]):
        return result  # other settings: this run replaces the file
    fresh = {r["scene"]: r for r in result["scenes"]}
    kept = [r for r in old.get("scenes", []) if r["scene"] not in fresh]
    order = {name: i for i, name in enumerate(SCENES)}
    rows = sorted(kept + list(fresh.values()), key=lambda r: order.get(r["scene"], len(order)))
    return {**result, "scenes": rows, "wall_s": old.get("wall_s", 0.0) + result["wall_s"]}


if __name__ == "__main__":
    sys.exit(main())
