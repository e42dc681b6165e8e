"""Uncertain physics: model parameters and initial positions perturbed by MJCF name.

A task declares what it is unsure of (`Task.uncertain`): the friction of some
geoms, the mass of some bodies, and so on, each with a spread. This module
resolves those declarations against a scene once (names to ids, one line for
a bad name or range) and draws perturbed `MjModel`s and initial positions
from them, seeded, for the robustness score of `mjstamp.verify.robustness`.

Relative kinds scale a parameter by a factor 1 + ε: ε uniform in
[−spread, spread] ("uniform", the default) or normal with standard deviation
`spread` ("normal", factors clipped at 0.01 so they stay positive). "position"
adds noise in metres to the translational coordinates (free and slide joints)
of a body's initial position: normal with standard deviation `spread` (the
default) or uniform in [−spread, spread].
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import math
from collections.abc import Sequence

import mujoco
import numpy as np

from mjstamp.errors import MjstampError, valid_list

#: Kind of parameter -> (the kind of MJCF element it names, what it scales).
KINDS = {
    "friction": ("geom", "geom_friction (sliding, torsional, rolling)"),
    "mass": ("body", "body_mass and body_inertia (density)"),
    "damping": ("joint", "dof_damping of the joint's degrees of freedom"),
    "solref": ("geom", "the contact time constant geom_solref[0]"),
    "gain": ("actuator", "actuator_gainprm[0] (and an affine bias's biasprm[1:3])"),
    "position": ("body", "the initial position of a free or slide-jointed body, metres"),
}

#: Spread of each kind when a task names none: ±20% friction, ±10% mass, ±20% damping,
#: ±20% contact time constant, ±10% actuator gain, 5 mm initial position noise.
DEFAULT_SPREAD = {"friction": 0.2, "mass": 0.1, "damping": 0.2, "solref": 0.2, "gain": 0.1,
                  "position": 0.005}

#: What `Task.uncertain()` with no kind declares: friction of every geom, mass of every
#: body and position of every free or slide-jointed body, at their default spreads.
DEFAULT_KINDS = ("friction", "mass", "position")

DISTRIBUTIONS = ("uniform", "normal")

#: Largest position spread, metres: noise wider than this is a different task.
MAX_POSITION_SPREAD = 1.0


@dataclasses.dataclass(frozen=True)
class Uncertain:
    """One declared uncertainty, resolved against a scene.

    Attributes:
      kind: one of `KINDS`.
      ids: ids of the elements it perturbs (geoms, bodies, joints or actuators).
      names: their names (or ids as text, for unnamed elements).
      spread: relative half-width or standard deviation; metres for "position".
      distribution: "uniform" or "normal".
    """

    kind: str
    ids: tuple[int, ...]
    names: tuple[str, ...]
    spread: float
    distribution: str

    def describe(self) -> dict:
        """JSON-ready: kind, names, spread, distribution."""
        return {"kind": self.kind, "names": list(self.names), "spread": self.spread,
                "distribution": self.distribution}


def _translational(m: mujoco.MjModel, body: int) -> list[int]:
    """Addresses in qpos of a body's translational coordinates (free: x, y, z; slides)."""
    out = []
    for j in range(m.body_jntadr[body], m.body_jntadr[body] + m.body_jntnum[body]):
        adr = int(m.jnt_qposadr[j])
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            out += [adr, adr + 1, adr + 2]
        elif m.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE:
            out.append(adr)
    return out


def _name(m: mujoco.MjModel, obj: str, i: int) -> str:
    return mujoco.mj_id2name(m, getattr(mujoco.mjtObj, f"mjOBJ_{obj.upper()}"), i) or str(i)


def _candidates(m: mujoco.MjModel, kind: str) -> list[int]:
    """Elements a kind applies to when the task names none."""
    if kind in ("friction", "solref"):
        return list(range(m.ngeom))
    if kind == "mass":
        return [b for b in range(1, m.nbody) if m.body_mass[b] > 0]
    if kind == "damping":
        return list(range(m.njnt))
    if kind == "gain":
        return list(range(m.nu))
    return [b for b in range(1, m.nbody) if _translational(m, b)]


