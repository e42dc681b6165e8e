"""How to differentiate through MJX's constraint solver: the options, measured (issue 10).

Recommendation: `implicit` by default. Measured (benchmarks/results/gradient_modes.json,
float64, 32 particles, 2 shared CPU cores, µs per particle-step as a ratio to scan-4 in
the same run): on the two frictional scenes it is as accurate as scan-4/scan-8 and at
the finite-difference floor (median relative error 4.6e-10 bank_table, 1.4e-9 box_wall;
one-iteration 0.11 and 0.19), its forward pass *is* MJX's converged solver (qpos
identical to the unpatched while_loop bit for bit; divergence from MuJoCo C 5e-13 and
2e-13 m, p95), and it costs 0.32 / 0.52 / 0.51 of scan-4 (bank_table / box_wall /
billiards), 0.8-1.5x one-iteration, with less memory than one-iteration (520 / 174 /
142 KB per particle against 717 / 248 / 170; scan-4 1994 / 699 / 349). 128 particles
give the same ratios. Why scan-k is dear: under vmap the `lax.cond` of
`_while_loop_scan` becomes a select, so every trip runs a full Newton iteration (line
search included) for every particle even after it converged, and reverse mode stores
every trip; MJX's while_loop stops when the slowest particle of the batch converges
(a few iterations), and the backward pass goes through one Newton step without a line
search. There is also no k to calibrate: the scene's own tolerance decides, per step.
`fwd-converged` is cheaper still (0.23-0.38 of scan-4) but pays one tangent per
coordinate of θ (2 here) and does not fit the library's reverse-mode `value_and_grad`;
scan-2 is not faithful (box_wall p90 error 0.36). Not measured here: float32,
elliptic cones, the CG solver (its Mgrad is M⁻¹∇f, not a Newton step: the
implicit step would need the Newton Hessian), batches far above 128.

Options, each a value-and-grad of f(θ) = Σᵢ c₁·qpos_T + c₂·mean_t qpos_t over N
particles whose θ is the initial planar velocity:

- `one-iteration`: reverse mode with `iterations=1` (the old model).
- `scan-k`: reverse mode through k solver iterations, MJX's own
  `_while_loop_scan` (what `gradsafe.patch_mjx` installs).
- `fwd-k`: forward mode (one JVP per coordinate of θ) through the same k
  iterations.
- `fwd-converged`: forward mode through MJX's *unpatched* `while_loop`, run to
  the scene's own tolerance (forward mode needs no fixed trip count).
- `implicit`: the solver runs to convergence in MJX's own `while_loop` on
  stop-gradient inputs (the forward values are that solver's, bit for bit), then
  one Newton step from the solution, q⁺ = q* − H⁻¹∇f(q*), is differentiated:
  since ∇f(q*) = 0 and H = ∂∇f/∂q, dq⁺/dp = −H⁻¹ ∂∇f/∂p, the implicit-function
  derivative of the converged solution. Prototyped here by swapping
  `mujoco.mjx._src.solver.solve` while the function is traced; not in the library.

Per (scene, option): median and p90 relative error of each particle's gradient
against central finite differences of the scene's *own* physics (MuJoCo C, float64,
the MJCF's solver settings), the physics divergence (largest body-position
difference over the horizon from that same C replay), µs per particle-step of
value-and-grad (steady state, medians of interleaved repeats), compile seconds
(trace + lower + compile, persistent cache off) and the executable's
`memory_analysis()` (temp + argument + output bytes) per particle; MuJoCo C
forward µs per particle-step for scale.

Scenes: the shipped billiards table (frictionless, soft: one iteration is exact)
and two written with MuJoCo's defaults: `bank_table` (two balls on slide joints,
box rails and a block, frictional condim-3 contacts, no floor, dt 0.005, 400 steps)
and `box_wall` (a 0.5 kg box on x, y, z slide joints sliding on a floor under
gravity into a wall, dt 0.01, 150 steps).

Usage: python benchmarks/perf/gradient_modes.py [--scenes billiards,bank_table,box_wall]
    [--options one-iteration,scan-4,...] [--particles 32] [--repeats 5] [--json] [--save]
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import RESULTS as RESULTS_DIR  # noqa: E402
from benchmarks.common import save_json  # noqa: E402

RESULTS = RESULTS_DIR / "gradient_modes.json"

BANK_TABLE = """
<mujoco model="bank_table">
  <option timestep="0.005"/>
  <default>
    <default class="ball">
      <geom type="sphere" size="0.03" mass="0.17"/>
      <joint type="slide" damping="0.02"/>
    </default>
    <default class="rail">
      <geom type="box" rgba="0.35 0.2 0.1 1"/>
    </default>
  </default>
  <worldbody>
    <geom name="rail_top" class="rail" pos="0 0.55 0" size="1.1 0.05 0.05"/>
    <geom name="rail_bottom" class="rail" pos="0 -0.55 0" size="1.1 0.05 0.05"/>
    <geom name="rail_left" class="rail" pos="-1.05 0 0" size="0.05 0.5 0.05"/>
    <geom name="rail_right" class="rail" pos="1.05 0 0" size="0.05 0.5 0.05"/>
    <geom name="block" class="rail" pos="-0.1 0.3 0" size="0.04 0.15 0.05"/>
    <body name="cue" pos="-0.6 -0.1 0">
      <joint name="cue_x" class="ball" axis="1 0 0"/>
      <joint name="cue_y" class="ball" axis="0 1 0"/>
      <geom name="cue" class="ball"/>
    </body>
    <body name="target" pos="0.6 0.2 0">
      <joint name="target_x" class="ball" axis="1 0 0"/>
      <joint name="target_y" class="ball" axis="0 1 0"/>
      <geom name="target" class="ball"/>
    </body>
  </worldbody>
