"""Signed distances between geoms, checked against mujoco.mj_geomDistance.

Comparisons with MuJoCo run in float64 (``jax.enable_x64`` as a context, so
they hold whatever precision the session runs in) to separate algorithmic
error from float32 rounding; a separate test bounds the float32 error.
Every geom pair MJX collides is covered: one compiled distance function (both
orders) per pair serves its comparisons, and one compiled value-and-gradient
function serves its gradient checks.
"""

import functools
import zlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from mjstamp.distance import SUPPORTED_PAIRS, make_distance_fn, signed_distance

_SIZES = {
    "plane": "0 0 1",
    "sphere": "0.1",
    "capsule": "0.08 0.2",
    "ellipsoid": "0.1 0.15 0.2",
    "cylinder": "0.1 0.15",
    "box": "0.1 0.15 0.2",
}
_TYPES = {t: int(getattr(mujoco.mjtGeom, f"mjGEOM_{t.upper()}")) for t in _SIZES}
_TYPES.update(mesh=int(mujoco.mjtGeom.mjGEOM_MESH), hfield=int(mujoco.mjtGeom.mjGEOM_HFIELD))
# The box of _SIZES as a mesh: mj_geomDistance takes it through MuJoCo's general
# convex path (GJK/EPA), an exact reference for capsule-box penetration, where
# MuJoCo's capsule-box primitive reports a shallower depth.
_BOX_MESH = (
    "-.1 -.15 -.2  .1 -.15 -.2  -.1 .15 -.2  .1 .15 -.2 "
    "-.1 -.15 .2  .1 -.15 .2  -.1 .15 .2  .1 .15 .2"
)
# "mesh" in the tests: 14 points on an ellipsoid, whose hull has 24 triangles.
_ROCK = np.random.default_rng(123).normal(size=(14, 3))
_ROCK = _ROCK / np.linalg.norm(_ROCK, axis=1, keepdims=True) * [0.12, 0.16, 0.2]
# A 4x4-cell height field, 1 m x 0.75 m, 0.25 m high on a 0.125 m base: grid
# steps, heights and base are binary fractions, so its prisms are exact as
# float32 mesh vertices (up to MuJoCo recentring each mesh).
_HFIELD = dict(nrow=5, ncol=5, size="0.5 0.375 0.25 0.125")
_ELEVATION = np.random.default_rng(5).uniform(0, 1, 25).round(3)
_DISTMAX = 10.0  # mj_geomDistance returns distmax beyond it; poses stay within 2 m
_N_POSES = 300
_N_GRAD = 32  # poses per batch of _derivatives: one shape, so one compile per pair
# N.B. MuJoCo's CCD (GJK/EPA, which mj_geomDistance uses for ellipsoids,
# cylinders, meshes and prisms) errs by up to 1e-6 at its default tolerance,
# and below it GJK on curved shapes fails outright at some poses (2.6e-4 seen
# for ellipsoids at 1e-12). Curved pairs are compared with the closer of the
# two (see test_curved_pairs_match_mj_ccd); 1000 iterations let EPA converge.
_CCD = '<option ccd_iterations="1000"/>'
def _size(t: str) -> np.ndarray:
    v = [float(x) for x in _SIZES[t].split()]
    return np.pad(v, (0, 3 - len(v)))