def resolve(scene, task: str, kind: str, names: Sequence[str | int] | str | None = None, *,
            spread: float | None = None, distribution: str | None = None) -> Uncertain:
    """One declaration checked against a scene, or one line saying what is valid.

    Args:
      scene: the `Scene`.
      task: the task's name (for messages).
      kind: one of `KINDS`.
      names: MJCF names (or ids) of the elements; None: every element the kind
        applies to (every geom, every body with mass, ...).
      spread: see the module docstring; None: `DEFAULT_SPREAD[kind]`.
      distribution: "uniform" or "normal"; None: normal for "position",
        uniform otherwise.

    Returns:
      An `Uncertain`.
    """
    where = f"task {task!r}: uncertain"
    if kind not in KINDS:
        raise MjstampError(f"{where} kind {kind!r} is not known; valid: {valid_list(KINDS)}")
    obj = KINDS[kind][0]
    if distribution is None:
        distribution = "normal" if kind == "position" else "uniform"
    if distribution not in DISTRIBUTIONS:
        raise MjstampError(f"{where} {kind}: distribution {distribution!r} is not known; "
                           f"valid: {valid_list(DISTRIBUTIONS)}")
    spread = DEFAULT_SPREAD[kind] if spread is None else spread
    try:
        spread = float(spread)
    except (TypeError, ValueError):
        raise MjstampError(f"{where} {kind}: spread={spread!r} is not a number") from None
    if kind == "position":
        if not 0 <= spread <= MAX_POSITION_SPREAD:
            raise MjstampError(f"{where} position: spread={spread} m is not possible; valid: "
                               f"0 to {MAX_POSITION_SPREAD} m")
    elif distribution == "uniform" and not 0 <= spread < 1:
        raise MjstampError(f"{where} {kind}: spread={spread} would make a factor 1 ± spread "
                           "reach zero or below; valid: 0 <= spread < 1 (a share, 0.2 = ±20%)")
    elif distribution == "normal" and not 0 <= spread <= 0.5:
        raise MjstampError(f"{where} {kind}: spread={spread} is not possible for a normal "
                           "factor 1 + N(0, spread²); valid: 0 <= spread <= 0.5")
    m = scene.m
    if names is None:
        ids = _candidates(m, kind)
    else:
        if isinstance(names, (str, int)):
            names = [names]
        ids = [scene.id(obj, n) for n in names]
        if kind == "position":
            movable = _candidates(m, kind)
            for n, i in zip(names, ids, strict=True):
                if i not in movable:
                    raise MjstampError(
                        f"{where} position: body {n!r} has no free or slide joint to move; "
                        f"valid: {valid_list([_name(m, 'body', b) for b in movable]) or '(none)'}")
    ids = tuple(dict.fromkeys(int(i) for i in ids))
    return Uncertain(kind, ids, tuple(_name(m, obj, i) for i in ids), spread, distribution)


def defaults(scene, task: str) -> tuple[Uncertain, ...]:
    """The uncertainty `Task.uncertain()` declares (`DEFAULT_KINDS`), empty kinds left out."""
    out = (resolve(scene, task, kind) for kind in DEFAULT_KINDS)
    return tuple(u for u in out if u.ids)


def merge(earlier: Sequence[Uncertain], new: Uncertain) -> tuple[Uncertain, ...]:
    """Declarations with `new` added: it replaces what earlier ones said of its elements."""
    out = []
    for u in earlier:
        if u.kind == new.kind:
            keep = [(i, n) for i, n in zip(u.ids, u.names, strict=True) if i not in new.ids]
            if not keep:
                continue
            u = dataclasses.replace(u, ids=tuple(i for i, _ in keep),
                                    names=tuple(n for _, n in keep))
        out.append(u)
    return (*out, new)


