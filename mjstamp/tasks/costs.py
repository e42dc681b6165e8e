"""A small library of costs (on MJX rollouts) and success predicates (on C replays).

Costs are functions of a `Rollout` returning (n,) values; any JAX function of
the rollout works the same way. Success predicates are functions of a
`verify.Replay` (numpy) returning (ok (n,) bool, label (n,) str).

A cost that is a squared distance also gives its residuals r (n, m), with
the cost Σ r² (`reach`, `box_target`): the solve's precision polish
(`mjstamp.svgd.polish`, Gauss–Newton) descends on them. `aim` is a gap, not
a squared distance, and gives none; `Task.residuals` declares a user's own.

Each factory here returns a `Bound`: its body, site and geom names are looked
up once, in the scene, when `Task.cost` or `Task.success` is given it (hydrax
resolves ids in its task's constructor), so a misspelt name fails where the
user wrote it, in one line listing the valid names; the function the solve
traces holds ids, not names.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp import relax


@dataclasses.dataclass(frozen=True)
class Bound:
    """A cost or predicate whose scene names are resolved once: `bind(scene)` -> function.

    `Task.cost` and `Task.success` bind it to their scene. Called unbound (a
    predicate inside a user's own success function), it binds to the scene of
    what it is called on, every call. A dataclass, so that a task's fingerprint
    hashes it by content (`mjstamp.tasks.fingerprint`).

    Attributes:
      make: scene -> the function, its names looked up in that scene.
      residuals: for a cost that is a sum of squares, scene -> fn(rollout) ->
        r (n, m) with the cost Σ r² (the polish's form of it); else None.
      goal: what the term or predicate measures, (body, goal sites), so that
        a reach cost finds the radius of the `reaches` predicate on the same
        goals (`Task.build`); None where there is no such goal.
      tolerance: the goal's radius in the units of the residuals (a
        predicate's `radius`): the polish stops inside it; None: unknown.
    """

    make: Callable
    residuals: Callable | None = None
    goal: tuple | None = None
    tolerance: float | None = None

    def bind(self, scene) -> Callable:
        """The function on `scene`, with its names looked up there (MjstampError if unknown)."""
        return self.make(scene)

    def bind_residuals(self, scene) -> Callable | None:
        """The residual function on `scene` (r (n, m), cost = Σ r²), or None if it has none."""
        return None if self.residuals is None else self.residuals(scene)

    def __call__(self, x):  # noqa: D102 - the class docstring says it: bound on x's scene
        return self.make(x.scene)(x)


def aim(geom1: str, geom2: str, *, temperature: float | None = None):
    """Aim loss: softmin over t ≤ t_c of the gap max(0, sd_t) between two geoms.

    L_aim = Σ_{t ≤ t_c} σ_t L^(t), σ = softmax(−L / temperature), with
    L^(t) = max(0, signed distance at t) (for two balls: |x_t − x'_t| − 2R)
    and t_c the first contact of the pair.

    Args:
      geom1: the moving geom (the cue ball).
      geom2: the geom to aim at (the target ball).
      temperature: in metres. STAMP's σ = softmax(−L) is temperature 1, too
        flat for distances of a metre or less. Default: a tenth of the scene's
        size (`Scene.length_scale`; 0.25 m on a 2.5 m table): with a sharp
        softmin a shot that leaves the target behind has its smallest gap at
        t = 0, which does not depend on θ, and its particle stalls; a wide one
        lets later, closer passes pull.

    References:
      STAMP App. B-D.
    """

    def make(scene):
        g1, g2 = scene.geom(geom1), scene.geom(geom2)
        tau = 0.1 * scene.length_scale if temperature is None else temperature

        def cost(r):
            sd = r.signed_distance(g1, g2)
            return relax.softmin_aggregate(
                jax.nn.relu(sd), mask=r.until_contact(g1, g2), temperature=tau
            )

        return cost

    return Bound(make)


def reach(
    body: str, sites: Sequence[str], *, when: str = "softmin", temperature: float | None = None,
    axes: Sequence[int] = (0, 1), tolerance: float | None = None,
):
    """Squared distance of a body to the nearest of several goal sites.

    L = min_g ‖x_t − g‖² at the final step (`when="final"`, App. B-D's
    L_target) or softmin-aggregated over the whole trajectory
    (`when="softmin"`): passing through a goal counts, which matches a success
    predicate that asks whether the body *enters* a goal region at any time.

    Its residuals (the polish's form) are r = x_t* − g* (n, len(axes)), the
    offset from the nearest goal g* at t* = T (final) or at the step where the
    body passes nearest a goal (softmin; t* and g* are held fixed within a
    Gauss–Newton step, as a hard argmin of the softmin).

    Args:
      body: body name.
      sites: goal site names.
      when: "final" or "softmin".
      axes: world axes the distance is measured along: (0, 1) on a table
        (the default), (0, 1, 2) in space.
      temperature: softmin temperature in m². Default: (L / 20)² with L the
        scene's size (`Scene.length_scale`; 0.016 m² on a 2.5 m table), so
        passes within a few tenths of the scene of the goal all pull.
      tolerance: the goal's radius in metres, where the polish may stop;
        None: the radius of the task's `reaches` predicate on the same body
        and sites, if it has one (`Task.build`).

    References:
      STAMP App. B-D (target loss).
    """
    if when not in ("final", "softmin"):
        raise ValueError(f"reach(when={when!r}); valid: final, softmin")

    axes = list(axes)

    def offsets(scene):
        """fn(rollout) -> (n, T, g, a) offsets of the body from each goal."""
        b, goal_sites = scene.body(body), [scene.site(s) for s in sites]

        def fn(r):
            x = r.body_pos(b)[..., axes]
            goals = jnp.stack([r.site_pos(s)[..., axes] for s in goal_sites], axis=-2)
            return x[:, :, None] - goals

        return fn

    def make(scene):
        offset = offsets(scene)
        tau = (scene.length_scale / 20) ** 2 if temperature is None else temperature

        def cost(r):
            d2 = jnp.min(jnp.sum(offset(r) ** 2, axis=-1), axis=-1)  # (n, T)
            if when == "final":
                return d2[:, -1]
            return relax.softmin_aggregate(d2, temperature=tau)

        return cost

    def residuals(scene):
        offset = offsets(scene)

        def fn(r):
            off = offset(r)  # (n, T, g, a)
            if when == "final":
                off = off[:, -1:]
            n, steps, goals, a = off.shape
            flat = off.reshape(n, steps * goals, a)
            # N.B. the nearest (step, goal) is a hard choice: no gradient flows through it.
            k = jnp.argmin(jax.lax.stop_gradient(jnp.sum(flat**2, axis=-1)), axis=1)
            return jnp.take_along_axis(flat, k[:, None, None], axis=1)[:, 0]

        return fn

    return Bound(make, residuals, goal=(body, tuple(sites), tuple(axes)), tolerance=tolerance)


def reaches(
    body: str, goals: Mapping[str, str], *, radius: float, axes: Sequence[int] = (0, 1)
):
    """Success predicate: the body's centre comes within `radius` of a goal site.

    Args:
      body: body name.
      goals: {label: site name}; the label of the first goal reached becomes
        part of the task plan (e.g. the pocket).
      radius: in metres.
      axes: world axes the distance is measured along: (0, 1), planar, by
        default; (0, 1, 2) in space.

    Returns:
      fn(replay) -> (ok (n,) bool, label (n,) str; "" where not reached).
    """
    axes_ = list(axes)
    labels = list(goals)

    def make(scene):
        b, goal_sites = scene.body(body), [scene.site(goals[k]) for k in labels]

        def predicate(replay):
            x = replay.body_pos(b)[..., axes_]  # (n, T, a)
            inside = np.stack(
                [np.linalg.norm(x - replay.site_pos(s)[..., axes_], axis=-1) < radius
                 for s in goal_sites], axis=-1)  # (n, T, g)
            hit_any = inside.any(axis=-1)
            ok = hit_any.any(axis=1)
            first_t = np.argmax(hit_any, axis=1)
            which = np.argmax(inside[np.arange(len(ok)), first_t], axis=-1)
            label = np.where(ok, np.asarray(labels, dtype=object)[which], "")
            return ok, label

        return predicate

    return Bound(make, goal=(body, tuple(goals[k] for k in labels), tuple(axes_)),
                 tolerance=float(radius))


def box_target(body: str, site: str, *, margin: float = 0.0):
    """Goal-region loss at the final step: how far a body's centre is outside a box site.

    L = Σ_{i ∈ {x, y}} max(0, |x_T,i − c_i| − t_i)², with c the site's centre
    and t_i its half-size less `margin` (so that a plan aims inside the region,
    not at its edge). Its residuals are r_i = max(0, |x_T,i − c_i| − t_i): zero
    inside, so the polish stops there.

    References:
      STAMP App. C-C (L_target).
    """

    def residuals(scene):
        b, s = scene.body(body), scene.site(site)
        half_size = scene.m.site_size[s, :2] - margin

        def fn(r):
            x = r.body_pos(b)[:, -1, :2]
            c = r.site_pos(s)[:, -1, :2]
            return jax.nn.relu(jnp.abs(x - c) - jnp.asarray(half_size, x.dtype))

        return fn

    def make(scene):
        outside = residuals(scene)

        def cost(r):
            return jnp.sum(outside(r) ** 2, axis=-1)

        return cost

    return Bound(make, residuals, tolerance=0.0)


def ends_in(body: str, site: str):
    """Success predicate: the body's centre is inside a box site at the final step.

    Returns:
      fn(replay) -> (ok (n,) bool, label (n,) str, always "").
    """

    def make(scene):
        b, s = scene.body(body), scene.site(site)
        half = np.array(scene.m.site_size[s, :2])

        def predicate(replay):
            x = replay.body_pos(b)[:, -1, :2]
            c = replay.site_pos(s)[:, -1, :2]
            ok = np.all(np.abs(x - c) <= half, axis=-1)
            return ok, np.full(len(ok), "", dtype=object)

        return predicate

    return Bound(make)


def ends_in_any(body: str, sites: Mapping[str, str]):
    """Success predicate: the body's centre ends inside one of several box sites.

    Args:
      body: body name.
      sites: {label: box site name}; the label of the first site (in this
        order) the body ends in becomes part of the task plan.

    Returns:
      fn(replay) -> (ok (n,) bool, label (n,) str; "" where in none).
    """

    def make(scene):
        checks = {label: ends_in(body, site).bind(scene) for label, site in sites.items()}

        def predicate(replay):
            ok = np.zeros(replay.qpos.shape[0], bool)
            label = np.full(len(ok), "", dtype=object)
            for name, check in checks.items():
                inside = check(replay)[0] & ~ok
                label[inside] = name
                ok |= inside
            return ok, label

        return predicate

    return Bound(make)