</mujoco>
"""

BOX_WALL = """
<mujoco model="box_wall">
  <option timestep="0.01"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <geom name="wall" type="box" pos="0.35 0 0.1" size="0.05 1 0.1"/>
    <body name="box" pos="0 0 0.05">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <joint name="z" type="slide" axis="0 0 1"/>
      <geom name="box" type="box" size="0.05 0.05 0.05" mass="0.5"/>
    </body>
  </worldbody>
</mujoco>
"""


@dataclasses.dataclass(frozen=True)
class SceneCase:
    """A scene, its horizon and the box θ (the initial planar velocity) is drawn from."""

    name: str
    horizon: int
    joints: tuple[str, str]
    low: tuple[float, float]
    high: tuple[float, float]


CASES = {
    "billiards": SceneCase("billiards", 150, ("cue_x", "cue_y"), (-3.0, -3.0), (3.0, 3.0)),
    "bank_table": SceneCase("bank_table", 400, ("cue_x", "cue_y"), (-3.0, -3.0), (3.0, 3.0)),
    # vx > 2.2 m/s reaches the wall (friction 1 stops the box within v^2 / 2g).
    "box_wall": SceneCase("box_wall", 150, ("x", "y"), (0.5, -1.5), (4.0, 1.5)),
}

# (name, mode, iterations): mode is reverse | forward | implicit; iterations None
# means the scene's own `opt.iterations` in MJX's own while_loop.
OPTIONS = (
    ("one-iteration", "reverse", 1),
    ("scan-2", "reverse", 2),
    ("scan-4", "reverse", 4),
    ("scan-8", "reverse", 8),
    ("fwd-2", "forward", 2),
    ("fwd-4", "forward", 4),
    ("fwd-8", "forward", 8),
    ("fwd-converged", "forward-converged", None),
    ("implicit", "implicit", None),
)
# Line-search iterations of every gradient model. N.B. MJX's line search is a
# `_while_loop_scan`: under vmap each of its trips costs a full evaluation for every
# particle, so the converged models keep the gradient models' 4 instead of the
# scene's 50 (the Newton iteration converges to the same unique solution).
LS_ITERATIONS = 4


def _setup(cache: bool):
    import jax

    jax.config.update("jax_enable_x64", True)
    if not cache:
        # N.B. compile seconds are part of the measurement: a warm persistent cache
        # would report a cache read.
        jax.config.update("jax_enable_compilation_cache", False)
    return jax


def _scene(name: str):
    from mjstamp.scenes import Scene

    if name == "billiards":
        return Scene.shipped("billiards")
    return Scene({"bank_table": BANK_TABLE, "box_wall": BOX_WALL}[name], name=name)


# The prototypes: MJX's own solver loop, and the one-step implicit solver.


def _mjx_solve():
    """MJX's own `solver.solve` (its `lax.while_loop`), rebuilt from the installed source.

    `gradsafe.patch_mjx` replaces `solver.solve` by a fixed-trip scan; this compiles
    the original text in the solver module's globals, so it calls the same (patched,
    forward-identical) line search and constraint update.
    """
    from mujoco.mjx._src import solver

    source = Path(solver.__file__).read_text()
    (node,) = [n for n in ast.parse(source).body
               if isinstance(n, ast.FunctionDef) and n.name == "solve"]
    text = ast.get_source_segment(source, node)
    if "jax.lax.while_loop(cond, body, ctx)" not in text:
        raise RuntimeError("MJX's solve changed: re-audit this benchmark's prototype")
    scope: dict = {}
    exec(compile(text, "<gradient_modes:mjx_solve>", "exec"), solver.__dict__, scope)  # noqa: S102
    return scope["solve"]


def _implicit_solve(mjx_solve):
    """solve(m, d): forward = MJX's converged solver; derivative = one Newton step from it."""
    import jax
    from mujoco.mjx._src import solver

    sg = jax.lax.stop_gradient

    def solve(m, d):
        # Forward only: no tangent reaches the while_loop, so reverse mode never sees it.
        d_star = mjx_solve(m, jax.tree_util.tree_map(sg, d))
        q_star = d_star.qacc
        # One Newton step from the solution, differentiable in everything d holds
        # (M, J, aref, D, qfrc_smooth): Context.create evaluates the constraint state,
        # the gradient ∇f(q*) and Mgrad = H⁻¹∇f(q*) at q* (its Newton Hessian is
        # exactly ∂∇f/∂q on the active set, pyramidal or elliptic).
        ctx = solver.Context.create(m, d.replace(qacc=q_star))
        q_new = q_star - ctx.Mgrad
        new = solver.Context.create(m, d.replace(qacc=q_new), grad=False)

        def straight(value, differentiable):
            # Forward: the converged value exactly (x - x == 0); tangent: the step's.
            return value + (differentiable - sg(differentiable))

        return d.tree_replace({
            "qacc": straight(q_star, q_new),
            "qfrc_constraint": straight(d_star.qfrc_constraint, new.qfrc_constraint),
            "_impl.efc_force": straight(d_star._impl.efc_force, new.efc_force),
        })

    return solve