def from_describe(m: mujoco.MjModel, entries: Sequence[dict], where: str) -> tuple[Uncertain, ...]:
    """The `Uncertain`s that `Uncertain.describe` wrote, resolved again against `m`.

    For a results directory: its plans.json's `robustness.uncertain` against its
    scene.mjb gives back the draws its scores were computed on (`sample`).

    Args:
      m: the model the declarations were resolved against.
      entries: `Uncertain.describe()` dicts.
      where: what holds them (named in errors), e.g. "'out/plans.json'".

    Raises:
      MjstampError: an entry of an unknown kind or distribution, without names
        or spread, or naming an element `m` lacks (one line, what is valid).
    """
    out = []
    for e in entries:
        kind = e.get("kind") if isinstance(e, dict) else None
        if kind not in KINDS:
            raise MjstampError(f"{where}: uncertain entry {e!r} has no known kind; valid: "
                               f"{valid_list(KINDS)}")
        obj = KINDS[kind][0]
        count = getattr(m, {"geom": "ngeom", "body": "nbody", "joint": "njnt",
                            "actuator": "nu"}[obj])
        try:
            spread, names = float(e["spread"]), [str(n) for n in e["names"]]
        except (KeyError, TypeError, ValueError):
            raise MjstampError(f"{where}: uncertain {kind} entry {e!r} needs names (a list) "
                               "and spread (a number)") from None
        if e.get("distribution") not in DISTRIBUTIONS:
            raise MjstampError(f"{where}: uncertain {kind} distribution "
                               f"{e.get('distribution')!r} is not known; valid: "
                               f"{valid_list(DISTRIBUTIONS)}")
        ids = []
        for n in names:
            i = mujoco.mj_name2id(m, getattr(mujoco.mjtObj, f"mjOBJ_{obj.upper()}"), n)
            if i < 0 and n.isdigit() and int(n) < count:
                i = int(n)  # an unnamed element, written as its id
            if i < 0:
                raise MjstampError(f"{where}: uncertain {kind} names {obj} {n!r}, which the "
                                   f"saved scene lacks; valid: "
                                   f"{valid_list(_name(m, obj, j) for j in range(count))}")
            ids.append(i)
        out.append(Uncertain(kind, tuple(ids), tuple(names), spread, str(e["distribution"])))
    return tuple(out)


@dataclasses.dataclass
class Perturbations:
    """M draws of the declared uncertainty.

    Attributes:
      models: M perturbed copies of the scene's MjModel (same size signature).
      qpos_noise: (M, nq) added to a plan's initial positions.
    """

    models: list[mujoco.MjModel]
    qpos_noise: np.ndarray


def _draw(rng: np.random.Generator, u: Uncertain, shape) -> np.ndarray:
    if u.distribution == "uniform":
        eps = rng.uniform(-u.spread, u.spread, shape)
    else:
        eps = rng.normal(0.0, u.spread, shape)
    return eps if u.kind == "position" else np.maximum(1.0 + eps, 0.01)


#: Random streams: the robustness score's draws, robust planning's, and robust
#: selection's (`robust.select`): other draws, so a robust solve is scored on models it
#: neither optimised for nor chose its plans on.
SCORE_STREAM, PLAN_STREAM, SELECT_STREAM = 0x0B05, 0x0B06, 0x0B07


def sample(m: mujoco.MjModel, uncertain: Sequence[Uncertain], samples: int,
           seed: int, *, stream: int = SCORE_STREAM) -> Perturbations:
    """`samples` perturbed models and initial-position offsets, the same for every plan.

    The same draws for every plan (common random numbers) make plans' scores
    comparable; the same seed gives the same draws.

    Args:
      m: the nominal model (the scene's own solver settings).
      uncertain: resolved declarations.
      samples: M >= 1.
      seed: seeds the draws.
      stream: `SCORE_STREAM`, `PLAN_STREAM` or `SELECT_STREAM`.

    Returns:
      `Perturbations`.
    """
    rng = np.random.default_rng([seed, stream])
    models = [copy.copy(m) for _ in range(samples)]
    noise = np.zeros((samples, m.nq))
    for u in uncertain:
        if not u.ids or u.spread == 0:
            continue
        if u.kind == "position":
            adr = [a for b in u.ids for a in _translational(m, b)]
            noise[:, adr] += _draw(rng, u, (samples, len(adr)))
            continue
        factor = _draw(rng, u, (samples, len(u.ids)))
        ids = np.asarray(u.ids)
        for k, mk in enumerate(models):
            f = factor[k]
            if u.kind == "friction":
                mk.geom_friction[ids] = m.geom_friction[ids] * f[:, None]
            elif u.kind == "solref":
                mk.geom_solref[ids, 0] = m.geom_solref[ids, 0] * f
            elif u.kind == "mass":
                mk.body_mass[ids] = m.body_mass[ids] * f
                mk.body_inertia[ids] = m.body_inertia[ids] * f[:, None]
            elif u.kind == "damping":
                for j, fj in zip(ids, f, strict=True):
                    dofs = [d for d in range(m.nv) if m.dof_jntid[d] == j]
                    mk.dof_damping[dofs] = m.dof_damping[dofs] * fj
            elif u.kind == "gain":
                mk.actuator_gainprm[ids, 0] = m.actuator_gainprm[ids, 0] * f
                affine = m.actuator_biastype[ids] == mujoco.mjtBias.mjBIAS_AFFINE
                a = ids[affine]
                mk.actuator_biasprm[a, 1:3] = m.actuator_biasprm[a, 1:3] * f[affine, None]
    if any(u.kind == "mass" and u.ids and u.spread for u in uncertain):
        for mk in models:
            # N.B. quantities derived from masses at compile time (subtree masses,
            # inverse weights that scale the constraint regularisation) follow them.
            mujoco.mj_setConst(mk, mujoco.MjData(mk))
    return Perturbations(models, noise)


