"""MuJoCo C's general convex collisions in MJX (colliders.convex) against the C engine.

Each pair is collided by MuJoCo C (mj_collision) and by MJX with the ported
colliders on random poses (`compare.run`), and must give the same contacts:
the same number, and distance, position and frame within 1e-9. Gradients of a
smooth function of the contacts are checked against central differences, and
must stay finite on degenerate poses.

N.B. the GJK/EPA colliders are large programs: a cold compile takes one to two
minutes per pair (three for a gradient) on two cores, so those tests are marked
slow; JAX's persistent compilation cache (conftest) makes later runs fast.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src.collision_types import GeomInfo

from mjstamp import colliders
from mjstamp.colliders import ccd, compare, convex, gjk

GJK_PAIRS = ["capsule-cylinder", "cylinder-cylinder", "cylinder-box", "sphere-ellipsoid",
             "capsule-ellipsoid", "ellipsoid-ellipsoid", "ellipsoid-cylinder", "ellipsoid-box",
             "sphere-mesh", "capsule-mesh", "cylinder-mesh", "ellipsoid-mesh", "box-mesh",
             "mesh-mesh"]
TOL = 1e-9


@pytest.fixture(scope="module", autouse=True)
def _patched():
    colliders.patch_collisions()
    colliders.exact_meshes()
    yield
    colliders.exact_meshes(False)


def test_mesh_pairs_mjx_collides_keep_mjx_by_default():
    """sphere-, capsule-, box- and mesh-mesh: MJX's own unless exact_meshes (and reported so)."""
    from mujoco.mjx._src import collision_driver

    table = collision_driver._COLLISION_FUNC  # pylint: disable=protected-access
    opt_in = {(2, 7), (3, 7), (6, 7), (7, 7)}
    colliders.exact_meshes(False)
    try:
        before = colliders.table_version()
        for pair in opt_in:
            assert table[pair] is not colliders.PORTED[pair]
            assert not colliders.is_exact(*pair)
        for pair in ((5, 7), (4, 7), (0, 7), (5, 6)):  # MJX has none, or it is plane-mesh
            assert table[pair] is colliders.PORTED[pair] and colliders.is_exact(*pair)
    finally:
        colliders.exact_meshes()
    assert colliders.table_version() != before
    assert all(table[pair] is colliders.PORTED[pair] and colliders.is_exact(*pair)
               for pair in opt_in)


def _check(pair: str, n: int, seed: int) -> None:
    r = compare.run(*compare.parse_pair(pair), n, seed=seed)
    assert r.count_mismatches == 0, r
    assert max(r.dist, r.pos, r.normal, r.frame) <= TOL, r
    assert r.contacts_c > n // 2, r  # the draws do collide


def test_plane_mesh_matches_c():
    _check("plane-mesh", 300, seed=11)


@pytest.mark.slow
@pytest.mark.parametrize("pair", GJK_PAIRS)
def test_pair_matches_c(pair):
    _check(pair, 300, seed=12)


def test_contact_slots_follow_c():
    """Slots per pair are mj_maxContact's of the 3.17 binary (no margin dependence)."""
    for pair, ncon in {"cylinder-box": 4, "capsule-cylinder": 2, "capsule-mesh": 2,
                       "mesh-mesh": 4, "sphere-ellipsoid": 1, "ellipsoid-box": 1,
                       "plane-mesh": 4}.items():
        t1, t2 = compare.parse_pair(pair)
        m = compare.pair_model(t1, t2).m
        for has_margin in (0, 1):
            assert mujoco.mj_maxContact(m, 0, 1, has_margin) == ncon, pair
        assert colliders.PORTED[(t1, t2)].ncon == ncon, pair
    assert convex.max_contacts(5, 6, int(mujoco.mjtDisableBit.mjDSBL_MULTICCD)) == 1


def test_unregistered_mesh_is_an_error():
    """A mesh collider without C's polygons must refuse, not guess."""
    m = compare.pair_model(*compare.parse_pair("box-mesh")).m
    convex._MESHES.clear()  # pylint: disable=protected-access
    with pytest.raises(KeyError, match="register_model"):
        convex._mesh_of(m, 0)  # pylint: disable=protected-access
    convex.register_model(m)
    assert convex._mesh_of(m, 0).polynum > 0  # pylint: disable=protected-access


