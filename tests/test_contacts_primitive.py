"""C's primitive colliders in MJX (mjstamp.colliders.primitive) against MuJoCo C.

Per pair: the installed table's contacts against C's on the harness's random
draws (`compare.run`) and on hand-made deep and degenerate poses the draws do
not reach (a sphere's centre inside a box or a cylinder, on a capsule's axis;
parallel, crossing and collinear capsules; cylinders and boxes flat on or
lying across a plane), then reverse-mode gradients against central
differences, and finite gradients on degenerate poses.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src.collision_types import GeomInfo

from mjstamp import colliders
from mjstamp.colliders import compare, primitive

PORTED = ["plane-capsule", "plane-cylinder", "plane-box", "sphere-sphere", "sphere-capsule",
          "sphere-cylinder", "sphere-box", "capsule-capsule"]
# MJX's own functions give C's contacts on these (left unported). N.B. sphere-sphere too,
# but for concentric spheres (ported for those: see _deep_cases).
MJX_OWN = ["plane-sphere", "plane-ellipsoid"]
TOL = 1e-9

# 90-degree turns, so that axes and faces are exactly parallel.
_ID = np.array([1.0, 0.0, 0.0, 0.0])
_X90 = np.array([np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0])
_Y90 = np.array([np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0])


@pytest.fixture(scope="module", autouse=True)
def _patched():
    colliders.patch_collisions()


def _fn(name: str):
    return colliders.PORTED[compare.parse_pair(name)]


@pytest.mark.parametrize("name", PORTED)
def test_port_gives_c_contacts_on_random_draws(name):
    t1, t2 = compare.parse_pair(name)
    assert colliders.PORTED[(t1, t2)] is getattr(primitive, name.replace("-", "_"))
    if name == "capsule-capsule":
        return _capsules_on_random_draws()
    report = compare.run(t1, t2, 300, seed=7)
    assert report.contacts_c > 250
    assert report.within(TOL), report


def _capsules_on_random_draws():
    """Capsule-capsule, with the normal judged by how well C itself defines it.

    The normal is the direction between the axes' closest points, |v| = dist +
    r1 + r2 apart; where the axes nearly cross, v is a difference of
    coordinates of 0.1 m that cancel to nanometres, and a rounding of 1e-16
    there (an XLA fused multiply-add) turns the normal by 1e-16 / |v|: 1.8e-6
    seen at |v| = 3.7e-9 m (seed 7, draw 2), where C's own normal is no better
    defined; the position, the normal times a radius off an axis, with it.
    Distances stay within 1e-9.
    """
    pm = compare.pair_model(*compare.parse_pair("capsule-capsule"))
    draws = compare.draw(pm, 300, np.random.default_rng(7))
    c, j = compare.c_contacts(pm, draws), compare.mjx_contacts(pm, draws)
    report = compare.compare(pm, draws, c, j)
    assert report.contacts_c > 250 and report.count_mismatches == 0, report
    assert report.dist <= TOL, report
    radii = draws.size[:, 0, 0] + draws.size[:, 1, 0]
    for i, (a, b) in enumerate(zip(c, j, strict=True)):
        for row in a:
            near = b[np.argmin(np.linalg.norm(b[:, 1:4] - row[1:4], axis=1))]
            loose = TOL + 1e-15 / (row[0] + radii[i])  # |v| = dist + r1 + r2
            assert np.abs(near[1:13] - row[1:13]).max() <= loose, (i, row[0] + radii[i])


@pytest.mark.parametrize("name", MJX_OWN)
def test_mjx_own_gives_c_contacts_on_random_draws(name):
    t1, t2 = compare.parse_pair(name)
    assert (t1, t2) not in colliders.PORTED
    report = compare.run(t1, t2, 300, seed=7)
    assert report.contacts_c > 250
    assert report.within(TOL), report


def _rot(q) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(q, float))
    return mat.reshape(3, 3)


def _quat(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _report(name: str, cases) -> compare.Report:
    """C against the installed table on poses (size1, size2, q1, q2, pos2, margins) each."""
    pm = compare.pair_model(*compare.parse_pair(name))
    kinds = (compare.NAMES[pm.t1], compare.NAMES[pm.t2])
    n = len(cases)
    size, rbound = np.zeros((n, 2, 3)), np.zeros((n, 2))
    margin, qpos = np.zeros((n, 2)), np.zeros((n, pm.m.nq))
    for i, (s1, s2, q1, q2, p2, mg) in enumerate(cases):
        size[i, 0, :len(s1)], size[i, 1, :len(s2)] = s1, s2
        for g, kind in enumerate(kinds):
            if kind == "plane":
                size[i, g], rbound[i, g] = pm.m.geom_size[g], pm.m.geom_rbound[g]
            else:
                rbound[i, g] = compare._rbound(kind, size[i, g][None])[0]
        margin[i] = mg
        qpos[i] = compare._qpos(pm.m, None if pm.plane else q1, q2, np.asarray(p2, float))
    draws = compare.Draws(size, rbound, margin, qpos, np.zeros(n))
    return compare.compare(pm, draws, compare.c_contacts(pm, draws),
                           compare.mjx_contacts(pm, draws))


def _deep_cases(name: str, rng) -> list:
    """Poses the harness's draws do not reach, for pair `name`."""
    cases = []
    if name in ("sphere-box", "sphere-cylinder"):
        # the sphere's centre inside the solid, random and exact
        for _ in range(40):
            r, q1, q2 = rng.uniform(0.05, 0.5), _quat(rng), _quat(rng)
            if name == "sphere-box":
                s2 = rng.uniform(0.05, 0.5, 3)
                u = rng.uniform(-1, 1, 3) * s2
            else:
                s2 = rng.uniform(0.05, 0.5, 2)
                rho, phi = s2[0] * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
                u = np.array([rho * np.cos(phi), rho * np.sin(phi), rng.uniform(-1, 1) * s2[1]])
            cases.append(([r], s2, q1, q2, -_rot(q2) @ u, [0.0, 0.0]))
    if name == "sphere-box":
        cases += [([0.1], [0.2, 0.2, 0.2], _ID, _ID, [0, 0, 0], [0, 0]),  # centre: six ties
                  ([0.1], [0.2, 0.3, 0.1], _ID, _X90, [0, 0, 0], [0, 0]),
                  ([0.1], [0.2, 0.3, 0.1], _ID, _ID, [0.2, 0, 0], [0, 0]),  # on a face
                  ([0.1], [0.2, 0.3, 0.1], _ID, _ID, [0.2, 0.3, 0.0], [0.01, 0])]  # on an edge
    if name == "sphere-sphere":
        # concentric: C's normal is the cross product of the z axes (MJX: always x)
        for q1, q2 in ((_ID, _X90), (_X90, _Y90), (_ID, _ID), (_quat(rng), _quat(rng))):
            cases.append(([0.1], [0.2], q1, q2, [0, 0, 0], [0.0, 0.0]))
    if name in ("sphere-cylinder", "sphere-capsule"):
        # on the axis: side, cap and (cylinder) rim branches, concentric for the capsule
        for z in (0.0, 0.05, 0.1, 0.3, -0.3, 0.45):
            for q1 in (_ID, _X90, _Y90):
                cases.append(([0.1], [0.2, 0.3], q1, _ID, [0, 0, -z], [0.01, 0]))
                cases.append(([0.1], [0.2, 0.3], q1, _ID, [0.25, 0, -z], [0.01, 0]))
    if name == "capsule-capsule":
        # parallel (overlapping, end to end, collinear), crossing and concentric
        for q1, q2 in ((_ID, _ID), (_ID, _X90), (_X90, _Y90), (_Y90, _Y90)):
            for p2 in ([0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.2], [0, 0, 0.5], [0, 0, 0.55],
                       [0.1, 0.1, 0.7], [0.2, 0, 0], [0, 0, -0.3]):
                cases.append(([0.1, 0.3], [0.15, 0.2], q1, q2, p2, [0.01, 0.0]))
        # zero-length segments (C's degenerate branches of the segment weights)
        for s1, s2 in (([0.1, 0.0], [0.15, 0.2]), ([0.1, 0.3], [0.15, 0.0]),
                       ([0.1, 0.0], [0.15, 0.0])):
            for p2 in ([0.1, 0, 0.1], [0, 0.2, 0.5], [0, 0, 0]):
                cases.append((s1, s2, _ID, _X90, p2, [0.01, 0.0]))
    if name in ("plane-cylinder", "plane-capsule", "plane-box"):
        # axis along the normal, and across it (disks and faces parallel to the plane)
        s2 = [0.2, 0.3, 0.1] if name == "plane-box" else [0.2, 0.3]
        for q2 in (_ID, _X90, _Y90):
            for z in (0.05, 0.1, 0.2, 0.25, 0.29, 0.3, 0.31, 0.35):
                cases.append(([], s2, None, q2, [0.1, 0.2, z], [0.0, 0.02]))
    return cases


