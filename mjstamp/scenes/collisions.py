"""Up-front checks that MJX 3.17 can build, and collide, a MuJoCo model.

The collision table judged is the one rollouts use: MJX's own, with MuJoCo C's
colliders ported by `mjstamp.colliders` in place of MJX's and where MJX
has none (cylinder-box).

``mjx.put_model`` refuses some models that MuJoCo C runs, with a
``NotImplementedError`` at the end of a traceback into MJX's internals: a geom
pair that the model collides but MJX has no collision function for (a
cylinder puck against box rails), a margin on a mesh or height-field pair, an
integrator or option flag MJX lacks. ``mjx.make_data`` (first called at the
first rollout) refuses condim-1 contacts with the elliptic cone, and
``mjx.step`` the discrete integrator, which ``put_model`` lets through.
`check_collidable` finds these before either runs and raises one line naming
the geoms, the file and what would work instead.

Which pairs the model collides is MJX's own rule
(``collision_driver.geom_pairs``): explicit ``<pair>``s, then every geom pair of
different bodies whose contype/conaffinity bits match, except bodies welded
together, parent and child (unless the filterparent flag is disabled), pairs
in ``<exclude>``, plane-plane and plane-hfield. N.B. MJX applies this rule even
when contacts are disabled, so such a model is refused then too.
"""

from __future__ import annotations

import mujoco

from mjstamp import _mjx  # noqa: F401 - imports mujoco.mjx without its stdout chatter
from mjstamp.errors import MjstampError, valid_list


def _mjx_src():
    """MJX's collision table and enums (`mujoco.mjx._src`, imported once mjx is).

    N.B. imported here, after mjstamp._mjx: importing `mujoco.mjx._src`
    first would import `mujoco.mjx` and print its chatter to stdout.
    """
    from mujoco.mjx._src import collision_driver, types  # pylint: disable=g-import-not-at-top

    from mjstamp import colliders  # pylint: disable=g-import-not-at-top

    # N.B. the table judged is the one rollouts use: MJX's, with C's ported colliders.
    colliders.patch_collisions()
    return collision_driver, types

_MJX = "MJX 3.17"
_MESH, _HFIELD = int(mujoco.mjtGeom.mjGEOM_MESH), int(mujoco.mjtGeom.mjGEOM_HFIELD)


def _type_name(t: int) -> str:
    return mujoco.mjtGeom(int(t)).name.removeprefix("mjGEOM_").lower()


def _partners(t: int) -> list[str]:
    """Geom types MJX collides type t with, in mjtGeom order."""
    collision_driver, _ = _mjx_src()
    out = set()
    for a, b in collision_driver._COLLISION_FUNC:  # noqa: SLF001 - MJX's own table
        if int(a) == t:
            out.add(int(b))
        if int(b) == t:
            out.add(int(a))
    return [_type_name(p) for p in sorted(out)]


def _geom(m: mujoco.MjModel, g: int) -> str:
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g)
    return f"geom {name!r}" if name else f"geom #{g}"


def _pair(m: mujoco.MjModel, g1: int, g2: int) -> str:
    """"geom 'puck' (cylinder) and geom 'rail' (box)"."""
    return (
        f"{_geom(m, g1)} ({_type_name(m.geom_type[g1])}) and "
        f"{_geom(m, g2)} ({_type_name(m.geom_type[g2])})"
    )


def _undo(ip: int) -> str:
    """How to stop a pair from colliding."""
    if ip >= 0:
        return "or remove their <pair>"
    return "or exclude the pair (contype/conaffinity bits, or an <exclude> of their bodies)"


