"""Fidelity of the gradient model: how far it drifts from the scene's own physics.

Plans are found on the gradient model (MJX with `GradOptions`: a fixed number
of solver iterations, no warm start) and verified in MuJoCo C with the scene's
own solver settings. The two agree only if the gradient model's solver
converges: one Newton iteration is exact for soft frictionless contacts (the
shipped billiards table) but drifts on a frictional scene with MuJoCo's
default contacts.

Divergence of one particle = the largest difference of any body's centre of
mass or geom's centre (`tracked_points`, metres) over the horizon between the
two models, started from the same
state with the same controls. A model is *faithful* when that divergence is
under the tolerance for `share` (95%) of the particles. The default tolerance
is 1e-3 of the scene's size (`Scene.length_scale`: 2.5 mm on a 2.2 m table):
plans are judged by where bodies end up, and that is far below the size of a
pocket or goal region.

`calibrate` picks the cheapest faithful setting among, by default, one
unrolled Newton iteration (exact on soft frictionless contacts, the cheapest)
and the implicit gradient (MJX's own solver run to the MJCF's tolerance, one
differentiated Newton step: exact wherever the solver converges; see
`gradsafe.gradient_mode`). Unrolled settings with more iterations can be
passed as candidates (benchmarks do). N.B. it steps the gradient model's
MuJoCo C twin (`m` with the candidate options), not MJX itself: C is faster
and compiles nothing, and MJX agrees with its C twin where both collide the
same shapes and converge (tests/test_rollout.py); `solve` then measures MJX
itself on the same particles before STAMP starts, and at the final particles.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Sequence
from pathlib import Path

import mujoco
import numpy as np

from mjstamp._mjx import model_bytes
from mjstamp.errors import MjstampError
from mjstamp.fileio import write_atomic
from mjstamp.kinematics import poses
from mjstamp.progress import Progress, ProgressLike
from mjstamp.scenes.rollout import controls, replay

CACHE = Path.home() / ".cache" / "mjstamp" / "fidelity"
SHARE = 0.95
RELATIVE_TOLERANCE = 1e-3

# (gradient, iterations, ls_iterations) in order of cost; None: the MJCF's own
# (iterations: a cap, the implicit loop stops at the MJCF's tolerance; line
# search None: the MJCF's line-search iterations *and* its warm start, which
# makes the implicit model the scene's own solver). Unrolled cost grows about
# linearly in iterations: every particle runs all of them under vmap, and
# reverse mode stores each; the implicit loop and the line search stop at
# their tolerances, so larger caps cost only where they are needed, and the
# warm start gets no gradient (the implicit forward loop is stop-gradient).
# N.B. the last candidate is for frictional pushes: the Jaco pushing a brick
# (16 screened particles, 240 steps of 5 ms) parted from its own physics by
# 6 cm p95 with 4 line-search steps, by 3.3-4.2 mm with 50 or 100 and no warm
# start (the brick sticks or slips on the start the solver is given), by 0
# with the MJCF's own settings.
CANDIDATES: tuple[tuple[str, int | None, int | None], ...] = (
    ("unrolled", 1, 4), ("implicit", None, 4), ("implicit", None, None))
UNROLLED: tuple[tuple[str, int | None, int], ...] = tuple(
    ("unrolled", k, ls) for k, ls in ((1, 4), (2, 4), (3, 4), (4, 4), (6, 6), (8, 8), (16, 10))
)


def default_tolerance(scene) -> float:
    """1e-3 of the scene's size (`Scene.length_scale`), in metres."""
    return RELATIVE_TOLERANCE * scene.length_scale


