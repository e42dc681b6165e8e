"""A small library of costs (on MJX rollouts) and success predicates (on C replays).

Costs are functions of a `Rollout` returning (n,) values; any JAX function of
the rollout works the same way. Success predicates are functions of a
`plans.Replay` (numpy) returning (ok (n,) bool, label (n,) str).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp import relax


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

    def cost(r):
        sd = r.signed_distance(geom1, geom2)
        tau = 0.1 * r.scene.length_scale if temperature is None else temperature
        return relax.softmin_aggregate(
            jax.nn.relu(sd), mask=r.until_contact(geom1, geom2), temperature=tau
        )

    return cost


def reach(
    body: str, sites: Sequence[str], *, when: str = "softmin", temperature: float | None = None,
    axes: Sequence[int] = (0, 1),
):
    """Squared distance of a body to the nearest of several goal sites.

    L = min_g ‖x_t − g‖² at the final step (`when="final"`, App. B-D's
    L_target) or softmin-aggregated over the whole trajectory
    (`when="softmin"`): passing through a goal counts, which matches a success
    predicate that asks whether the body *enters* a goal region at any time.

    Args:
      body: body name.
      sites: goal site names.
      when: "final" or "softmin".
      axes: world axes the distance is measured along: (0, 1) on a table
        (the default), (0, 1, 2) in space.
      temperature: softmin temperature in m². Default: (L / 20)² with L the
        scene's size (`Scene.length_scale`; 0.016 m² on a 2.5 m table), so
        passes within a few tenths of the scene of the goal all pull.

    References:
      STAMP App. B-D (target loss).
    """
    if when not in ("final", "softmin"):
        raise ValueError(f"reach(when={when!r}); valid: final, softmin")

    axes = list(axes)

    def cost(r):
        x = r.body_pos(body)[..., axes]
        goals = jnp.stack([r.site_pos(s)[..., axes] for s in sites], axis=-2)  # (n, T, g, a)
        d2 = jnp.min(jnp.sum((x[:, :, None] - goals) ** 2, axis=-1), axis=-1)  # (n, T)
        if when == "final":
            return d2[:, -1]
        tau = (r.scene.length_scale / 20) ** 2 if temperature is None else temperature
        return relax.softmin_aggregate(d2, temperature=tau)

    return cost


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
    axes = list(axes)

    def predicate(replay):
        x = replay.body_pos(body)[..., axes]  # (n, T, a)
        labels = list(goals)
        inside = np.stack(
            [np.linalg.norm(x - replay.site_pos(goals[k])[..., axes], axis=-1) < radius
             for k in labels], axis=-1)  # (n, T, g)
        hit_any = inside.any(axis=-1)
        ok = hit_any.any(axis=1)
        first_t = np.argmax(hit_any, axis=1)
        which = np.argmax(inside[np.arange(len(ok)), first_t], axis=-1)
        label = np.where(ok, np.asarray(labels, dtype=object)[which], "")
        return ok, label

    return predicate


def box_target(body: str, site: str, *, margin: float = 0.0):
    """Goal-region loss at the final step: how far a body's centre is outside a box site.

    L = Σ_{i ∈ {x, y}} max(0, |x_T,i − c_i| − t_i)², with c the site's centre
    and t_i its half-size less `margin` (so that a plan aims inside the region,
    not at its edge).

    References:
      STAMP App. C-C (L_target).
    """

    def cost(r):
        x = r.body_pos(body)[:, -1, :2]
        c = r.site_pos(site)[:, -1, :2]
        half = jnp.asarray(r.scene.m.site_size[r.scene.site(site), :2] - margin, x.dtype)
        return jnp.sum(jax.nn.relu(jnp.abs(x - c) - half) ** 2, axis=-1)

    return cost


def ends_in(body: str, site: str):
    """Success predicate: the body's centre is inside a box site at the final step.

    Returns:
      fn(replay) -> (ok (n,) bool, label (n,) str, always "").
    """

    def predicate(replay):
        x = replay.body_pos(body)[:, -1, :2]
        c = replay.site_pos(site)[:, -1, :2]
        half = replay.scene.m.site_size[replay.scene.site(site), :2]
        ok = np.all(np.abs(x - c) <= half, axis=-1)
        return ok, np.full(len(ok), "", dtype=object)

    return predicate