@contextlib.contextmanager
def _solver_as(fn):
    """Swaps MJX's `solver.solve` (looked up at trace time by `forward.forward`)."""
    from mujoco.mjx._src import solver

    saved = solver.solve
    if fn is not None:
        solver.solve = fn
    try:
        yield
    finally:
        solver.solve = saved


# Measurement.


def _inputs(scene, case: SceneCase, theta: np.ndarray, xp):
    """θ (n, 2) -> qpos0 (n, nq), qvel0 (n, nv)."""
    n = theta.shape[0]
    qpos0 = xp.broadcast_to(xp.asarray(scene.m.qpos0), (n, scene.m.nq))
    dofs = [scene.dof_adr(j) for j in case.joints]
    qvel0 = xp.zeros((n, scene.m.nv), theta.dtype)
    if xp is np:
        qvel0[:, dofs] = theta
    else:
        qvel0 = qvel0.at[:, dofs].set(theta)
    return qpos0, qvel0


def _objective(qpos, c1, c2):
    """(n,) per-particle f = c₁·qpos_T + c₂·mean_t qpos_t."""
    return qpos[:, -1] @ c1 + qpos.mean(axis=1) @ c2


def finite_differences(scene, case, theta, c1, c2, eps):
    """(n, 2) central differences of f in float64 MuJoCo C with the scene's own solver."""
    from mjstamp.scenes.rollout import replay

    n, dim = theta.shape
    step = eps * np.eye(dim)
    both = np.concatenate([(theta[:, None] + step).reshape(-1, dim),
                           (theta[:, None] - step).reshape(-1, dim)])
    qpos = replay(scene, *_inputs(scene, case, both, np), horizon=case.horizon,
                  fields=("qpos",), solver="scene")["qpos"]
    f = _objective(qpos, c1, c2).reshape(2, n, dim)
    return (f[0] - f[1]) / (2 * eps)