def tracked_points(m: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """(n, T, nbody + ngeom, 3) points of states (n, T, nq): body COMs and geom centres.

    By MuJoCo C kinematics. N.B. not body frame origins (`xpos`): a body hinged
    at its own origin (a pendulum, a link of an arm) keeps its origin still
    however it swings, and a divergence read from origins alone is 0 there.
    """
    k = poses(m, qpos, ("xipos", "geom_xpos"))
    return np.concatenate([k["xipos"], k["geom_xpos"]], axis=-2)


def divergence(x_a: np.ndarray, x_b: np.ndarray) -> np.ndarray:
    """(n,) largest difference of tracked points over steps and points, in metres.

    Args:
      x_a: (n, T, p, 3) points of one rollout (`tracked_points`).
      x_b: (n, T, p, 3) those of another rollout of the same inputs.
    """
    diff = np.abs(np.asarray(x_a) - np.asarray(x_b)).max(axis=(1, 2, 3))
    # N.B. a non-finite state is infinitely far from any finite one.
    return np.where(np.isfinite(diff), diff, np.inf)


@dataclasses.dataclass(frozen=True)
class Measurement:
    """Divergence of one gradient-model setting from the scene's own physics.

    Attributes:
      gradient: "unrolled" or "implicit" (`GradOptions.gradient`).
      iterations, ls_iterations: the gradient model's solver settings.
      warmstart: whether its solver starts from the last step's accelerations.
      median_m, p95_m, max_m: statistics of the per-particle divergence.
      seconds: wall time of the gradient model's C rollouts.
    """

    gradient: str
    iterations: int
    ls_iterations: int
    median_m: float
    p95_m: float
    max_m: float
    seconds: float
    warmstart: bool = False

    def options(self) -> dict:
        """`Scene.with_grad_options` keywords of this setting."""
        return {"gradient": self.gradient, "iterations": self.iterations,
                "ls_iterations": self.ls_iterations, "warmstart": self.warmstart}

    def faithful(self, tolerance: float) -> bool:
        """Whether 95% of the particles (`SHARE`) stay within `tolerance`."""
        return self.p95_m <= tolerance


def _stats(div: np.ndarray) -> tuple[float, float, float]:
    return float(np.median(div)), float(np.percentile(div, 95)), float(np.max(div))


@dataclasses.dataclass(frozen=True)
class Calibration:
    """What `calibrate` found (JSON view: `as_dict`).

    Attributes:
      scene: the scene's name.
      tolerance_m: the divergence allowed to 95% of the particles.
      particles, horizon: the measurement's size.
      before: the scene's configured gradient model (`scene.grad_options`).
      after: the chosen setting (the cheapest faithful one, else the least
        divergent one tried).
      faithful: whether `after` is within tolerance.
      tried: every setting measured, in order.
      seconds: wall time of the calibration (0 when read from the cache).
      cached: read from the on-disk cache.
    """

    scene: str
    tolerance_m: float
    particles: int
    horizon: int
    before: Measurement
    after: Measurement
    faithful: bool
    tried: tuple[Measurement, ...]
    seconds: float = 0.0
    cached: bool = False

    def as_dict(self) -> dict:
        """JSON-ready view."""
        return {
            "scene": self.scene,
            "tolerance_m": self.tolerance_m,
            "particles": self.particles,
            "horizon": self.horizon,
            "faithful": self.faithful,
            "gradient": self.after.gradient,
            "iterations": self.after.iterations,
            "ls_iterations": self.after.ls_iterations,
            "warmstart": self.after.warmstart,
            "divergence_before_median_m": self.before.median_m,
            "divergence_before_p95_m": self.before.p95_m,
            "divergence_after_median_m": self.after.median_m,
            "divergence_after_p95_m": self.after.p95_m,
            "before": dataclasses.asdict(self.before),
            "after": dataclasses.asdict(self.after),
            "tried": [dataclasses.asdict(t) for t in self.tried],
            "seconds": self.seconds,
            "cached": self.cached,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Calibration:
        """Inverse of `as_dict`."""
        return cls(
            scene=d["scene"], tolerance_m=d["tolerance_m"], particles=d["particles"],
            horizon=d["horizon"], before=Measurement(**d["before"]),
            after=Measurement(**d["after"]), faithful=d["faithful"],
            tried=tuple(Measurement(**t) for t in d["tried"]), seconds=0.0, cached=True,
        )

    def message(self) -> str:
        """One line: what was chosen, or why no setting is faithful."""
        a, b = self.after, self.before
        if self.faithful:
            return (
                f"scene {self.scene!r}: {describe(a.gradient, a.iterations)} gradient model; "
                f"divergence from the scene's own physics p95 {a.p95_m:.2g} m <= tolerance "
                f"{self.tolerance_m:.2g} m (was {b.p95_m:.2g} m "
                f"{describe(b.gradient, b.iterations)})"
            )
        return (
            f"scene {self.scene!r} cannot be made faithful within {a.iterations} solver "
            f"iterations ({a.gradient}): divergence from the scene's own physics p95 "
            f"{a.p95_m:.2g} m "
            f"> tolerance {self.tolerance_m:.2g} m over {self.horizon} steps "
            f"({self.particles} particles)"
        )


def describe(gradient: str, iterations: int) -> str:
    """'implicit (up to 100 iterations)' or 'unrolled (2 iterations)'."""
    if gradient == "implicit":
        return f"implicit (up to {iterations} solver iterations)"
    return f"unrolled ({iterations} solver iteration{'s' if iterations != 1 else ''})"


def _key(scene, inputs, tolerance, candidates) -> str:
    # N.B. "v" counts changes to what a calibration measures; 4: the C twin drops
    # noslip and sleeping (GradOptions.apply), which MJX ignores.
    h = hashlib.sha256(model_bytes(scene.m))
    h.update(json.dumps(
        {"grad": dataclasses.asdict(scene.grad_options), "tol": tolerance,
         "candidates": list(candidates), "share": SHARE, "v": 4}, sort_keys=True,
    ).encode())
    for a in inputs:
        h.update(np.ascontiguousarray(np.asarray(a, np.float64)).tobytes())
    return h.hexdigest()[:24]


def calibrate(
    scene,
    qpos0: np.ndarray,
    qvel0: np.ndarray,
    ctrl: np.ndarray | None = None,
    *,
    horizon: int | None = None,
    tolerance: float | None = None,
    max_iterations: int | None = None,
    candidates: Sequence[tuple[str, int | None, int]] = CANDIDATES,
    cache: bool = True,
    progress: ProgressLike = False,
    reference: np.ndarray | None = None,
) -> Calibration:
    """The cheapest gradient-solver setting that follows the scene's own physics.

    Replays the particles' inputs in MuJoCo C with the scene's own options (the
    reference, what plans are verified with) and with each candidate gradient
    model in order of cost, stopping at the first whose divergence is within
    `tolerance` for 95% of the particles.

    Args:
      scene: a `Scene`; `scene.grad_options` is the "before" model and supplies
        every option a candidate does not set (solver, timestep, warm start).
      qpos0: (n, nq) initial positions.
      qvel0: (n, nv) initial velocities.
      ctrl: (n, T, nu) controls, or None with `horizon`.
      horizon: T, when `ctrl` is None.
      tolerance: metres; default `default_tolerance(scene)`.
      max_iterations: the budget of solver iterations: unrolled candidates with
        more are not tried and the implicit loop stops there; None: the MJCF's
        own `opt.iterations`.
      candidates: (gradient, iterations or None, ls_iterations or None) in order of
        cost; None: the MJCF's own (line search None: its warm start too).
      cache: read and write the result on disk (~/.cache/mjstamp/fidelity),
        keyed by the compiled model, the options, the inputs and the tolerance.
      progress: status lines (`mjstamp.progress`: a callable, a `Progress`, True;
        False: none).
      reference: (n, T, nq) positions of these inputs replayed in MuJoCo C with
        the scene's own solver (`replay(..., solver="scene")`), where the caller
        has them (a solve's seeding screen); None replays them here.

    Returns:
      A `Calibration`.
    """
    say = Progress.of(progress or False, "fidelity")  # N.B. None: silent, as before
    tolerance, own, budget = _limits(scene, tolerance, max_iterations)
    qpos0 = np.asarray(qpos0, np.float64)
    qvel0 = np.asarray(qvel0, np.float64)
    ctrl = controls(ctrl, horizon, len(qpos0), scene.m.nu, who="calibrate")
    todo = _settings(scene, candidates, own, budget)
    path = CACHE / f"{scene.name}-{_key(scene, (qpos0, qvel0, ctrl), tolerance, todo)}.json"
    if cache and (hit := _cached(path)) is not None:
        return hit
    started = time.perf_counter()
    if reference is None:
        reference = replay(scene, qpos0, qvel0, ctrl, fields=("qpos",), solver="scene")["qpos"]
    tried = _measure(scene, todo, (qpos0, qvel0, ctrl), tracked_points(scene.m, reference),
                     tolerance, say)
    result = _verdict(scene, tried, tolerance, (len(qpos0), int(ctrl.shape[1])),
                      time.perf_counter() - started)
    if cache:
        _write(path, result)
    return result


def _limits(scene, tolerance: float | None, max_iterations: int | None) -> tuple[float, int, int]:
    """(tolerance in metres, the MJCF's solver iterations, the budget of iterations), checked.

    Raises:
      MjstampError: the tolerance is not > 0 or the budget is under 1.
    """
    tolerance = default_tolerance(scene) if tolerance is None else float(tolerance)
    if not tolerance > 0:
        raise MjstampError(f"fidelity tolerance={tolerance} must be > 0 (metres)")
    own = int(scene.m.opt.iterations)
    budget = own if max_iterations is None else int(max_iterations)
    if budget < 1:
        raise MjstampError(f"max_solver_iterations={max_iterations} must be >= 1")
    return tolerance, own, budget


def _cached(path: Path) -> Calibration | None:
    """The calibration stored at `path`, or None where there is none or it is corrupt."""
    if not path.is_file():
        return None
    try:
        return Calibration.from_dict(json.loads(path.read_text()))
    except (ValueError, KeyError, TypeError):
        return None  # a corrupt entry is measured again and rewritten


def _measure(scene, todo, inputs, x_ref: np.ndarray, tolerance: float, say) -> list[Measurement]:
    """One `Measurement` per setting of `todo`, in order, up to the first faithful one.

    Args:
      scene: the `Scene`.
      todo: (gradient, iterations, ls_iterations, warm start) settings, `_settings`.
      inputs: (qpos0 (n, nq), qvel0 (n, nv), ctrl (n, T, nu)).
      x_ref: (n, T, p, 3) tracked points of the reference replay (`tracked_points`).
      tolerance: metres.
      say: where status lines go.
    """
    qpos0, qvel0, ctrl = inputs
    tried: list[Measurement] = []
    for gradient, iterations, ls, warm in todo:
        candidate = scene.with_grad_options(
            gradient=gradient, iterations=iterations, ls_iterations=ls, warmstart=warm
        )
        t0 = time.perf_counter()
        qpos = replay(candidate, qpos0, qvel0, ctrl, fields=("qpos",), solver="grad")["qpos"]
        seconds = time.perf_counter() - t0
        diff = divergence(tracked_points(scene.m, qpos), x_ref)
        tried.append(Measurement(gradient, iterations, ls, *_stats(diff), seconds, warm))
        say(f"{describe(gradient, iterations)}, line search {ls}{', warm start' if warm else ''}: "
            f"divergence p95 "
            f"{tried[-1].p95_m:.2g} m (tolerance {tolerance:.2g} m)")
        if tried[-1].faithful(tolerance):
            break
    return tried


def _verdict(scene, tried: list[Measurement], tolerance: float, size: tuple[int, int],
             seconds: float) -> Calibration:
    """The `Calibration` of the settings tried: the first faithful one, else the closest.

    size: (particles n, horizon T) replayed; seconds: the calibration's wall time.
    """
    faithful = [t for t in tried if t.faithful(tolerance)]
    after = faithful[0] if faithful else min(tried, key=lambda t: t.p95_m)
    return Calibration(
        scene=scene.name, tolerance_m=tolerance, particles=size[0],
        horizon=size[1], before=tried[0], after=after,
        faithful=bool(faithful), tried=tuple(tried),
        seconds=seconds,
    )


def _settings(scene, candidates, own: int, budget: int) -> list[tuple[str, int, int, bool]]:
    """The scene's configured model, then the candidates within budget, in order."""
    g = scene.grad_options
    todo = [(g.gradient, g.iterations, g.ls_iterations, g.warmstart)]
    warm = not scene.m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)
    for gradient, iterations, ls in candidates:
        wanted = own if iterations is None else iterations
        if gradient == "unrolled" and wanted > budget:
            continue  # over budget; the implicit loop is capped at the budget instead
        setting = (gradient, min(wanted, budget), ls, g.warmstart) if ls is not None else (
            gradient, min(wanted, budget), max(1, int(scene.m.opt.ls_iterations)), warm)
        if setting not in todo:
            todo.append(setting)
    return todo


def _write(path: Path, result: Calibration) -> None:
    try:
        CACHE.mkdir(parents=True, exist_ok=True)
        payload = json.dumps(result.as_dict()).encode()
        write_atomic(path, lambda f: f.write(payload))
    except OSError:
        pass  # a read-only cache only costs time


# What C does to itself: the spread a chaotic scene shows when its initial
# positions move by a nanometre, against which a gradient model's rounding-level
# differences are judged where they outgrow the tolerance (pachinko's pegs).
NUDGE_M = 1e-9


def chaos_spread(scene, qpos0: np.ndarray, qvel0: np.ndarray, ctrl: np.ndarray | None = None,
                 *, horizon: int | None = None, nudge: float = NUDGE_M,
                 seed: int = 0) -> np.ndarray:
    """(n,) divergence of MuJoCo C from itself with the initial positions moved by `nudge`.

    Every coordinate of qpos0 moves by ±`nudge` (a random sign each): metres for
    translations, radians for angles, which MuJoCo renormalises where it is a
    quaternion's. Both runs use the scene's own solver, as plans are verified.

    Args:
      scene: a `Scene`.
      qpos0: (n, nq) initial positions.
      qvel0: (n, nv) initial velocities.
      ctrl: (n, T, nu) controls, or None with `horizon`.
      horizon: T, when `ctrl` is None.
      nudge: the move, metres (radians).
      seed: the signs.
    """
    qpos0 = np.asarray(qpos0, np.float64)
    signs = np.random.default_rng(seed).choice([-1.0, 1.0], size=qpos0.shape)
    a = replay(scene, qpos0, qvel0, ctrl, horizon=horizon, fields=("qpos",))["qpos"]
    b = replay(scene, qpos0 + nudge * signs, qvel0, ctrl, horizon=horizon,
               fields=("qpos",))["qpos"]
    return divergence(tracked_points(scene.m, a), tracked_points(scene.m, b))


@dataclasses.dataclass(frozen=True)
class Parting:
    """Where MJX rollouts first part from MuJoCo C, and what was in contact there.

    Attributes:
      particles: particles that parted (divergence above the threshold).
      steps: (particles,) first step (1-based) at which each parted.
      pairs: {(geom1, geom2) ids in the model's order: particles whose first
        parting step had the pair in contact in C}, most frequent first.
      threshold_m: the difference that counts as parting.
    """

    particles: int
    steps: tuple[int, ...]
    pairs: dict[tuple[int, int], int]
    threshold_m: float

    def describe(self, m: mujoco.MjModel, *, limit: int = 4) -> str:
        """"box-box 'paddle'/'bumper' (12 of 16)", the commonest first; '' when none."""
        from mjstamp import colliders  # pylint: disable=g-import-not-at-top

        parts = [f"{colliders.describe_pair(m, g1, g2)} ({k} of {self.particles})"
                 for (g1, g2), k in list(self.pairs.items())[:limit]]
        more = len(self.pairs) - limit
        return ", ".join(parts) + (f" and {more} more" if more > 0 else "")

    def as_dict(self, m: mujoco.MjModel) -> dict:
        """JSON view: pairs by name and type."""
        from mjstamp import colliders  # pylint: disable=g-import-not-at-top

        return {
            "particles": self.particles,
            "first_step_median": float(np.median(self.steps)) if self.steps else None,
            "threshold_m": self.threshold_m,
            "pairs": [{**colliders.pair_info(m, g1, g2), "particles": k}
                      for (g1, g2), k in self.pairs.items()],
        }


def parting(m: mujoco.MjModel, qpos0: np.ndarray, qpos_a: np.ndarray, qpos_c: np.ndarray, *,
            threshold: float) -> Parting:
    """The first step at which two rollouts of the same inputs part, and C's contacts there.

    A particle parts at the first step where a tracked point (`tracked_points`)
    differs by more than `threshold`; the geom pairs in contact in the C
    rollout at the state before that step and after it are what the step
    collided (a step's contacts come from the state it starts from).

    Args:
      m: the scene's model.
      qpos0: (n, nq) initial positions.
      qpos_a: (n, T, nq) the gradient model's states after steps 1..T.
      qpos_c: (n, T, nq) MuJoCo C's.
      threshold: metres.
    """
    x_a = tracked_points(m, np.asarray(qpos_a, np.float64))
    x_c = tracked_points(m, np.asarray(qpos_c, np.float64))
    diff = np.abs(x_a - x_c).max(axis=(2, 3))  # (n, T)
    diff = np.where(np.isfinite(diff), diff, np.inf)
    parted = np.flatnonzero((diff > threshold).any(axis=1))
    d = mujoco.MjData(m)
    counts: dict[tuple[int, int], int] = {}
    steps = []
    for i in parted:
        t = int(np.argmax(diff[i] > threshold))
        steps.append(t + 1)
        seen = set()
        for q in (qpos0[i] if t == 0 else qpos_c[i, t - 1], qpos_c[i, t]):
            d.qpos[:] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
            seen |= {(int(c.geom1), int(c.geom2)) for c in d.contact[: d.ncon] if not c.exclude}
        for pair in seen:
            counts[pair] = counts.get(pair, 0) + 1
    ranked = dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))
    return Parting(len(parted), tuple(steps), ranked, float(threshold))


