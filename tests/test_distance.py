"""Signed distances between geoms, checked against mujoco.mj_geomDistance.

Comparisons with MuJoCo run in float64 (``jax.enable_x64`` as a context, so
they hold whatever precision the session runs in) to separate algorithmic
error from float32 rounding; a separate test bounds the float32 error.
"""

import functools
import zlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from mjstamp.scenes.distance import SUPPORTED_PAIRS, make_distance_fn, signed_distance

_SIZES = {
    "plane": "0 0 1",
    "sphere": "0.1",
    "capsule": "0.08 0.2",
    "ellipsoid": "0.1 0.15 0.2",
    "cylinder": "0.1 0.15",
    "box": "0.1 0.15 0.2",
}
_TYPES = {t: int(getattr(mujoco.mjtGeom, f"mjGEOM_{t.upper()}")) for t in _SIZES}
# The box of _SIZES as a mesh: mj_geomDistance takes it through MuJoCo's general
# convex path (GJK/EPA), an exact reference for capsule-box penetration, where
# MuJoCo's capsule-box primitive reports a shallower depth.
_BOX_MESH = (
    "-.1 -.15 -.2  .1 -.15 -.2  -.1 .15 -.2  .1 .15 -.2 "
    "-.1 -.15 .2  .1 -.15 .2  -.1 .15 .2  .1 .15 .2"
)
_DISTMAX = 10.0  # mj_geomDistance returns distmax beyond it; poses stay within 2 m
_N_POSES = 300


def _size(t: str) -> np.ndarray:
    v = [float(x) for x in _SIZES[t].split()]
    return np.pad(v, (0, 3 - len(v)))


def _model(*types: str) -> mujoco.MjModel:
    """One mocap body per geom g0, g1, ..., so that any pose can be set."""
    geoms = [
        'type="mesh" mesh="boxmesh"'
        if t == "mesh"
        else f'type="{t}" size="{_SIZES[t]}"'
        for t in types
    ]
    bodies = "".join(
        f'<body mocap="true"><geom name="g{i}" {g}/></body>'
        for i, g in enumerate(geoms)
    )
    return mujoco.MjModel.from_xml_string(
        f'<mujoco><asset><mesh name="boxmesh" vertex="{_BOX_MESH}"/></asset>'
        f"<worldbody>{bodies}</worldbody></mujoco>"
    )


def _random_poses(m: mujoco.MjModel, seed: int, *, same_pose: tuple[int, ...] = ()):
    """Random poses: geom_xpos (n, ngeom, 3) and geom_xmat (n, ngeom, 9).

    Centres are uniform in a 0.6 m cube, so with these 0.1-0.2 m shapes a fair
    share of poses penetrate (each test checks both sides are drawn). Mocap
    bodies listed in ``same_pose`` all take the pose of the first of them.
    """
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    xpos, xmat = [], []
    for _ in range(_N_POSES):
        d.mocap_pos = rng.uniform(-0.3, 0.3, (m.nmocap, 3))
        q = rng.normal(size=(m.nmocap, 4))
        d.mocap_quat = q / np.linalg.norm(q, axis=1, keepdims=True)
        for i in same_pose[1:]:
            d.mocap_pos[i] = d.mocap_pos[same_pose[0]]
            d.mocap_quat[i] = d.mocap_quat[same_pose[0]]
        mujoco.mj_kinematics(m, d)
        xpos.append(d.geom_xpos.copy())
        xmat.append(d.geom_xmat.copy())
    return np.array(xpos), np.array(xmat)


def _mj_distances(m, xpos, xmat, g1: int, g2: int) -> np.ndarray:
    """mj_geomDistance at each pose, (n,)."""
    d = mujoco.MjData(m)
    out = []
    for p, r in zip(xpos, xmat, strict=True):
        d.geom_xpos, d.geom_xmat = p, r
        out.append(mujoco.mj_geomDistance(m, d, g1, g2, _DISTMAX, None))
    return np.array(out)