@pytest.mark.parametrize("name", PORTED)
def test_port_gives_c_contacts_on_deep_and_degenerate_poses(name):
    report = _report(name, _deep_cases(name, np.random.default_rng(11)))
    assert report.contacts_c > 0
    assert report.within(TOL), report


def test_parallel_capsules_follow_the_binary_not_the_source():
    """Capsule 2 inside capsule 1's span: C's contacts sit at capsule 2's ends.

    The C source's mjraw_CapsuleCapsule would put them at capsule 1's ends
    (x1 = ±1); the installed binary's segment weights do not. The port follows
    the binary.
    """
    cases = [([0.1, 0.3], [0.15, 0.2], _ID, _ID, [0.2, 0, 0.05], [0.0, 0.0])]
    report = _report("capsule-capsule", cases)
    assert report.contacts_c == 2 and report.within(TOL), report
    pm = compare.pair_model(*compare.parse_pair("capsule-capsule"))
    draws = compare.Draws(np.array([[[0.1, 0.3, 0], [0.15, 0.2, 0]]]), np.array([[0.4, 0.35]]),
                          np.zeros((1, 2)), compare._qpos(pm.m, _ID, _ID,
                                                          np.array([0.2, 0, 0.05]))[None],
                          np.zeros(1))
    z = np.sort(compare.c_contacts(pm, draws)[0][:, 3])
    np.testing.assert_allclose(z, [0.05 - 0.2, 0.05 + 0.2], atol=1e-12)