@dataclasses.dataclass(frozen=True)
class Verdict:
    """MJX itself against MuJoCo C, judged by the tolerance or by C's own chaos.

    Attributes:
      median_m, p95_m: MJX's divergence from C.
      tolerance_m: the fidelity tolerance.
      chaos_p95_m: C against itself nudged by `NUDGE_M` (None when not needed:
        MJX was within the tolerance).
      judged_by: "tolerance" (p95 within it), "chaos" (beyond it, but within
        C's own spread: the scene amplifies any difference, rounding included)
        or "none" (beyond both).
      parting: where the rollouts part and which geom pairs were in contact
        (None when faithful by either measure).
      approximate: geom pairs of the model that MJX collides differently from C.
    """

    median_m: float
    p95_m: float
    tolerance_m: float
    chaos_p95_m: float | None
    judged_by: str
    parting: Parting | None
    approximate: tuple[tuple[int, int], ...]

    @property
    def faithful(self) -> bool:
        """Within the tolerance or the chaos spread."""
        return self.judged_by != "none"

    def message(self, scene_name: str, m: mujoco.MjModel, horizon: int) -> str:
        """One line: how MJX compares with C and, where it parts, the pairs responsible."""
        from mjstamp import colliders  # pylint: disable=g-import-not-at-top

        head = (f"scene {scene_name!r}: MJX rollouts vs MuJoCo C (scene's own solver) p95 "
                f"{self.p95_m:.2g} m")
        if self.judged_by == "tolerance":
            return f"{head} <= tolerance {self.tolerance_m:.2g} m"
        chaos = f"C against itself nudged by {NUDGE_M:g} m: p95 {self.chaos_p95_m:.2g} m"
        if self.judged_by == "chaos":
            return (f"{head} > tolerance {self.tolerance_m:.2g} m but within the scene's own "
                    f"chaos ({chaos}): faithful as C is to itself")
        where = self.parting.describe(m) if self.parting is not None else ""
        approx = [p for p in self.approximate
                  if self.parting is not None and p in self.parting.pairs]
        cause = (f"where MJX collides these pairs differently from C: "
                 f"{', '.join(colliders.describe_pair(m, *p) for p in approx)}"
                 if approx else "MJX collides or integrates something differently")
        return (f"{head} > tolerance {self.tolerance_m:.2g} m and > {chaos}, over {horizon} "
                f"steps; they part at contacts of {where or 'no geom pair'}; {cause}")

    def as_dict(self, m: mujoco.MjModel) -> dict:
        """JSON view."""
        from mjstamp import colliders  # pylint: disable=g-import-not-at-top

        return {
            "median_m": self.median_m, "p95_m": self.p95_m, "tolerance_m": self.tolerance_m,
            "chaos_p95_m": self.chaos_p95_m, "judged_by": self.judged_by,
            "faithful": self.faithful,
            "parting": None if self.parting is None else self.parting.as_dict(m),
            "approximate_pairs": [colliders.pair_info(m, *p) for p in self.approximate],
        }