def _distance_fn(m):
    """The jit(vmap) of make_distance_fn both ways round, g0-g1 and g1-g0.

    (n, ngeom, 3), (n, ngeom, 9) -> (n, 2): one compile for both orders.
    """
    ab, ba = make_distance_fn(m, "g0", "g1"), make_distance_fn(m, "g1", "g0")
    return jax.jit(jax.vmap(lambda p, r: jnp.stack([ab(p, r), ba(p, r)])))


def _ours(f, xpos, xmat) -> tuple[np.ndarray, np.ndarray]:
    """Evaluates f in the float width of the current x64 setting: (n,) twice."""
    dtype = jnp.float64 if jax.config.x64_enabled else jnp.float32
    out = np.asarray(f(jnp.asarray(xpos, dtype), jnp.asarray(xmat, dtype)))
    return out[:, 0], out[:, 1]


@functools.cache
def _pair_data(t1: str, t2: str):
    """Our jitted distances, poses and mj_geomDistance for a pair, shared."""
    m = _model(t1, t2)
    xpos, xmat = _random_poses(m, seed=zlib.crc32(f"{t1}-{t2}".encode()))
    return _distance_fn(m), xpos, xmat, _mj_distances(m, xpos, xmat, 0, 1)


# MuJoCo's collider is exact on both sides of contact for these (it returns
# minus the penetration depth when they overlap), and we agree to rounding
# (≤ 4e-16 seen); 1e-9 only keeps the test off the last bits.
EXACT_PAIRS = [
    ("plane", "sphere"),
    ("plane", "capsule"),
    ("plane", "ellipsoid"),
    ("plane", "cylinder"),
    ("plane", "box"),
    ("sphere", "sphere"),
    ("sphere", "capsule"),
    ("sphere", "cylinder"),
    ("sphere", "box"),
    ("capsule", "capsule"),
    ("box", "box"),
]


@pytest.mark.parametrize(("t1", "t2"), EXACT_PAIRS)
def test_matches_mj_geom_distance(t1, t2):
    """Exact pairs agree with MuJoCo on both sides of contact, either order."""
    f, xpos, xmat, ref = _pair_data(t1, t2)
    assert (ref > 0).sum() >= 30 and (ref < 0).sum() >= 30  # both sides of contact
    with jax.enable_x64(True):
        ours, swapped = _ours(f, xpos, xmat)
    np.testing.assert_allclose(ours, ref, atol=1e-9, rtol=0)
    np.testing.assert_allclose(swapped, ours, atol=1e-12, rtol=0)


def test_near_parallel_capsules_exact():
    """Nearly parallel axes: exact, where MuJoCo's own collider is off by 2e-6."""
    f, _, _, _ = _pair_data("capsule", "capsule")
    rng = np.random.default_rng(4)
    # Axis 1 along z; axis 2 offset by `gap` along x and tilted by θ about x,
    # so the axes' closest points are both centres and the distance is `gap`.
    theta = 10.0 ** rng.uniform(-8, -2, _N_POSES)
    gap = 10.0 ** rng.uniform(-4, -2, _N_POSES)
    xpos = np.zeros((_N_POSES, 2, 3))
    xpos[:, 1, 0] = gap
    c, s = np.cos(theta), np.sin(theta)
    xmat = np.zeros((_N_POSES, 2, 3, 3))
    xmat[:, 0] = np.eye(3)
    xmat[:, 1, 0, 0] = 1
    xmat[:, 1, 1:, 1:] = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    xmat = xmat.reshape(_N_POSES, 2, 9)
    with jax.enable_x64(True):
        ours, swapped = _ours(f, xpos, xmat)
    # Rounding of w, amplified by the near-parallel solve (5e-15 seen).
    np.testing.assert_allclose(ours, gap - 0.16, atol=1e-13, rtol=0)
    np.testing.assert_allclose(swapped, gap - 0.16, atol=1e-13, rtol=0)
    with jax.enable_x64(False):
        ours32, _ = _ours(f, xpos, xmat)
    # float32: 1 - (u₁·u₂)² cancels for θ below ~3e-4 (2e-6 seen).
    np.testing.assert_allclose(ours32, gap - 0.16, atol=5e-6, rtol=0)