def relative_errors(grad, fd):
    """(n,) ‖g − fd‖ / max(‖g‖, ‖fd‖), as `mjstamp check` measures it."""
    err = np.linalg.norm(grad - fd, axis=1)
    scale = np.maximum(np.linalg.norm(fd, axis=1), np.linalg.norm(grad, axis=1))
    return err / np.maximum(scale, 1e-9)


def _build(scene, case, option, c1, c2, theta, mjx_solve):
    """Compiles one option's value-and-grad: θ (n, 2) -> (f sum, grad (n, 2), qpos)."""
    import jax
    import jax.numpy as jnp

    from mjstamp.scenes.rollout import build_rollout

    name, mode, k = option
    iterations = int(scene.m.opt.iterations) if k is None else k
    gscene = scene.with_grad_options(iterations=iterations, ls_iterations=LS_ITERATIONS)
    rollout = build_rollout(gscene, case.horizon, fields=("qpos",))
    c1j, c2j = jnp.asarray(c1), jnp.asarray(c2)

    def per_particle(th):
        qpos = rollout(*_inputs(scene, case, th, jnp))["qpos"]
        return _objective(qpos, c1j, c2j), qpos

    if mode in ("reverse", "implicit"):
        def value_and_grad(th):
            def total(th):
                f, qpos = per_particle(th)
                return f.sum(), qpos
            (f, qpos), g = jax.value_and_grad(total, has_aux=True)(th)
            return f, g, qpos
    else:
        def value_and_grad(th):
            # One JVP per coordinate of θ, all particles at once: particle i's f
            # depends on θᵢ only, so tangent e_j gives every ∂fᵢ/∂θᵢⱼ.
            dim = th.shape[1]
            tangents = jnp.broadcast_to(jnp.eye(dim)[:, None, :], (dim, *th.shape))

            def jvp(t):
                (f, qpos), (df, _) = jax.jvp(per_particle, (th,), (t,))
                return f, df, qpos

            f, df, qpos = jax.vmap(jvp, out_axes=(None, 0, None))(tangents)
            return f.sum(), df.T, qpos

    override = {"implicit": _implicit_solve(mjx_solve),
                "forward-converged": mjx_solve}.get(mode)
    arg = jnp.asarray(theta)
    t0 = time.perf_counter()
    # N.B. the swap must cover tracing: MJX looks `solver.solve` up when traced.
    with _solver_as(override):
        compiled = jax.jit(value_and_grad).lower(arg).compile()
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    n = theta.shape[0]
    # The qpos trajectory is returned only to measure divergence: not counted.
    traj = n * case.horizon * scene.m.nq * 8
    memory = mem.temp_size_in_bytes + mem.argument_size_in_bytes + (
        mem.output_size_in_bytes - traj)
    return compiled, arg, {"compile_s": compile_s, "iterations": iterations,
                           "memory_bytes_per_particle": memory / n,
                           "temp_bytes_per_particle": mem.temp_size_in_bytes / n}


def _c_forward(scene, case, theta):
    """A callable stepping the scene's own model in MuJoCo C (all cores)."""
    import mujoco
    import mujoco.rollout

    m = scene.m
    qpos0, qvel0 = _inputs(scene, case, theta, np)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    d = mujoco.MjData(m)
    state0 = np.empty((len(theta), mujoco.mj_stateSize(m, spec)))
    for i in range(len(theta)):
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = qpos0[i], qvel0[i]
        mujoco.mj_getState(m, d, state0[i], spec)
    datas = [mujoco.MjData(m) for _ in range(len(os.sched_getaffinity(0)))]
    ctrl = np.zeros((len(theta), case.horizon, m.nu))
    return lambda: mujoco.rollout.rollout(m, datas, state0, ctrl, nstep=case.horizon)