def judge(scene, qpos0: np.ndarray, qvel0: np.ndarray, ctrl: np.ndarray | None,
          qpos_mjx: np.ndarray, qpos_c: np.ndarray, *, tolerance: float,
          horizon: int | None = None) -> Verdict:
    """Judges MJX rollouts against C replays of the same inputs (`Verdict`).

    Within the tolerance, nothing more is measured. Beyond it, C is replayed
    from initial positions nudged by `NUDGE_M` (`chaos_spread`); MJX within
    that spread is as faithful as C is to itself. Beyond both, `parting`
    finds the first step at which each particle parts and the geom pairs in
    contact there, with a threshold of 1e-6 of the scene's size (rounding
    differences stay near 1e-12 m; a contact computed differently gives 1e-5
    m or more within a step or two).

    Args:
      scene: the `Scene`.
      qpos0: (n, nq) initial positions.
      qvel0: (n, nv) initial velocities.
      ctrl: (n, T, nu) controls, or None with `horizon`.
      qpos_mjx: (n, T, nq) MJX's states after each step.
      qpos_c: (n, T, nq) C's, with the scene's own solver.
      tolerance: metres.
      horizon: T when `ctrl` is None.
    """
    from mjstamp import colliders  # pylint: disable=g-import-not-at-top

    m = scene.m
    div = divergence(tracked_points(m, qpos_mjx), tracked_points(m, qpos_c))
    median, p95 = float(np.median(div)), float(np.percentile(div, 95))
    approximate = tuple(colliders.approximate_pairs(m))
    if p95 <= tolerance:
        return Verdict(median, p95, tolerance, None, "tolerance", None, approximate)
    spread = chaos_spread(scene, qpos0, qvel0, ctrl, horizon=horizon)
    chaos = float(np.percentile(spread, 95))
    if p95 <= chaos:
        return Verdict(median, p95, tolerance, chaos, "chaos", None, approximate)
    where = parting(m, qpos0, qpos_mjx, qpos_c, threshold=1e-6 * scene.length_scale)
    return Verdict(median, p95, tolerance, chaos, "none", where, approximate)