def test_capsule_box_against_primitive_and_convex_paths():
    """Capsule-box is exact: MuJoCo's convex path agrees everywhere."""
    # g0 capsule, g1 box primitive, g2 the same box as a mesh at the same pose.
    m = _model("capsule", "box", "mesh")
    np.testing.assert_allclose(m.geom_pos[2], 0, atol=1e-12)  # mesh frame = box frame
    np.testing.assert_allclose(m.geom_quat[2], [1, 0, 0, 0], atol=1e-12)
    xpos, xmat = _random_poses(m, seed=3, same_pose=(1, 2))
    prim = _mj_distances(m, xpos, xmat, 0, 1)
    convex = _mj_distances(m, xpos, xmat, 0, 2)
    with jax.enable_x64(True):
        ours, sw = _ours(_distance_fn(m), xpos, xmat)
    sep, pen = convex > 0, convex < 0
    assert sep.sum() >= 30 and pen.sum() >= 30
    np.testing.assert_allclose(sw, ours, atol=1e-12, rtol=0)
    # Separated, or penetrating with the capsule's axis still outside the box
    # (d > -r): MuJoCo's primitive is exact there (3e-15 seen).
    axis_out = convex > -0.08 + 1e-4
    np.testing.assert_allclose(ours[axis_out], prim[axis_out], atol=1e-9, rtol=0)
    # Everywhere: the convex path (GJK when separated, EPA when penetrating,
    # which stops at ~1e-6: 6e-7 seen) agrees with our SAT depth.
    np.testing.assert_allclose(ours, convex, atol=5e-6, rtol=0)
    # Axis inside the box: the primitive is shallower than the true depth.
    assert np.all(prim[~axis_out] >= ours[~axis_out] - 1e-6)


def test_capsule_cylinder_against_mj():
    """Capsule-cylinder: exact until the axis enters, then a shallower bound."""
    f, xpos, xmat, ref = _pair_data("capsule", "cylinder")
    with jax.enable_x64(True):
        ours, sw = _ours(f, xpos, xmat)
    np.testing.assert_allclose(sw, ours, atol=1e-12, rtol=0)
    axis_out = ref > -0.08 + 1e-3  # separated, or the axis outside the cylinder
    assert (ref > 0).sum() >= 30 and (axis_out & (ref < 0)).sum() >= 30
    assert (~axis_out).sum() >= 15
    np.testing.assert_allclose(ours[axis_out], ref[axis_out], atol=1e-9, rtol=0)
    # Axis inside: ours is the deepest axis point, shallower than (or equal to)
    # the true depth. MuJoCo's EPA on the curved cylinder is itself off by up
    # to ~4e-5 (ours was that much deeper at worst), hence the slack.
    assert np.all(ours >= ref - 1e-4)
    np.testing.assert_array_equal(ours < 0, ref < 0)


# The pairs with cancellation-prone arithmetic: near-parallel segments,
# cross-product axes, the golden-section search, a cylinder's rim. The others
# are a dot product or a norm minus a radius (sphere-box runs in float32 in
# test_rollout_batch_under_jit_vmap_grad).
FLOAT32_PAIRS = [
    ("plane", "cylinder"),
    ("capsule", "capsule"),
    ("capsule", "cylinder"),
    ("capsule", "box"),
    ("box", "box"),
]


@pytest.mark.parametrize(("t1", "t2"), FLOAT32_PAIRS)
def test_float32_close_to_float64(t1, t2):
    """Float32 stays within rounding of float64."""
    f, xpos, xmat, _ = _pair_data(t1, t2)
    with jax.enable_x64(False):
        ours32 = np.stack(_ours(f, xpos, xmat))
    with jax.enable_x64(True):
        ours64 = np.stack(_ours(f, xpos, xmat))
    assert ours32.dtype == np.float32 and ours64.dtype == np.float64
    # float32 rounding of poses and of sums of ~0.3 m terms (≤ 9e-8 seen).
    np.testing.assert_allclose(ours32, ours64, atol=5e-7, rtol=0)