# ----------------------------------------------------------------------------- gradients


def _turn(axis, angle):
    """Rotation by `angle` about unit `axis` (Rodrigues)."""
    k = jnp.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * k + (1 - jnp.cos(angle)) * (k @ k)


_C = (jnp.array([0.3, -0.7, 0.5]), jnp.array([-0.2, 0.4, 0.9]), jnp.array([0.8, 0.1, -0.3]))
_AXIS = jnp.array([0.48, -0.6, 0.64])


def _objective(fn, x, pose):
    """Σ over active slots of dist + pos·c + normal·c' + tangent·c'' at geom 2 moved by x.

    x = (shift of geom 2 (3), turn about `_AXIS` (1)).
    """
    pos1, mat1, size1, pos2, mat2, size2, margin = pose
    mat2 = _turn(_AXIS, x[3]) @ mat2
    dist, pos, frame = fn(GeomInfo(pos1, mat1, size1), GeomInfo(pos2 + x[:3], mat2, size2),
                          margin)
    val = dist + pos @ _C[0] + frame[:, 0] @ _C[1] + frame[:, 1] @ _C[2]
    return jnp.sum(jnp.where(dist < margin, val, 0.0))


def _poses(name: str, n: int, rng) -> tuple:
    """Generic penetrating poses of the harness (C's kinematics), stacked.

    Sphere-box and sphere-cylinder get three more with the sphere's centre
    inside (C's deep branch, which the harness's draws do not reach).
    """
    pm = compare.pair_model(*compare.parse_pair(name))
    draws = compare.draw(pm, n, rng, margin_share=0.0, aligned_share=0.0, miss_share=0.0)
    m, d = pm.m, mujoco.MjData(pm.m)
    rows = []
    for i in range(n):
        compare._set_sizes(m, draws.size[i], draws.rbound[i], draws.margin[i])
        d.qpos[:] = draws.qpos[i]
        mujoco.mj_kinematics(m, d)
        rows.append((d.geom_xpos[0].copy(), d.geom_xmat[0].reshape(3, 3).copy(),
                     m.geom_size[0].copy(), d.geom_xpos[1].copy(),
                     d.geom_xmat[1].reshape(3, 3).copy(), m.geom_size[1].copy(), 0.0))
    if name in ("sphere-box", "sphere-cylinder"):
        size2 = [0.2, 0.3, 0.1] if name == "sphere-box" else [0.2, 0.3, 0.0]
        top = 0.08 if name == "sphere-box" else 0.25  # near the top face or cap
        for u in ([0.05, -0.1, 0.03], [-0.13, 0.04, -0.02], [0.02, 0.03, top]):
            mat1, mat2 = _rot(_quat(rng)), _rot(_quat(rng))
            rows.append((np.zeros(3), mat1, np.array([0.1, 0, 0]), -mat2 @ np.array(u), mat2,
                         np.array(size2), 0.0))
    return tuple(jnp.asarray(np.stack(col)) for col in zip(*rows, strict=True))