# ----------------------------------------------------------------------------- gradients

C_VEC = jnp.array([0.3, -0.7, 0.5])
AXIS = jnp.array([0.2, 0.9, -0.4]) / jnp.linalg.norm(jnp.array([0.2, 0.9, -0.4]))


def _rot(th):
    k = jnp.array([[0.0, -AXIS[2], AXIS[1]], [AXIS[2], 0.0, -AXIS[0]], [-AXIS[1], AXIS[0], 0.0]])
    return jnp.eye(3) + jnp.sin(th) * k + (1.0 - jnp.cos(th)) * (k @ k)


def _objective(pair_fn, k1, k2):
    """Sum over active contacts of dist + pos . c, as geom 2 moves by x[:3] and turns by x[3]."""

    def f(x, pos, mat, size, margin):
        i1 = GeomInfo(pos[0], mat[0].reshape(9), size[0])
        i2 = GeomInfo(pos[1] + x[:3], (_rot(x[3]) @ mat[1]).reshape(9), size[1])
        dist, cpos, _ = pair_fn(i1, i2, margin, k1=k1, k2=k2)
        active = jax.lax.stop_gradient(dist < margin)
        return jnp.sum(jnp.where(active, dist + cpos @ C_VEC, 0.0))

    return f


def _poses(pair: str, n: int, seed: int):
    pm = compare.pair_model(*compare.parse_pair(pair))
    dr = compare.draw(pm, n, np.random.default_rng(seed), aligned_share=0.0, miss_share=0.0)
    m, d = pm.m, mujoco.MjData(pm.m)
    out = []
    for i in range(n):
        compare._set_sizes(m, dr.size[i], dr.rbound[i], dr.margin[i])  # pylint: disable=protected-access
        d.qpos[:] = dr.qpos[i]
        mujoco.mj_kinematics(m, d)
        out.append((d.geom_xpos.copy(), d.geom_xmat.copy().reshape(2, 3, 3), m.geom_size.copy(),
                    float(dr.margin[i].sum())))
    return pm, out


@pytest.mark.slow
# N.B. a GJK/EPA gradient takes about three minutes to compile on two cores: cylinder-box
# (GJK, EPA and the multi-contact rule) and capsule-cylinder (shrunk to a segment) cover the
# code paths; the degenerate poses reuse cylinder-box's compiled gradient (the persistent cache).
@pytest.mark.parametrize("pair", ["cylinder-box", "capsule-cylinder"])
def test_gradients_match_central_differences(pair):
    """Reverse-mode gradients equal central differences (eps 1e-6) on smooth pieces.

    N.B. GJK and EPA stop on a tolerance (1e-6), so their output is piecewise
    smooth with pieces that can be narrower than eps: a pose is used only where
    central differences at eps and 2 eps agree (both within one piece).
    """
    pm, poses = _poses(pair, 24, seed=3)
    fn = colliders.PORTED[compare.parse_pair(pair)].pair_fn
    f = _objective(fn, convex.kind_of(pm.m, 0), convex.kind_of(pm.m, 1))
    val = jax.jit(f)
    grad = jax.jit(jax.grad(f))
    x0 = jnp.zeros(4)
    checked = 0
    for pose in poses:
        args = tuple(jnp.asarray(a) for a in pose)
        g = np.asarray(grad(x0, *args))
        assert np.all(np.isfinite(g))
        fd = []
        for eps in (1e-6, 2e-6):
            e = np.eye(4) * eps
            fd.append(np.array([(float(val(x0 + e[k], *args)) - float(val(x0 - e[k], *args)))
                                / (2 * eps) for k in range(4)]))
        scale = np.maximum(np.abs(fd[0]), 1e-2)
        if np.max(np.abs(fd[0] - fd[1]) / scale) > 1e-6:
            continue  # a discontinuity within eps (another EPA face, a clipped vertex)
        np.testing.assert_allclose(g, fd[0], rtol=1e-5, atol=1e-5 * scale.max())
        checked += 1
    assert checked >= 8