def _exp(w: jax.Array) -> jax.Array:
    """exp([w]×) to second order: exact enough for steps of 1e-6 around w = 0."""
    k = jnp.cross(jnp.eye(3), w)  # [w]×: row i is eᵢ × w
    return jnp.eye(3) + k + k @ k / 2


@functools.cache
def _derivatives(t1: str, t2: str):
    """The jit of (x, pose) -> (f, ∇ₓf): one compile serves every check.

    f(x, pose) is the signed distance with geom i moved to pos_i + Δpos_i and
    rotated to mat_i·exp([w_i]×), where x = (size1, Δpos1, w1, size2, Δpos2,
    w2) and pose = (pos1, mat1, pos2, mat2).
    N.B. rotations are perturbed through exp, not entry by entry: MJX's
    geom_xmat is always a rotation, and off SO(3) formulas that agree on it
    (a vertex-to-box and an edge-to-edge distance at a shared closest point)
    have different derivatives.
    """

    def f(x, pose):
        s1, dp1, w1, s2, dp2, w2 = x
        p1, r1, p2, r2 = pose
        return signed_distance(_TYPES[t1], s1, p1 + dp1, r1 @ _exp(w1),
                               _TYPES[t2], s2, p2 + dp2, r2 @ _exp(w2))  # fmt: skip

    return jax.jit(jax.value_and_grad(f))


def _pose_and_x(t1, t2, rng, spread):
    """Random float64 pose (pos1, mat1, pos2, mat2) and x at it (Δ = 0, w = 0)."""
    pose = []
    for _ in (t1, t2):
        q = rng.normal(size=4)
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, q / np.linalg.norm(q))
        pos = rng.uniform(-spread, spread, 3)
        pose += [jnp.asarray(pos), jnp.asarray(mat.reshape(3, 3))]
    z = jnp.zeros(3)
    return tuple(pose), (jnp.asarray(_size(t1)), z, z, jnp.asarray(_size(t2)), z, z)


@pytest.mark.parametrize(("t1", "t2"), SUPPORTED_PAIRS)
def test_gradients_match_central_differences(t1, t2):
    """The gradient along random directions against central differences.

    Only reverse mode is checked: it is what the SVGD score uses, and with no
    custom_jvp/custom_vjp rules in the module JAX's VJP is the transpose of its
    JVP by construction (a JVP check would double the compile time).
    """
    derivatives = _derivatives(t1, t2)
    rng = np.random.default_rng(7)
    eps = 1e-6
    with jax.enable_x64(True):
        seen = set()
        for _ in range(100):
            pose, x = _pose_and_x(t1, t2, rng, spread=0.3)
            xdot = tuple(jnp.asarray(rng.normal(size=3)) for _ in x)
            value, grad = derivatives(x, pose)
            value = float(value)  # f(x ± eps·ẋ) below reuse the same compile
            # Skip the kink at contact, where box-box and capsule-box switch
            # from the closest-feature formula to the separating-axis one.
            if (value > 0) in seen or abs(value) < 1e-3:
                continue
            seen.add(value > 0)
            plus = derivatives(jax.tree.map(lambda a, t: a + eps * t, x, xdot), pose)
            minus = derivatives(jax.tree.map(lambda a, t: a - eps * t, x, xdot), pose)
            fd = float(plus[0] - minus[0]) / (2 * eps)
            directional = sum(
                float(jnp.vdot(g, t)) for g, t in zip(grad, xdot, strict=True)
            )
            # Central differences: O(eps²) truncation plus 1e-16/eps rounding.
            np.testing.assert_allclose(directional, fd, atol=1e-7, rtol=1e-6)
            if len(seen) == 2:
                break
        assert seen == {True, False}, "no separated or no penetrating pose drawn"