def _no_collider(m: mujoco.MjModel, label: str, g1: int, g2: int, ip: int) -> str:
    t1, t2 = int(m.geom_type[g1]), int(m.geom_type[g2])
    n1, n2 = _type_name(t1), _type_name(t2)
    p1, p2 = _partners(t1), _partners(t2)
    partners = f"they collide {n1} with: {valid_list(p1) if p1 else 'nothing'}"
    if n2 != n1:
        partners += f"; and {n2} with: {valid_list(p2) if p2 else 'nothing'}"
    # Planes and height fields are static ground, not a stand-in for a body's geom.
    fixes = []
    for g, others in ((g1, p2), (g2, p1)):
        movable = [t for t in others if t not in ("plane", "hfield")]
        if movable and _type_name(m.geom_type[g]) not in ("plane", "hfield"):
            fixes.append(f"make {_geom(m, g)} a {_or(movable)}")
            own = _type_name(m.geom_type[g])
            if "mesh" in movable and own in ("ellipsoid", "cylinder"):
                fixes[-1] += f" (a mesh collides by its convex hull: a faceted {own} will do)"
    fix = ", or ".join(fixes + [_undo(ip).removeprefix("or ")])
    return (
        f"{label}: {_pair(m, g1, g2)} collide in this model, but {n1}-{n2} is not "
        f"collided by {_MJX} or mjstamp's ports of MuJoCo C's colliders; {partners}; {fix}"
    )