def _parts(pair_fn, k1, k2):
    """(distance, position . c, normal . c) summed over active contacts, as `_objective` moves."""

    def f(x, pos, mat, size, margin):
        i1 = GeomInfo(pos[0], mat[0].reshape(9), size[0])
        i2 = GeomInfo(pos[1] + x[:3], (_rot(x[3]) @ mat[1]).reshape(9), size[1])
        dist, cpos, frame = pair_fn(i1, i2, margin, k1=k1, k2=k2)
        active = jax.lax.stop_gradient(dist < margin)
        return jnp.stack([jnp.sum(jnp.where(active, v, 0.0))
                          for v in (dist, cpos @ C_VEC, frame[:, 0] @ C_VEC)])

    return f


@pytest.mark.slow
@pytest.mark.parametrize("pair", ["box-mesh", "capsule-mesh"])
def test_converged_gradients_match_central_differences(pair):
    """`ccd.ccd_converged`'s rebuild: distance, position and normal each as C's differences.

    N.B. the sum `_objective` hides a wrong normal (it reads distances and
    positions only); a rebuild from material points alone missed positions and
    normals on cylinder-box poses by up to 100% (why cylinders keep `ccd.ccd`).
    """
    t1, t2 = compare.parse_pair(pair)
    assert {t1, t2} <= ccd.CONVERGED_KINDS
    pm, poses = _poses(pair, 24, seed=3)
    f = _parts(colliders.PORTED[(t1, t2)].pair_fn, convex.kind_of(pm.m, 0),
               convex.kind_of(pm.m, 1))
    val = jax.jit(f)
    jac = jax.jit(jax.jacrev(f))
    x0 = jnp.zeros(4)
    checked = 0
    for pose in poses:
        args = tuple(jnp.asarray(a) for a in pose)
        J = np.asarray(jac(x0, *args))
        fd = []
        for eps in (1e-6, 2e-6):
            e = np.eye(4) * eps
            fd.append(np.stack([(np.asarray(val(x0 + e[k], *args))
                                 - np.asarray(val(x0 - e[k], *args))) / (2 * eps)
                                for k in range(4)], axis=1))
        scale = np.maximum(np.abs(fd[0]), 1e-2)
        if np.max(np.abs(fd[0] - fd[1]) / scale) > 1e-6:
            continue  # a discontinuity within eps
        np.testing.assert_allclose(J, fd[0], rtol=1e-5, atol=1e-5 * scale.max())
        checked += 1
    assert checked >= 8


def _aligned(pair):
    """Degenerate poses: parallel faces, coaxial, coincident centers, exactly touching."""
    t1, t2 = compare.parse_pair(pair)
    size = np.array([[0.2, 0.1, 0.15], [0.2, 0.1, 0.15]])
    eye = np.eye(3)
    flip = np.diag([1.0, -1.0, -1.0])
    poses = []
    for p2, mat2 in ((np.array([0.0, 0.0, 0.15]), eye), (np.array([0.0, 0.0, 0.0]), eye),
                     (np.array([0.0, 0.0, 0.25]), flip), (np.array([0.1, 0.0, 0.2]), eye)):
        pos = np.stack([np.zeros(3), p2])
        poses.append((pos, np.stack([eye, mat2]), size, 0.0))
    return t1, t2, poses


@pytest.mark.slow
@pytest.mark.parametrize("pair", ["cylinder-box", "ellipsoid-ellipsoid"])
def test_gradients_finite_on_degenerate_poses(pair):
    t1, t2, poses = _aligned(pair)
    fn = colliders.PORTED[(t1, t2)].pair_fn
    grad = jax.jit(jax.grad(_objective(fn, gjk.Kind(t1), gjk.Kind(t2))))
    for pose in poses:
        g = np.asarray(grad(jnp.zeros(4), *(jnp.asarray(a) for a in pose)))
        assert np.all(np.isfinite(g)), (pose, g)