def _degenerate(name: str) -> list:
    """Poses where C branches on a degeneracy (pos1, mat1, size1, pos2, mat2, size2, margin)."""
    eye, z = np.eye(3), np.zeros(3)
    x90, y90 = _rot(_X90), _rot(_Y90)
    plane = np.array([0.0, 0.0, 1.0])
    out = []
    if name.startswith("plane-"):
        s2 = [0.2, 0.3, 0.1] if name == "plane-box" else [0.2, 0.3, 0.0]
        for mat in (eye, x90, y90, -eye @ x90 @ x90):  # along and across the normal, flipped
            for h in (0.05, 0.2, 0.3):
                out.append((z, eye, plane, np.array([0.1, 0.2, h]), mat, s2, 0.01))
    elif name == "sphere-sphere":
        for mat1, mat2 in ((eye, eye), (eye, x90), (x90, y90)):  # concentric, then apart
            for p in ([0, 0, 0], [0.1, 0, 0]):
                out.append((z, mat1, [0.1, 0, 0], np.asarray(p, float), mat2, [0.2, 0, 0], 0.0))
    elif name in ("sphere-box", "sphere-cylinder", "sphere-capsule"):
        s2 = [0.2, 0.3, 0.1] if name == "sphere-box" else [0.2, 0.3, 0.0]
        for p in ([0, 0, 0], [0.2, 0, 0], [0, 0, 0.1], [0, 0, 0.3], [0.2, 0, 0.3],
                  [0.25, 0, 0.4], [0, 0, 0.25]):
            for mat1 in (eye, x90):
                out.append((np.asarray(p, float), mat1, [0.1, 0, 0], z, eye, s2, 0.0))
    elif name == "capsule-capsule":
        for mat2 in (eye, x90, y90):
            for p in ([0, 0, 0], [0.1, 0, 0], [0, 0, 0.5], [0, 0, 0.6], [0, 0, -0.3]):
                out.append((z, eye, [0.1, 0.3, 0], np.asarray(p, float), mat2, [0.15, 0.2, 0],
                            0.0))
                out.append((z, eye, [0.1, 0.0, 0], np.asarray(p, float), mat2, [0.15, 0.0, 0],
                            0.0))  # zero-length segments
    return out


@pytest.mark.parametrize("name", PORTED)
def test_gradients_match_central_differences_and_stay_finite_on_degenerate_poses(name):
    """Reverse mode against central differences (eps 1e-6) on generic poses; finite on all.

    N.B. one compiled gradient per pair serves both sets (compiles dominate the
    file's time). The objective masks unused slots with `jnp.where`, whose zero
    cotangent still runs through every slot's computation: a non-finite local
    derivative anywhere shows as NaN.
    """
    fn = _fn(name).pair_fn
    generic = _poses(name, 12, np.random.default_rng(5))
    degenerate = tuple(np.stack(col) for col in zip(*_degenerate(name), strict=True))
    poses = tuple(jnp.concatenate([jnp.asarray(g), jnp.asarray(d, jnp.float64)])
                  for g, d in zip(generic, degenerate, strict=True))
    n = len(generic[0])
    x0 = jnp.zeros((len(poses[0]), 4))
    grad = np.asarray(jax.jit(jax.vmap(jax.grad(lambda x, p: _objective(fn, x, p))))(x0, poses))
    assert np.all(np.isfinite(grad)), grad[n:]

    value = jax.jit(jax.vmap(lambda x, p: _objective(fn, x, p)))
    some = tuple(p[:n] for p in poses)
    assert np.all(np.asarray(value(x0[:n], some)) != 0)  # some contact active on every pose
    eps = 1e-6
    fd = []
    for k in range(4):
        e = jnp.zeros(4).at[k].set(eps)
        fd.append((value(x0[:n] + e, some) - value(x0[:n] - e, some)) / (2 * eps))
    fd = np.asarray(jnp.stack(fd, axis=1))
    err = np.abs(grad[:n] - fd).max(axis=1) / np.abs(fd).max(axis=1)
    assert err.max() <= 1e-5, (err, grad[:n], fd)