def _or(names: list[str]) -> str:
    """'a, b or c'."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


def _condim(m: mujoco.MjModel, g1: int, g2: int, ip: int) -> int:
    """The contact dimension MJX gives a pair (collision_driver._geom_groups)."""
    if ip >= 0:
        return int(m.pair_dim[ip])
    p1, p2 = m.geom_priority[g1], m.geom_priority[g2]
    if p1 != p2:
        return int(m.geom_condim[g1] if p1 > p2 else m.geom_condim[g2])
    return int(max(m.geom_condim[g1], m.geom_condim[g2]))


def _check_options(m: mujoco.MjModel, label: str) -> None:
    """The option refusals of mjx.put_model (io._put_option), as one line."""
    _, mjx_types = _mjx_src()
    o = m.opt
    # N.B. put_model accepts every mjx IntegratorType, DISCRETE included, but
    # mjx.step only integrates these three: a discrete model failed at the first step.
    stepped = {mjx_types.IntegratorType.EULER, mjx_types.IntegratorType.RK4,
               mjx_types.IntegratorType.IMPLICITFAST}
    if o.integrator not in stepped:
        name = mujoco.mjtIntegrator(o.integrator).name.removeprefix("mjINT_").lower()
        raise MjstampError(
            f"{label}: <option integrator={name!r}> is not supported by {_MJX}; valid: "
            "Euler, RK4, implicitfast"
        )
    for kind, value, valid in (
        ("cone", o.cone, mjx_types.ConeType),
        ("jacobian", o.jacobian, mjx_types.JacobianType),
    ):
        if value not in set(valid):
            raise MjstampError(
                f"{label}: <option {kind}={int(value)}> is not supported by {_MJX}; valid: "
                f"{valid_list(v.name.lower() for v in valid)}"
            )
    for i in range(int(mujoco.mjtEnableBit.mjNENABLE)):
        bit = 1 << i
        if o.enableflags & bit and bit not in set(mjx_types.EnableBit):
            flag = mujoco.mjtEnableBit(bit).name.removeprefix("mjENBL_").lower()
            raise MjstampError(
                f"{label}: <option><flag {flag}=\"enable\"/> is not supported by {_MJX}; "
                "remove it"
            )
    fluid = o.density > 0 or o.viscosity > 0 or any(o.wind)
    if fluid and o.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        raise MjstampError(
            f"{label}: fluid forces (density, viscosity or wind) with integrator "
            f"'implicitfast' are not supported by {_MJX}; use integrator Euler or RK4, "
            "or remove the fluid"
        )


def _check_elements(m: mujoco.MjModel, label: str) -> None:
    """The model-element refusals of mjx.put_model (io._put_model_jax)."""
    _, mjx_types = _mjx_src()
    if m.nflex:
        raise MjstampError(f"{label}: flex objects are not supported by {_MJX}; remove them")
    contact = m.sensor_type == mujoco.mjtSensor.mjSENS_CONTACT
    if contact.any():
        objs = set(int(t) for t in m.sensor_objtype[contact])
        refs = objs | set(int(t) for t in m.sensor_reftype[contact])
        for what, used in (
            ("site", int(mujoco.mjtObj.mjOBJ_SITE) in objs),
            ("body", int(mujoco.mjtObj.mjOBJ_BODY) in refs),
            ("subtree", int(mujoco.mjtObj.mjOBJ_XBODY) in refs),
        ):
            if used:
                raise MjstampError(
                    f"{label}: contact sensors matching by {what} are not supported by "
                    f"{_MJX}; match geoms instead"
                )
        if (m.sensor_intprm[contact, 1] == 3).any():
            raise MjstampError(
                f"{label}: contact sensors with the netforce reduction are not supported "
                f"by {_MJX}"
            )
    for what, values, valid, enum in (
        ("actuator bias type", m.actuator_biastype, mjx_types.BiasType, mujoco.mjtBias),
        ("actuator dynamics type", m.actuator_dyntype, mjx_types.DynType, mujoco.mjtDyn),
        ("actuator gain type", m.actuator_gaintype, mjx_types.GainType, mujoco.mjtGain),
        ("actuator transmission", m.actuator_trntype, mjx_types.TrnType, mujoco.mjtTrn),
        ("equality type", m.eq_type, mjx_types.EqType, mujoco.mjtEq),
        ("sensor type", m.sensor_type, mjx_types.SensorType, mujoco.mjtSensor),
        ("tendon wrap type", m.wrap_type, mjx_types.WrapType, mujoco.mjtWrap),
    ):
        missing = sorted(set(int(v) for v in values) - set(int(v) for v in valid))
        if missing:
            name = enum(missing[0]).name.split("_", 1)[1].lower()
            raise MjstampError(
                f"{label}: {what} {name!r} is not supported by {_MJX}; valid: "
                f"{valid_list(v.name.lower() for v in valid)}"
            )


def check_collidable(m: mujoco.MjModel, label: str) -> None:
    """Raises one line if MJX 3.17 cannot build or collide the model.

    Checks, in this order, what ``mjx.put_model``, ``mjx.make_data`` and
    ``mjx.step`` would refuse: options (integrator, enable flags, fluid forces with
    implicitfast), elements (flex, some contact sensors, actuator, equality,
    sensor and wrap types), then every geom pair the model collides: that MJX
    has a collision function for its types, that a mesh or height-field pair
    has no margin, and that no contact has condim 1 under the elliptic cone.
    N.B. the solver is not checked: a Scene replaces it (`GradOptions.solver`)
    before MJX sees the model, so an MJCF with PGS builds.

    Args:
      m: the model, as compiled from the MJCF.
      label: the file or source, named first in the message.

    Raises:
      MjstampError: one line naming the two geoms (names, else #ids), their
        types, `label`, and what MJX collides instead; or the option or
        element that MJX refuses.
    """
    collision_driver, _ = _mjx_src()
    _check_options(m, label)
    _check_elements(m, label)
    contacts = not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    elliptic = m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    for g1, g2, ip in collision_driver.geom_pairs(m):
        g1, g2, ip = int(g1), int(g2), int(ip)
        t1, t2 = int(m.geom_type[g1]), int(m.geom_type[g2])
        if not collision_driver.has_collision_fn(t1, t2):
            raise MjstampError(_no_collider(m, label, g1, g2, ip))
        if {t1, t2} & {_MESH, _HFIELD}:
            margin = m.pair_margin[ip] if ip >= 0 else m.geom_margin[g1] + m.geom_margin[g2]
            if margin:
                raise MjstampError(
                    f"{label}: {_pair(m, g1, g2)} collide with margin {margin:g}, but "
                    f"{_MJX} has no margin on mesh or height-field collisions; set "
                    f'margin="0" on both geoms{" and their <pair>" if ip >= 0 else ""}'
                )
        if contacts and elliptic and _condim(m, g1, g2, ip) == 1:
            raise MjstampError(
                f"{label}: {_pair(m, g1, g2)} make condim=1 contacts, which {_MJX} does "
                'not support with <option cone="elliptic">; use condim="3" or the '
                "pyramidal cone"
            )