def _model(*types: str, elevation: np.ndarray = _ELEVATION, hfield=_HFIELD) -> mujoco.MjModel:
    """One mocap body per geom g0, g1, ..., so that any pose can be set.

    Types are _SIZES keys, "mesh" (the rock), "boxmesh" (the box as a mesh) or
    "hfield".
    """
    special = {
        "mesh": 'type="mesh" mesh="rock"',
        "boxmesh": 'type="mesh" mesh="boxmesh"',
        "hfield": 'type="hfield" hfield="hf"',
    }
    geoms = [special.get(t) or f'type="{t}" size="{_SIZES[t]}"' for t in types]
    bodies = "".join(
        f'<body mocap="true"><geom name="g{i}" {g}/></body>'
        for i, g in enumerate(geoms)
    )
    rock = " ".join(f"{x:.6f}" for x in _ROCK.ravel())
    hf = " ".join(f'{k}="{v}"' for k, v in hfield.items())
    return mujoco.MjModel.from_xml_string(
        f'<mujoco>{_CCD}<asset><mesh name="boxmesh" vertex="{_BOX_MESH}"/>'
        f'<mesh name="rock" vertex="{rock}"/>'
        f'<hfield name="hf" {hf} elevation="{" ".join(map(str, elevation))}"/></asset>'
        f"<worldbody>{bodies}</worldbody></mujoco>"
    )


def _random_poses(m: mujoco.MjModel, seed: int, *, same_pose: tuple[int, ...] = ()):
    """Random poses: geom_xpos (n, ngeom, 3) and geom_xmat (n, ngeom, 9).

    Centres are uniform in a 0.6 m cube, so with these 0.1-0.2 m shapes a fair
    share of poses penetrate (each test checks both sides are drawn). Mocap
    bodies listed in ``same_pose`` all take the pose of the first of them. A
    height field stays at the origin, unrotated (so its prisms can be built as
    meshes in the world), with the other geoms over it, from 0.1 m under its
    top to 0.2 m above.
    """
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    hfield = m.geom_type == mujoco.mjtGeom.mjGEOM_HFIELD
    xpos, xmat = [], []
    for _ in range(_N_POSES):
        d.mocap_pos = rng.uniform(-0.3, 0.3, (m.nmocap, 3))
        q = rng.normal(size=(m.nmocap, 4))
        d.mocap_quat = q / np.linalg.norm(q, axis=1, keepdims=True)
        for i in same_pose[1:]:
            d.mocap_pos[i] = d.mocap_pos[same_pose[0]]
            d.mocap_quat[i] = d.mocap_quat[same_pose[0]]
        if hfield.any():
            d.mocap_pos[hfield], d.mocap_quat[hfield] = 0.0, [1, 0, 0, 0]
            d.mocap_pos[~hfield] = rng.uniform([-0.55, -0.45, 0.0], [0.55, 0.45, 0.45])
        mujoco.mj_kinematics(m, d)
        xpos.append(d.geom_xpos.copy())
        xmat.append(d.geom_xmat.copy())
    return np.array(xpos), np.array(xmat)


def _mj_distances(m, xpos, xmat, g1: int, g2: int, distmax=_DISTMAX) -> np.ndarray:
    """mj_geomDistance at each pose, (n,)."""
    d = mujoco.MjData(m)
    out = []
    for p, r in zip(xpos, xmat, strict=True):
        d.geom_xpos, d.geom_xmat = p, r
        out.append(mujoco.mj_geomDistance(m, d, g1, g2, distmax, None))
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
def _poses(t1: str, t2: str):
    """The model of a pair and its random poses, shared."""
    m = _model(t1, t2)
    return (m, *_random_poses(m, seed=zlib.crc32(f"{t1}-{t2}".encode())))


@functools.cache
def _pair_data(t1: str, t2: str):
    """Our jitted distances, poses and mj_geomDistance for a pair, shared."""
    m, xpos, xmat = _poses(t1, t2)
    return _distance_fn(m), xpos, xmat, _mj_distances(m, xpos, xmat, 0, 1)