def run_scene(name, *, options, particles, repeats, seed, fd_eps, say):
    """Measures every option on one scene; returns its JSON object."""
    import jax

    from mjstamp.scenes import fidelity
    from mjstamp.scenes.rollout import replay

    case = CASES[name]
    scene = _scene(name)
    rng = np.random.default_rng(seed)
    c1, c2 = rng.normal(size=(2, scene.m.nq))
    c1, c2 = c1 / np.linalg.norm(c1), c2 / np.linalg.norm(c2)
    theta = rng.uniform(case.low, case.high, (particles, 2))

    say(f"{name}: C replay and central differences (eps {fd_eps:g}, {fd_eps * 10:g})")
    ref = replay(scene, *_inputs(scene, case, theta, np), horizon=case.horizon,
                 fields=("qpos",), solver="scene")["qpos"]
    x_ref = fidelity.tracked_points(scene.m, ref)
    fd = finite_differences(scene, case, theta, c1, c2, fd_eps)
    # How far apart two step sizes put the FD itself: the floor of any comparison.
    fd_floor = relative_errors(finite_differences(scene, case, theta, c1, c2, 10 * fd_eps), fd)

    mjx_solve = _mjx_solve()
    rows, fns, qpos_of = {}, {}, {}
    for option in options:
        say(f"{name}: compiling {option[0]}")
        fn, arg, row = _build(scene, case, option, c1, c2, theta, mjx_solve)
        _, grad, qpos = jax.block_until_ready(fn(arg))
        grad, qpos = np.asarray(grad), np.asarray(qpos)
        qpos_of[option[0]] = qpos
        finite = np.isfinite(grad).all(axis=1)
        rel = relative_errors(grad, fd)
        div = fidelity.divergence(fidelity.tracked_points(scene.m, qpos), x_ref)
        row.update({
            "nonfinite": int((~finite).sum()),
            "rel_err_median": float(np.median(rel)),
            "rel_err_p90": float(np.percentile(rel, 90)),
            "divergence_p95_m": float(np.percentile(div, 95)),
            "divergence_max_m": float(div.max()),
        })
        rows[option[0]] = row
        fns[option[0]] = (fn, arg)

    say(f"{name}: timing, {repeats} interleaved rounds")
    c_run = _c_forward(scene, case, theta)
    c_run()
    samples = {k: [] for k in [*fns, "mujoco-c"]}
    for _ in range(repeats):
        for key, (fn, arg) in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(arg))
            samples[key].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        c_run()
        samples["mujoco-c"].append(time.perf_counter() - t0)
    per = particles * case.horizon
    for key in fns:
        rows[key]["us_per_particle_step"] = float(np.median(samples[key])) / per * 1e6
    c_us = float(np.median(samples["mujoco-c"])) / per * 1e6
    base = rows.get("one-iteration", {}).get("us_per_particle_step")
    for row in rows.values():
        row["cost_over_one_iteration"] = row["us_per_particle_step"] / base if base else None
        row["cost_over_mujoco_c"] = row["us_per_particle_step"] / c_us

    out = {
        "scene": name,
        "particles": particles,
        "horizon": case.horizon,
        "timestep": float(scene.m.opt.timestep),
        "scene_solver": {"iterations": int(scene.m.opt.iterations),
                         "ls_iterations": int(scene.m.opt.ls_iterations),
                         "tolerance": float(scene.m.opt.tolerance)},
        "theta_box": [list(case.low), list(case.high)],
        "fd_eps": fd_eps,
        "fd_floor_median": float(np.median(fd_floor)),
        "fd_floor_p90": float(np.percentile(fd_floor, 90)),
        "mujoco_c_us_per_particle_step": c_us,
        "options": rows,
    }
    if "implicit" in qpos_of and "fwd-converged" in qpos_of:
        # Both run MJX's own converged solver forward: they must agree bit for bit.
        out["implicit_vs_converged_max_qpos_diff"] = float(
            np.abs(qpos_of["implicit"] - qpos_of["fwd-converged"]).max())
    return out