@pytest.mark.parametrize(("t1", "t2"), SUPPORTED_PAIRS)
def test_finite_gradients_at_coincident_centres(t1, t2):
    """Finite value and gradient where norms and axes degenerate."""
    derivatives = _derivatives(t1, t2)
    with jax.enable_x64(True):
        (_, tilted, _, _), x = _pose_and_x(t1, t2, np.random.default_rng(0), 0.0)
        z, eye = jnp.zeros(3), jnp.eye(3)
        # Same centre with equal, then different, orientations: parallel axes
        # and edges, points on axes, a centre on the other's centre.
        for r2 in (eye, tilted):
            out = jax.tree.leaves(derivatives(x, (z, eye, z, r2)))
            assert all(np.all(np.isfinite(np.asarray(a))) for a in out), (t1, t2)


def test_rollout_batch_under_jit_vmap_grad():
    """Batched over particles and time; gradients flow before contact."""
    _, xpos, xmat, ref = _pair_data("sphere", "box")
    f = make_distance_fn(_model("sphere", "box"), "g0", "g1")
    # A (particles, time) batch, in MJX's (ngeom, 3, 3) rotation layout.
    xpos_b = jnp.asarray(xpos, jnp.float32).reshape(10, 30, 2, 3)
    xmat_b = jnp.asarray(xmat, jnp.float32).reshape(10, 30, 2, 3, 3)
    d = jax.jit(jax.vmap(jax.vmap(f)))(xpos_b, xmat_b)
    np.testing.assert_allclose(np.asarray(d).ravel(), ref, atol=2e-6, rtol=0)

    # A soft contact indicator over one trajectory has gradients before
    # contact (where MJX's contact distance has none) as well as in it.
    def soft_contact(xpos):
        return jnp.sum(jax.nn.sigmoid(-50.0 * jax.vmap(f)(xpos, xmat_b[0])))

    g = np.asarray(jax.jit(jax.grad(soft_contact))(xpos_b[0]))[:, 0]  # (30, 3)
    separated = ref[:30] > 0
    assert separated.any() and (~separated).any()
    assert np.all(np.isfinite(g))
    assert np.all(np.linalg.norm(g[separated], axis=1) > 0)


def test_unknown_geom_name_lists_valid_names():
    """Bad names or ids raise one-line errors that list the valid names."""
    m = _model("sphere", "box")
    with pytest.raises(ValueError, match=r"unknown geom 'nope'.*'g0', 'g1'") as e:
        make_distance_fn(m, "nope", "g1")
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="out of range"):
        make_distance_fn(m, 0, 5)
    with pytest.raises(ValueError, match="with itself"):
        make_distance_fn(m, "g0", 0)


def test_unsupported_pair_names_both_geoms():
    """An unsupported pair names both geoms, their types, and what works."""
    m = mujoco.MjModel.from_xml_string("""
    <mujoco><asset>
      <mesh name="tet" vertex="0 0 0  1 0 0  0 1 0  0 0 1"/>
      <hfield name="hf" nrow="2" ncol="2" size="1 1 0.1 0.1"/>
    </asset><worldbody>
      <geom name="bar" type="hfield" hfield="hf"/>
      <body><geom name="foo" type="mesh" mesh="tet"/></body>
    </worldbody></mujoco>""")
    with pytest.raises(ValueError) as e:
        make_distance_fn(m, "foo", "bar")
    msg = str(e.value)
    assert msg.startswith(
        "signed distance between 'mesh' geom 'foo' and 'hfield' geom 'bar' "
        "is not supported; supported pairs: plane-sphere, "
    )
    assert "\n" not in msg
    with pytest.raises(ValueError, match="'ellipsoid' and 'box' is not supported"):
        signed_distance(
            _TYPES["ellipsoid"], np.ones(3), np.zeros(3), np.eye(3),
            _TYPES["box"], np.ones(3), np.zeros(3), np.eye(3),
        )  # fmt: skip