def is_zero(uncertain: Sequence[Uncertain]) -> bool:
    """Whether nothing is perturbed (no declaration, or every spread zero)."""
    return all(not u.ids or u.spread == 0 or math.isclose(u.spread, 0.0) for u in uncertain)


#: MjModel fields a draw can change: directly, or through mj_setConst when masses change.
MODEL_FIELDS = ("geom_friction", "geom_solref", "body_mass", "body_inertia", "body_subtreemass",
                "body_invweight0", "dof_invweight0", "tendon_invweight0", "dof_damping",
                "actuator_gainprm", "actuator_biasprm", "actuator_acc0", "dof_M0")


@dataclasses.dataclass(frozen=True, eq=False)
class Batch:
    """K draws of the uncertainty for robust planning: every particle is rolled out in each.

    The same K draws for every particle and every iteration (common random
    numbers), so the robust cost is a smooth function of θ.

    Attributes:
      samples: K.
      cvar: the share of the worst draws whose mean cost is optimised (CVaR at
        that level); 1.0: the expected cost.
      seed: the solve's seed (`PLAN_STREAM`).
      fields: `mjx.Model` fields that differ from the nominal model, (K, ...) each.
      qpos_noise: (K, nq) added to every particle's initial positions.
    """

    samples: int
    cvar: float
    seed: int
    fields: dict
    qpos_noise: np.ndarray

    def key(self) -> str:
        """A digest of the draws (for trace-cache keys)."""
        h = hashlib.sha256(f"{self.samples} {self.cvar!r} {self.seed}".encode())
        for name in sorted(self.fields):
            h.update(name.encode())
            h.update(np.ascontiguousarray(self.fields[name], np.float64).tobytes())
        h.update(np.ascontiguousarray(self.qpos_noise, np.float64).tobytes())
        return h.hexdigest()[:16]

    def worst(self) -> int:
        """How many of the K draws the CVaR averages (at least one)."""
        return max(1, math.ceil(self.cvar * self.samples - 1e-9))

    def describe(self) -> dict:
        """JSON-ready: samples, cvar, seed and the fields drawn."""
        return {"samples": self.samples, "cvar": self.cvar, "seed": self.seed,
                "fields": sorted(self.fields),
                "position_noise": bool(np.any(self.qpos_noise))}


def batch(m_grad: mujoco.MjModel, uncertain: Sequence[Uncertain], samples: int, seed: int,
          cvar: float = 1.0) -> Batch:
    """K draws on the gradient model (`Scene.m_grad`) for robust planning (`Batch`).

    Fields derived from masses at compile time follow them (mj_setConst on the
    gradient model), as in the perturbed MuJoCo C models the score replays.
    """
    p = sample(m_grad, uncertain, samples, seed, stream=PLAN_STREAM)
    fields = {}
    for name in MODEL_FIELDS:
        nominal = np.asarray(getattr(m_grad, name))
        drawn = np.stack([np.asarray(getattr(mk, name)) for mk in p.models])
        if drawn.size and not np.array_equal(drawn, np.broadcast_to(nominal, drawn.shape)):
            fields[name] = drawn
    return Batch(samples, float(cvar), seed, fields, p.qpos_noise)