def _batched(t1: str, t2: str, xpos, xmat, *, swap: bool = False) -> np.ndarray:
    """Our distances at poses (n, 2, 3), (n, 2, 9), through _derivatives: (n,).

    In batches of _N_GRAD, so the pair's one compiled value-and-gradient
    function (shared with the gradient tests) serves; in the float width of
    the current x64 setting. `swap` exchanges the two geoms' poses (for pairs
    of one type: the distance the other way round).
    """
    dtype = jnp.float64 if jax.config.x64_enabled else jnp.float32
    n = len(xpos)
    idx = np.concatenate([np.arange(n), np.full(-n % _N_GRAD, n - 1)])
    p, r = xpos[idx], xmat[idx].reshape(-1, 2, 3, 3)
    if swap:
        p, r = p[:, ::-1], r[:, ::-1]
    _, x = _poses_and_x(t1, t2, np.random.default_rng(0), _N_GRAD, 0.0)
    out = []
    for k in range(0, len(p), _N_GRAD):
        pose = tuple(jnp.asarray(a[k : k + _N_GRAD, i], dtype) for i in (0, 1) for a in (p, r))
        out.append(np.asarray(_derivatives(t1, t2)(x, pose)[0]))
    return np.concatenate(out)[:n]


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
    m = _model("capsule", "box", "boxmesh")
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


# Meshes collide by their convex hulls. MuJoCo's CCD converges on polytopes
# (EPA terminates on a face), once its tolerance is tight enough for a sphere
# or capsule partner (at 1e-6, 2e-7 off seen); we agree to 4e-13.
POLYTOPE_PAIRS = [
    ("plane", "mesh"),
    ("sphere", "mesh"),
    ("capsule", "mesh"),
    ("box", "mesh"),
    ("mesh", "mesh"),
]


@pytest.mark.parametrize(("t1", "t2"), POLYTOPE_PAIRS)
def test_mesh_pairs_match_mj_geom_distance(t1, t2):
    """Mesh pairs agree with MuJoCo's convex-hull collider on both sides."""
    m, xpos, xmat = _poses(t1, t2)
    m.opt.ccd_tolerance = 1e-12
    ref = _mj_distances(m, xpos, xmat, 0, 1)
    assert (ref > 0).sum() >= 30 and (ref < 0).sum() >= 30
    with jax.enable_x64(True):
        ours = _batched(t1, t2, xpos, xmat)
        if t1 == t2:
            swapped = _batched(t1, t2, xpos, xmat, swap=True)
            np.testing.assert_allclose(swapped, ours, atol=1e-12, rtol=0)
    np.testing.assert_allclose(ours, ref, atol=1e-9, rtol=0)


CURVED_PAIRS = [
    ("sphere", "ellipsoid"),
    ("capsule", "ellipsoid"),
    ("ellipsoid", "ellipsoid"),
    ("ellipsoid", "cylinder"),
    ("cylinder", "cylinder"),
]