def _table(result: dict) -> str:
    head = (f"{'scene':<11} {'option':<14} {'err med':>8} {'err p90':>8} {'div p95 m':>9} "
            f"{'div max m':>9} {'us/p-step':>9} {'x 1-it':>6} {'compile s':>9} "
            f"{'KB/part':>8} {'nonfin':>6}")
    lines = [head, "-" * len(head)]
    for s in result["scenes"]:
        for name, r in s["options"].items():
            ratio = r["cost_over_one_iteration"]
            lines.append(
                f"{s['scene']:<11} {name:<14} {r['rel_err_median']:8.1e} "
                f"{r['rel_err_p90']:8.1e} {r['divergence_p95_m']:9.1e} "
                f"{r['divergence_max_m']:9.1e} {r['us_per_particle_step']:9.1f} "
                f"{ratio if ratio is not None else float('nan'):6.2f} {r['compile_s']:9.1f} "
                f"{r['memory_bytes_per_particle'] / 1024:8.0f} {r['nonfinite']:6d}")
        extra = ""
        if "implicit_vs_converged_max_qpos_diff" in s:
            extra = (f"; implicit vs MJX converged forward: max |dqpos| "
                     f"{s['implicit_vs_converged_max_qpos_diff']:.1e}")
        lines.append(
            f"{s['scene']:<11} {'MuJoCo C':<14} fwd {s['mujoco_c_us_per_particle_step']:.2f} "
            f"us/particle-step; FD floor (eps vs 10 eps) median {s['fd_floor_median']:.1e}, "
            f"p90 {s['fd_floor_p90']:.1e}{extra}")
        lines.append("")
    return "\n".join(lines)


def _args_key(args) -> dict:
    """The arguments that decide what a run measured (its key in RESULTS)."""
    return {"scenes": args.scenes.split(","), "options": args.options.split(","),
            "particles": args.particles, "repeats": args.repeats, "seed": args.seed,
            "fd_eps": args.fd_eps, "horizon": args.horizon}


def main(argv=None) -> int:
    """Runs the benchmark; prints a table (or JSON) and optionally saves it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(CASES))
    parser.add_argument("--options", default=",".join(o[0] for o in OPTIONS))
    parser.add_argument("--particles", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fd-eps", type=float, default=1e-6)
    parser.add_argument("--horizon", type=int, help="override every scene's horizon (smoke)")
    parser.add_argument("--cache", action="store_true",
                        help="allow JAX's persistent compilation cache (compile_s then lies)")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--save", action="store_true",
                        help=f"add this run to {RESULTS} (replacing one with the same arguments)")
    args = parser.parse_args(argv)
    scenes = args.scenes.split(",")
    known = {o[0]: o for o in OPTIONS}
    bad = [s for s in scenes if s not in CASES] + [
        o for o in args.options.split(",") if o not in known]
    if bad:
        parser.error(f"unknown scene or option {bad[0]!r}; valid: "
                     f"{', '.join(CASES)} / {', '.join(known)}")
    options = [known[o] for o in args.options.split(",")]
    if args.horizon:
        for s in scenes:
            CASES[s] = dataclasses.replace(CASES[s], horizon=args.horizon)
    jax = _setup(args.cache)

    def say(text):
        print(text, file=sys.stderr, flush=True)

    started = time.perf_counter()
    result = {
        "benchmark": "gradient_modes",
        "precision": "float64",
        "device": str(jax.devices()[0]),
        "machine": f"{platform.machine()} {len(os.sched_getaffinity(0))} cpus (shared)",
        "ls_iterations": LS_ITERATIONS,
        "args": _args_key(args),
        "scenes": [run_scene(s, options=options, particles=args.particles,
                             repeats=args.repeats, seed=args.seed, fd_eps=args.fd_eps,
                             say=say) for s in scenes],
    }
    result["wall_s"] = time.perf_counter() - started
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print(_table(result))
    if args.save:
        save(result)
    return 0


def save(result: dict) -> None:
    """Adds `result` to RESULTS, replacing the run with the same arguments."""
    runs = []
    if RESULTS.is_file():
        try:
            runs = json.loads(RESULTS.read_text()).get("runs", [])
        except (ValueError, AttributeError):
            runs = []  # an unreadable file is rewritten
    runs = [r for r in runs if r.get("args") != result["args"]] + [result]
    save_json(RESULTS, {"benchmark": "gradient_modes", "runs": runs}, indent=1, newline=True)


if __name__ == "__main__":
    sys.exit(main())