def _support(t: str, mat: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Support function h(n) (k,) of a sphere, capsule, ellipsoid or cylinder."""
    s = _size(t)
    nl = n @ mat  # (k, 3) local directions
    if t == "ellipsoid":
        return np.linalg.norm(s * nl, axis=1)
    if t == "cylinder":
        return s[0] * np.linalg.norm(nl[:, :2], axis=1) + s[1] * np.abs(nl[:, 2])
    return s[0] + (s[1] * np.abs(nl[:, 2]) if t == "capsule" else 0.0)


@pytest.mark.parametrize(("t1", "t2"), CURVED_PAIRS)
def test_curved_pairs_match_mj_ccd(t1, t2):
    """Ellipsoid and cylinder pairs agree with MuJoCo's CCD to its accuracy.

    The reference is the closer of two CCD runs: ccd_tolerance 1e-6 (GJK at its
    best; EPA stops within 1e-6) and 1e-12 (EPA converged; GJK sometimes fails).
    Where both disagreed with ours by more than 1e-9, a brute-force
    maximization of the gap over directions sided with ours to 1e-15 at every
    pose checked (see distance.py). Independently, no direction of a dense
    sample gives a wider gap |n·(c₂ - c₁)| - h₁(n) - h₂(n) than ours: the
    direction search did not miss the optimum.
    """
    m, xpos, xmat = _poses(t1, t2)
    coarse = _mj_distances(m, xpos, xmat, 0, 1)
    m.opt.ccd_tolerance = 1e-12
    fine = _mj_distances(m, xpos, xmat, 0, 1)
    assert (coarse > 0).sum() >= 30 and (coarse < 0).sum() >= 30
    with jax.enable_x64(True):
        ours = _batched(t1, t2, xpos, xmat)
        if t1 == t2:
            swapped = _batched(t1, t2, xpos, xmat, swap=True)
            np.testing.assert_allclose(swapped, ours, atol=1e-12, rtol=0)
    err = np.minimum(np.abs(ours - coarse), np.abs(ours - fine))
    assert err.max() < 1e-6, err.max()  # MuJoCo's tolerance; 3e-7 seen (ours exact there)
    assert np.median(err) < 1e-11, np.median(err)
    dirs = np.random.default_rng(0).normal(size=(20000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rot = xmat.reshape(-1, 2, 3, 3)
    for k in range(0, _N_POSES, 10):
        gap = np.abs(dirs @ (xpos[k, 1] - xpos[k, 0]))
        gap -= _support(t1, rot[k, 0], dirs) + _support(t2, rot[k, 1], dirs)
        assert gap.max() <= ours[k] + 1e-12, (k, gap.max(), ours[k])


@functools.cache
def _prism_reference(t: str):
    """Min over the height field's 32 prisms, each a mesh, of mj_geomDistance.

    MuJoCo's own definition of a height field's distance, at any distance
    (mj_geomDistance on the height field itself gives up beyond distmax and,
    with a large distmax, misreports penetration: see distance.py).
    """
    m = _model("hfield", t)
    nrow, ncol = m.hfield_nrow[0], m.hfield_ncol[0]
    sx, sy, sz, base = m.hfield_size[0]
    z = m.hfield_data.reshape(nrow, ncol).astype(float) * sz
    corner = lambda c, r: (2 * sx * c / (ncol - 1) - sx, 2 * sy * r / (nrow - 1) - sy, z[r, c])  # noqa: E731
    meshes = []
    for r in range(nrow - 1):
        for c in range(ncol - 1):
            for tri in (((c, r + 1), (c, r), (c + 1, r + 1)), ((c, r), (c + 1, r + 1), (c + 1, r))):
                top = [corner(*v) for v in tri]
                verts = top + [(x, y, -base) for x, y, _ in top]
                meshes.append(" ".join(f"{x:.17g}" for v in verts for x in v))
    geom = f'type="{t}" size="{_SIZES[t]}"' if t in _SIZES else 'type="mesh" mesh="rock"'
    rock = " ".join(f"{x:.6f}" for x in _ROCK.ravel())
    mp = mujoco.MjModel.from_xml_string(
        f'<mujoco>{_CCD}<asset><mesh name="rock" vertex="{rock}"/>'
        + "".join(f'<mesh name="p{i}" vertex="{v}"/>' for i, v in enumerate(meshes))
        + '</asset><worldbody><body mocap="true"><geom name="other" ' + geom + "/></body>"
        + "".join(f'<geom type="mesh" mesh="p{i}"/>' for i in range(len(meshes)))
        + "</worldbody></mujoco>"
    )
    mp.opt.ccd_tolerance = 1e-12
    _, xpos, xmat = _poses("hfield", t)
    d = mujoco.MjData(mp)
    mujoco.mj_kinematics(mp, d)
    other = mp.geom("other").id  # world-body geoms (the prisms) come first
    out = []
    for p, r in zip(xpos, xmat, strict=True):
        d.geom_xpos[other], d.geom_xmat[other] = p[1], r[1]
        out.append(min(mujoco.mj_geomDistance(mp, d, other, g, _DISTMAX, None)
                       for g in range(mp.ngeom) if g != other))  # fmt: skip
    return np.array(out)


HFIELD_PAIRS = [("hfield", "sphere"), ("hfield", "capsule"), ("hfield", "box"), ("hfield", "mesh")]


@pytest.mark.parametrize(("t1", "t2"), HFIELD_PAIRS)
def test_hfield_pairs_match_mj(t1, t2):
    """Height-field pairs: the minimum over prisms, as MuJoCo collides them."""
    m, xpos, xmat = _poses(t1, t2)
    m.opt.ccd_tolerance = 1e-12
    # N.B. MuJoCo raises each prism's top by the margin it is given, so a
    # small distmax keeps its penetration depths right (as in simulation),
    # and it reports distmax beyond.
    near = _mj_distances(m, xpos, xmat, 0, 1, distmax=0.05)
    prisms = _prism_reference(t2)
    with jax.enable_x64(True):
        ours = _batched(t1, t2, xpos, xmat)
    close = near < 0.05 - 1e-9
    assert (near[close] > 0).sum() >= 10 and (near < 0).sum() >= 30 and (prisms > 0.05).sum() >= 30
    np.testing.assert_allclose(ours[close], near[close], atol=1e-9, rtol=0)  # ≤ 7e-13 seen
    # Everywhere, to the float32 rounding of MuJoCo's recentred prism meshes.
    np.testing.assert_allclose(ours, prisms, atol=1e-7, rtol=0)  # ≤ 1e-8 seen


def test_hfield_window_exact_near_contact():
    """A fine height field: only prisms near the geom are searched.

    The window covers 2·rbound around the geom's centre, so the distance is
    exact while it is at most rbound (beyond, it may be larger).
    """
    n = 17
    elevation = np.random.default_rng(11).uniform(0, 1, n * n).round(3)
    hfield = dict(nrow=n, ncol=n, size="0.5 0.375 0.25 0.125")
    fine = _model("hfield", "sphere", elevation=elevation, hfield=hfield)
    # The reference: the same model with the sphere's rbound so large that the
    # window is the whole grid.
    whole = _model("hfield", "sphere", elevation=elevation, hfield=hfield)
    whole.geom_rbound[1] = 10.0
    xpos, xmat = _random_poses(fine, seed=12)
    with jax.enable_x64(True):
        f = jax.jit(jax.vmap(make_distance_fn(fine, "g0", "g1")))
        ours = np.asarray(f(xpos, xmat))
        ref = np.asarray(jax.jit(jax.vmap(make_distance_fn(whole, "g0", "g1")))(xpos, xmat))
    near = ref <= 0.1  # the sphere's rbound
    assert near.sum() >= 100 and (~near).sum() >= 30 and (ref < 0).sum() >= 30
    np.testing.assert_array_equal(ours[near], ref[near])
    assert np.all(ours >= ref)


# The pairs with cancellation-prone arithmetic: near-parallel segments,
# cross-product axes, the golden-section search, a cylinder's rim, the
# direction search. The others are a dot product or a norm minus a radius
# (sphere-box runs in float32 in test_rollout_batch_under_jit_vmap_grad), or
# the same polytope arithmetic as box-box (meshes, height-field prisms).
FLOAT32_PAIRS = [
    ("plane", "cylinder"),
    ("capsule", "capsule"),
    ("capsule", "cylinder"),
    ("capsule", "box"),
    ("box", "box"),
    ("ellipsoid", "cylinder"),  # the direction search, to float32 resolution
]


@pytest.mark.parametrize(("t1", "t2"), FLOAT32_PAIRS)
def test_float32_close_to_float64(t1, t2):
    """Float32 stays within rounding of float64."""
    _, xpos, xmat = _poses(t1, t2)
    with jax.enable_x64(False):
        ours32 = _batched(t1, t2, xpos, xmat)
    with jax.enable_x64(True):
        ours64 = _batched(t1, t2, xpos, xmat)
    assert ours32.dtype == np.float32 and ours64.dtype == np.float64
    # float32 rounding of poses and of sums of ~0.3 m terms (≤ 9e-8 seen).
    np.testing.assert_allclose(ours32, ours64, atol=5e-7, rtol=0)


def _exp(w: jax.Array) -> jax.Array:
    """exp([w]×) to second order: exact enough for steps of 1e-6 around w = 0."""
    k = jnp.cross(jnp.eye(3), w)  # [w]×: row i is eᵢ × w
    return jnp.eye(3) + k + k @ k / 2


@functools.cache
def _derivatives(t1: str, t2: str):
    """The jit(vmap) of (x, pose) -> (f, ∇ₓf): one compile serves every check.

    f(x, pose) is the signed distance with geom i moved to pos_i + Δpos_i and
    rotated to mat_i·exp([w_i]×), where x = (size1, Δpos1, w1, size2, Δpos2,
    w2) and pose = (pos1, mat1, pos2, mat2), batched over a leading axis.
    Primitive pairs go through signed_distance (so sizes are differentiated
    too); mesh and height-field pairs, which need model data, through
    make_distance_fn (their size entries are unused).
    N.B. rotations are perturbed through exp, not entry by entry: MJX's
    geom_xmat is always a rotation, and off SO(3) formulas that agree on it
    (a vertex-to-box and an edge-to-edge distance at a shared closest point)
    have different derivatives.
    """
    if t1 in _SIZES and t2 in _SIZES:

        def f(x, pose):
            s1, dp1, w1, s2, dp2, w2 = x
            p1, r1, p2, r2 = pose
            return signed_distance(_TYPES[t1], s1, p1 + dp1, r1 @ _exp(w1),
                                   _TYPES[t2], s2, p2 + dp2, r2 @ _exp(w2))  # fmt: skip

    else:
        distance = make_distance_fn(_model(t1, t2), "g0", "g1")

        def f(x, pose):
            _, dp1, w1, _, dp2, w2 = x
            p1, r1, p2, r2 = pose
            return distance(
                jnp.stack([p1 + dp1, p2 + dp2]), jnp.stack([r1 @ _exp(w1), r2 @ _exp(w2)])
            )

    return jax.jit(jax.vmap(jax.value_and_grad(f)))


def _poses_and_x(t1, t2, rng, n, spread):
    """Random float64 poses (pos1, mat1, pos2, mat2), n of each, and x (Δ = 0, w = 0).

    A height field stays at the origin with the other geom over it, as in
    _random_poses.
    """
    pose = []
    for t in (t1, t2):
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        mat = np.zeros((n, 9))
        for k in range(n):
            mujoco.mju_quat2Mat(mat[k], q[k])
        pos = rng.uniform(-spread, spread, (n, 3))
        if t == "hfield":
            pos, mat = np.zeros((n, 3)), np.tile(np.eye(3).ravel(), (n, 1))
        elif "hfield" in (t1, t2):
            pos = rng.uniform([-0.55, -0.45, 0.0], [0.55, 0.45, 0.45], (n, 3)) * (spread > 0)
        pose += [jnp.asarray(pos), jnp.asarray(mat.reshape(n, 3, 3))]
    z = jnp.zeros((n, 3))
    sizes = [jnp.tile(_size(t) if t in _SIZES else np.zeros(3), (n, 1)) for t in (t1, t2)]
    return tuple(pose), (sizes[0], z, z, sizes[1], z, z)


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
        pose, x = _poses_and_x(t1, t2, rng, _N_GRAD, spread=0.3)
        xdot = tuple(jnp.asarray(rng.normal(size=a.shape)) for a in x)
        value, grad = derivatives(x, pose)
        plus, _ = derivatives(jax.tree.map(lambda a, t: a + eps * t, x, xdot), pose)
        minus, _ = derivatives(jax.tree.map(lambda a, t: a - eps * t, x, xdot), pose)
        value, fd = np.asarray(value), np.asarray(plus - minus) / (2 * eps)
        directional = sum(
            np.sum(np.asarray(g * t), axis=1) for g, t in zip(grad, xdot, strict=True)
        )
    # Skip the kink at contact, where box-box and capsule-box switch from the
    # closest-feature formula to the separating-axis one.
    keep = np.abs(value) > 1e-3
    assert (value[keep] > 0).any() and (value[keep] < 0).any(), "one side of contact undrawn"
    # Central differences: O(eps²) truncation plus 1e-16/eps rounding.
    np.testing.assert_allclose(directional[keep], fd[keep], atol=1e-7, rtol=1e-6)


def _contact_scale(derivatives, pose, x):
    """Per pose, the s at which geom 2's centre at s·pos2 touches geom 1 (at 0).

    By bisection: at s = 0 the centres coincide, so the geoms penetrate.
    """
    p1, r1, p2, r2 = pose
    lo, hi = np.zeros(len(p2)), np.full(len(p2), 20.0)
    for _ in range(45):  # 20·2⁻⁴⁵ = 6e-13
        mid = (lo + hi) / 2
        d, _ = derivatives(x, (p1, r1, p2 * mid[:, None], r2))
        inside = np.asarray(d) < 0
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return (lo + hi) / 2


@pytest.mark.parametrize(("t1", "t2"), SUPPORTED_PAIRS)
def test_finite_gradients_where_geometry_degenerates(t1, t2):
    """Finite value and gradient at contact, deep inside and at shared centres.

    Same centre with equal, then different, orientations (parallel axes and
    edges, points on axes, a centre on the other's centre); centres 1e-9 apart;
    and exactly at contact along random directions.
    """
    derivatives = _derivatives(t1, t2)
    with jax.enable_x64(True):
        (_, tilted, _, _), x = _poses_and_x(t1, t2, np.random.default_rng(0), _N_GRAD, 0.0)
        z, eye = jnp.zeros((_N_GRAD, 3)), jnp.tile(jnp.eye(3), (_N_GRAD, 1, 1))
        cases = [(z, eye, z, eye), (z, eye, z, tilted), (z, tilted, z + 1e-9, tilted)]
        if t1 != "plane":  # a plane's "centre" is any point of it: no contact scale
            pose, x = _poses_and_x(t1, t2, np.random.default_rng(1), _N_GRAD, 0.3)
            p1, r1, p2, r2 = pose
            s = _contact_scale(derivatives, (z, r1, p2 - p1, r2), x)
            cases.append((z, r1, (p2 - p1) * s[:, None], r2))
        for pose in cases:
            out = jax.tree.leaves(derivatives(x, pose))
            assert all(np.all(np.isfinite(np.asarray(a))) for a in out), (t1, t2)
        if t1 != "plane":
            value, _ = derivatives(x, cases[-1])
            np.testing.assert_allclose(np.asarray(value), 0.0, atol=1e-12)


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
    </asset><worldbody>
      <geom name="bar" type="box" size="1 1 1"/>
      <body><geom name="foo" type="cylinder" size="1 1"/></body>
      <body><geom name="tet" type="mesh" mesh="tet"/></body>
    </worldbody></mujoco>""")
    with pytest.raises(ValueError) as e:
        make_distance_fn(m, "foo", "bar")
    msg = str(e.value)
    assert msg.startswith(
        "signed distance between 'cylinder' geom 'foo' and 'box' geom 'bar' "
        "is not supported; supported pairs: plane-sphere, "
    )
    assert "\n" not in msg
    # MJX collides 27 pairs, and so many are supported.
    assert len(SUPPORTED_PAIRS) == 27 and ("mesh", "mesh") in SUPPORTED_PAIRS
    with pytest.raises(ValueError, match="'ellipsoid' and 'box' is not supported"):
        signed_distance(
            _TYPES["ellipsoid"], np.ones(3), np.zeros(3), np.eye(3),
            _TYPES["box"], np.ones(3), np.zeros(3), np.eye(3),
        )  # fmt: skip
    # A mesh needs its vertices, which only the model has.
    with pytest.raises(ValueError, match="needs the model's 'mesh' data; use make_distance_fn"):
        signed_distance(
            _TYPES["sphere"], np.ones(3), np.zeros(3), np.eye(3),
            _TYPES["mesh"], np.ones(3), np.zeros(3), np.eye(3),
        )  # fmt: skip
