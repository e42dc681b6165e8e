"""Contacts of the gradient model against MuJoCo C's, pair by pair.

MJX's own tests compare MJX against the C engine field by field; this does the
same for collisions. For two geom types it builds a model of two geoms (the
first on a free body, or a world plane; the second on a free body), draws
random sizes, relative poses and margins around contact (penetrating, touching,
separated by less than the margin, and a few clear misses), and collides each
draw twice: MuJoCo C (`mj_kinematics` + `mj_collision`, the contacts a C step
builds its constraints from) and MJX (`mjx.kinematics` + `mjx.collision`, with
whatever collision table is installed: MJX's own, or mjstamp's
`contacts.patch_collisions`). A contact counts when it enters the constraint
problem: C's ``exclude == 0``, MJX's ``dist < includemargin``. Per draw, the two
sets are matched by position (an optimal assignment) and compared field by
field: distance, position, normal and frame (the normal and both tangents).

Used by tests/test_contacts.py (a few hundred draws per pair) and
benchmarks/perf/contacts.py (10,000 or more per pair).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from scipy.optimize import linear_sum_assignment

from mjstamp._mjx import mjx, model_bytes

T = mujoco.mjtGeom
NAMES = {i: T(i).name.removeprefix("mjGEOM_").lower() for i in range(int(T.mjNGEOMTYPES))}

# A mesh the pairs with meshes use: a tetrahedron-like wedge (8 vertices) and a
# convex hull of a few points; shapes a user writes as meshes.
_MESH = """
<asset>
  <mesh name="wedge" vertex="-0.2 -0.15 -0.1  0.2 -0.15 -0.1  -0.2 0.15 -0.1  0.2 0.15 -0.1
                             -0.2 -0.05 0.1  0.2 -0.05 0.1  -0.2 0.05 0.1  0.2 0.05 0.1"/>
</asset>
"""


def pair_name(t1: int, t2: int) -> str:
    """'box-box', 'plane-cylinder': types in mjtGeom order."""
    t1, t2 = sorted((int(t1), int(t2)))
    return f"{NAMES[t1]}-{NAMES[t2]}"


def parse_pair(name: str) -> tuple[int, int]:
    """Inverse of `pair_name`; the types in mjtGeom order."""
    valid = {v: k for k, v in NAMES.items()}
    parts = name.split("-")
    if len(parts) != 2 or any(p not in valid for p in parts):
        raise ValueError(f"geom pair {name!r}; valid: TYPE-TYPE with TYPE one of "
                         f"{', '.join(sorted(valid))}")
    a, b = sorted(valid[p] for p in parts)
    return a, b


def _geom_xml(name: str, t: int) -> str:
    kind = NAMES[t]
    if kind == "mesh":
        return f'<geom name="{name}" type="mesh" mesh="wedge"/>'
    # N.B. compiled at the largest size drawn, so C's bounding boxes (geom_aabb,
    # which its broad phase reads) stay conservative when the sizes shrink.
    size = {"sphere": "0.6", "capsule": "0.6 0.6", "ellipsoid": "0.6 0.6 0.6",
            "cylinder": "0.6 0.6", "box": "0.6 0.6 0.6"}[kind]
    return f'<geom name="{name}" type="{kind}" size="{size}"/>'


@dataclasses.dataclass(frozen=True)
class PairModel:
    """A two-geom model for one pair of types.

    Attributes:
      t1, t2: the geom types, in mjtGeom order (as both engines order a pair).
      m: the MjModel; geom 0 is `t1` (a world plane, or on free body 1), geom 1
        is `t2` on the last free body.
      xml: its MJCF.
    """

    t1: int
    t2: int
    m: mujoco.MjModel
    xml: str

    @property
    def name(self) -> str:
        """'box-box'."""
        return pair_name(self.t1, self.t2)

    @property
    def plane(self) -> bool:
        """Whether the first geom is a (world) plane."""
        return NAMES[self.t1] == "plane"


def pair_model(t1: int, t2: int, *, flags: str = "") -> PairModel:
    """The model of `PairModel` for types t1, t2 (any order).

    Args:
      t1: a geom type (mjtGeom).
      t2: the other.
      flags: extra attributes of <option><flag .../></option>, e.g.
        'multiccd="disable"'.
    """
    t1, t2 = sorted((int(t1), int(t2)))
    if NAMES[t2] == "plane":
        raise ValueError("plane-plane is not collided")
    if NAMES[t1] == "plane":
        first = '<geom name="g1" type="plane" size="0 0 1"/>'
    else:
        first = f'<body name="b1"><freejoint/>{_geom_xml("g1", t1)}</body>'
    xml = f"""
<mujoco model="{pair_name(t1, t2)}">
  <option gravity="0 0 0"><flag {flags}/></option>
  {_MESH}
  <worldbody>
    {first}
    <body name="b2"><freejoint/>{_geom_xml("g2", t2)}</body>
  </worldbody>
</mujoco>"""
    return PairModel(t1, t2, mujoco.MjModel.from_xml_string(xml), xml)


@dataclasses.dataclass(frozen=True)
class Draws:
    """Random sizes, poses and margins of a pair (n draws).

    Attributes:
      size: (n, 2, 3) geom sizes (a mesh's and a plane's are the model's).
      rbound: (n, 2) bounding radii of those sizes.
      margin: (n, 2) geom margins.
      qpos: (n, nq) free-joint positions of the model's bodies.
      target: (n,) the signed distance aimed at when drawing (metres).
      gap: (n, 2) geom gaps (C collides within margin + gap and keeps those
        within the margin active); None: none.
    """

    size: np.ndarray
    rbound: np.ndarray
    margin: np.ndarray
    qpos: np.ndarray
    target: np.ndarray
    gap: np.ndarray | None = None

    def __post_init__(self):
        if self.gap is None:
            object.__setattr__(self, "gap", np.zeros_like(self.margin))

    def __len__(self) -> int:
        return len(self.qpos)


def _rbound(kind: str, s: np.ndarray) -> np.ndarray:
    if kind == "sphere":
        return s[:, 0]
    if kind == "capsule":
        return s[:, 0] + s[:, 1]
    if kind == "ellipsoid":
        return s.max(axis=1)
    if kind == "cylinder":
        return np.hypot(s[:, 0], s[:, 1])
    if kind == "box":
        return np.linalg.norm(s, axis=1)
    raise ValueError(kind)


def _random_quat(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _aligned_quat(rng: np.random.Generator, n: int) -> np.ndarray:
    """Rotations by multiples of 90 degrees about the axes, where pairs are degenerate."""
    out = np.empty((n, 4))
    for i in range(n):
        mat = np.eye(3)[rng.permutation(3)] * rng.choice([-1.0, 1.0], size=(3, 1))
        if np.linalg.det(mat) < 0:
            mat[2] *= -1
        mujoco.mju_mat2Quat(out[i], mat.ravel())
    return out


def draw(pm: PairModel, n: int, rng: np.random.Generator, *, margin_share: float = 0.3,
         aligned_share: float = 0.2, miss_share: float = 0.05) -> Draws:
    """Random sizes, relative poses and margins around contact.

    Sizes are log-uniform in [0.05, 0.5] m per dimension. The second geom is
    placed along a random direction from the first (for a plane: above a random
    point of it) at the offset where MuJoCo C's signed distance
    (`mj_geomDistance`) equals a target drawn uniformly between a penetration of
    30% of the smaller geom's size and the margin (plus `miss_share` of draws
    just beyond it). `aligned_share` of draws turn both geoms by multiples of 90
    degrees (faces parallel: the degenerate cases of box pairs).

    Args:
      pm: the pair's model.
      n: draws.
      rng: random source.
      margin_share: share of draws with a positive margin (none on mesh pairs:
        MJX has no margin there).
      aligned_share: share of draws with axis-aligned orientations.
      miss_share: share of draws separated by more than the margin.

    Returns:
      `Draws`.
    """
    m = pm.m
    d = mujoco.MjData(m)
    kinds = (NAMES[pm.t1], NAMES[pm.t2])
    size = np.tile(m.geom_size[None], (n, 1, 1)).astype(float)
    rbound = np.tile(m.geom_rbound[None], (n, 1)).astype(float)
    for g, kind in enumerate(kinds):
        if kind in ("plane", "mesh"):
            continue
        s = np.exp(rng.uniform(np.log(0.05), np.log(0.5), size=(n, 3)))
        if kind == "sphere":
            s[:, 1:] = 0.0
        elif kind in ("capsule", "cylinder"):
            s[:, 2] = 0.0
        size[:, g] = s
        rbound[:, g] = _rbound(kind, s)
    has_mesh = "mesh" in kinds
    margin = np.zeros((n, 2))
    gap = np.zeros((n, 2))
    if not has_mesh:
        use = rng.uniform(size=n) < margin_share
        margin[use] = rng.uniform(0.0, 0.02, size=(use.sum(), 2))
        # N.B. half of those with a gap as well, at most the margin (MuJoCo's intent).
        gapped = use & (rng.uniform(size=n) < 0.5)
        gap[gapped] = margin[gapped] * rng.uniform(0.0, 1.0, size=(gapped.sum(), 2))
    aligned = rng.uniform(size=n) < aligned_share
    quats = _random_quat(rng, 2 * n).reshape(n, 2, 4)
    quats[aligned] = _aligned_quat(rng, 2 * aligned.sum()).reshape(-1, 2, 4)
    scale = np.minimum(rbound[:, 0] if not pm.plane else np.inf, rbound[:, 1])
    total_margin = margin.sum(axis=1)
    target = rng.uniform(-0.3 * scale, total_margin)
    miss = rng.uniform(size=n) < miss_share
    target[miss] = total_margin[miss] + rng.uniform(1e-4, 0.05, size=miss.sum())
    qpos = np.zeros((n, m.nq))
    for i in range(n):
        _set_sizes(m, size[i], rbound[i], margin[i], gap[i])
        if pm.plane:
            lateral = rng.uniform(-1, 1, size=3) * np.array([1.0, 1.0, 0.0])
            direction = np.array([0.0, 0.0, 1.0])
            base = lateral
            q2 = quats[i, 1]
            qpos[i] = _place(m, d, None, q2, base, direction, target[i], pm)
        else:
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            qpos[i] = _place(m, d, quats[i, 0], quats[i, 1], np.zeros(3), direction,
                             target[i], pm)
    return Draws(size, rbound, margin, qpos, target, gap)


def _set_sizes(m: mujoco.MjModel, size, rbound, margin, gap=0.0) -> None:
    m.geom_size[:] = size
    m.geom_rbound[:] = rbound
    m.geom_margin[:] = margin
    m.geom_gap[:] = gap


def _qpos(m, q1, q2, p2) -> np.ndarray:
    qpos = np.zeros(m.nq)
    if q1 is not None:
        qpos[3:7] = q1
        qpos[7:10], qpos[10:14] = p2, q2
    else:
        qpos[0:3], qpos[3:7] = p2, q2
    return qpos


def _distance(m, d, qpos) -> float:
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    return mujoco.mj_geomDistance(m, d, 0, 1, 10.0, None)


def _place(m, d, q1, q2, base, direction, target, pm) -> np.ndarray:
    """The qpos with geom 2 at base + s * direction where C's signed distance is `target`."""
    lo, hi = 0.0, 4.0
    if pm.plane:
        lo = -4.0
    # N.B. along a ray from inside, the signed distance of two convex sets only
    # grows, so bisection finds the offset (to about C's own GJK/EPA tolerance).
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _distance(m, d, _qpos(m, q1, q2, base + mid * direction)) < target:
            lo = mid
        else:
            hi = mid
    return _qpos(m, q1, q2, base + hi * direction)


# A contact as a row: dist, pos (3), frame (9).
ROW = 13


def c_contacts(pm: PairModel, draws: Draws) -> list[np.ndarray]:
    """MuJoCo C's contacts of every draw: a (k, 13) array each (dist, pos, frame)."""
    m = pm.m
    d = mujoco.MjData(m)
    out = []
    for i in range(len(draws)):
        _set_sizes(m, draws.size[i], draws.rbound[i], draws.margin[i], draws.gap[i])
        d.qpos[:] = draws.qpos[i]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        rows = [np.concatenate([[c.dist], c.pos, c.frame]) for c in d.contact[: d.ncon]
                if not c.exclude]
        out.append(np.array(rows).reshape(-1, ROW))
    return out


def c_poses(pm: PairModel, draws: Draws) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo C's geom poses of every draw: xpos (n, ngeom, 3), xmat (n, ngeom, 9)."""
    m = pm.m
    d = mujoco.MjData(m)
    xpos, xmat = np.empty((len(draws), m.ngeom, 3)), np.empty((len(draws), m.ngeom, 9))
    for i in range(len(draws)):
        d.qpos[:] = draws.qpos[i]
        mujoco.mj_kinematics(m, d)
        xpos[i], xmat[i] = d.geom_xpos, d.geom_xmat
    return xpos, xmat


@functools.cache
def mjx_collide(xml: str, table_key, c_kinematics: bool = True):
    """Compiled batched MJX collision of the pair model (sizes, margins, poses vmapped)."""
    m = mujoco.MjModel.from_xml_string(xml)
    mx = mjx.put_model(m)

    def one(size, rbound, margin, gap, qpos, xpos, xmat):
        mxi = mx.replace(geom_size=size, geom_rbound=rbound, geom_margin=margin, geom_gap=gap)
        d = mjx.make_data(mxi).replace(qpos=qpos)
        d = mjx.kinematics(mxi, d)
        if c_kinematics:
            d = d.replace(geom_xpos=xpos, geom_xmat=xmat.reshape(-1, 3, 3))
        d = mjx.collision(mxi, d)
        c = d._impl.contact  # pylint: disable=protected-access
        frame = c.frame.reshape(c.frame.shape[0], 9)
        rows = jnp.concatenate([c.dist[:, None], c.pos, frame], axis=1)
        return rows, c.dist < c.includemargin

    return jax.jit(jax.vmap(one))


def mjx_contacts(pm: PairModel, draws: Draws, *, batch: int = 2048,
                 kinematics: str = "c") -> list[np.ndarray]:
    """The installed MJX collision table's contacts of every draw, as `c_contacts`.

    Args:
      pm: the pair's model.
      draws: the draws.
      batch: draws per compiled call.
      kinematics: "c" collides the geom poses MuJoCo C computes (`c_poses`), so
        that only the collision functions are compared; "mjx" those of
        `mjx.kinematics`, which differ from C's in the last bits (1e-15), and an
        ill-conditioned pair (two capsule axes crossing, a nearly parallel
        clipping edge) can magnify that to 1e-6 in a normal.

    N.B. compiled once per pair model, collision table (`table_version`) and kinematics.
    """
    from mjstamp import colliders  # pylint: disable=g-import-not-at-top

    if kinematics not in ("c", "mjx"):
        raise ValueError(f"kinematics={kinematics!r}; valid: c, mjx")
    fn = mjx_collide(pm.xml, colliders.table_version(), kinematics == "c")
    xpos, xmat = c_poses(pm, draws)
    out = []
    for start in range(0, len(draws), batch):
        sl = slice(start, start + batch)
        args = (draws.size[sl], draws.rbound[sl], draws.margin[sl], draws.gap[sl],
                draws.qpos[sl], xpos[sl], xmat[sl])
        rows, active = jax.device_get(fn(*(jnp.asarray(a) for a in args)))
        out.extend(np.asarray(r[a], np.float64) for r, a in zip(rows, active, strict=True))
    return out


@dataclasses.dataclass(frozen=True)
class Report:
    """How far one engine's contacts are from C's over many draws.

    Attributes:
      pair: 'box-box'.
      draws: number of draws.
      contacts_c: C's contacts over all draws.
      count_mismatches: draws whose number of contacts differs.
      dist, pos, normal, frame: worst absolute difference over matched
        contacts (of draws with equal counts), metres or unit vectors.
      worst: the draw index of the first count mismatch, else of the worst
        field difference (-1 when no draw has a contact).
      mismatch_examples: up to 5 draw indices with different counts.
    """

    pair: str
    draws: int
    contacts_c: int
    count_mismatches: int
    dist: float
    pos: float
    normal: float
    frame: float
    worst: int
    mismatch_examples: tuple[int, ...]

    def as_dict(self) -> dict:
        """JSON view."""
        return dataclasses.asdict(self)

    def within(self, tol: float) -> bool:
        """No count mismatch and every field within `tol`."""
        return (self.count_mismatches == 0
                and max(self.dist, self.pos, self.normal, self.frame) <= tol)


def compare(pm: PairModel, draws, c: list[np.ndarray], j: list[np.ndarray]) -> Report:
    """Matches each draw's contacts by position and reports the worst differences.

    Args:
      pm: the pair's model (names the report).
      draws: the draws (their count; any sized collection).
      c: C's contacts per draw, (k, 13) each.
      j: MJX's, the same way.
    """
    worst = {"dist": 0.0, "pos": 0.0, "normal": 0.0, "frame": 0.0}
    worst_at, worst_value = -1, 0.0
    mismatches = []
    for i, (a, b) in enumerate(zip(c, j, strict=True)):
        if len(a) != len(b):
            mismatches.append(i)
            continue
        if not len(a):
            continue
        cost = np.linalg.norm(a[:, None, 1:4] - b[None, :, 1:4], axis=2)
        # N.B. coincident contacts (C emits some twice) make position alone
        # ambiguous: break ties by the rest of the row.
        cost = cost + 1e-3 * np.abs(a[:, None] - b[None]).sum(axis=2)
        ra, rb = linear_sum_assignment(cost)
        a, b = a[ra], b[rb]
        diffs = {
            "dist": np.abs(a[:, 0] - b[:, 0]).max(),
            "pos": np.abs(a[:, 1:4] - b[:, 1:4]).max(),
            "normal": np.abs(a[:, 4:7] - b[:, 4:7]).max(),
            "frame": np.abs(a[:, 4:13] - b[:, 4:13]).max(),
        }
        for k, v in diffs.items():
            worst[k] = max(worst[k], float(v))
        top = max(diffs.values())
        if top > worst_value:
            worst_at, worst_value = i, float(top)
    return Report(
        pair=pm.name, draws=len(draws), contacts_c=int(sum(len(a) for a in c)),
        count_mismatches=len(mismatches), worst=mismatches[0] if mismatches else worst_at,
        mismatch_examples=tuple(mismatches[:5]), **worst,
    )


def run(t1: int, t2: int, n: int, *, seed: int = 0, flags: str = "") -> Report:
    """Draws `n` poses of the pair and compares the installed MJX table with C."""
    pm = pair_model(t1, t2, flags=flags)
    draws = draw(pm, n, np.random.default_rng(seed))
    return compare(pm, draws, c_contacts(pm, draws), mjx_contacts(pm, draws))


@functools.cache
def _mjx_scene_collide(m_bytes: bytes, table_key):
    """Compiled batched MJX collision of a whole model at given qpos."""
    import tempfile  # pylint: disable=g-import-not-at-top

    with tempfile.NamedTemporaryFile(suffix=".mjb") as f:
        f.write(m_bytes)
        f.flush()
        m = mujoco.MjModel.from_binary_path(f.name)
    mx = mjx.put_model(m)

    def one(qpos):
        d = mjx.make_data(mx).replace(qpos=qpos)
        d = mjx.kinematics(mx, d)
        d = mjx.collision(mx, d)
        c = d._impl.contact  # pylint: disable=protected-access
        frame = c.frame.reshape(c.frame.shape[0], 9)
        rows = jnp.concatenate([c.dist[:, None], c.pos, frame], axis=1)
        return rows, c.geom, c.dist < c.includemargin

    return jax.jit(jax.vmap(one))


def compare_states(m: mujoco.MjModel, qpos: np.ndarray) -> dict[str, Report]:
    """A whole model's contacts at states `qpos` (n, nq), MJX against C, per type pair.

    Contacts are grouped by geom pair and matched within each as `compare`
    does; the reports are merged per pair of geom types ('box-box'), so a
    model's own sizes, margins and `<pair>` settings are what is compared.
    """
    from mjstamp import colliders  # pylint: disable=g-import-not-at-top

    qpos = np.asarray(qpos, np.float64)
    fn = _mjx_scene_collide(model_bytes(m), colliders.table_version())
    rows, geoms, active = (np.asarray(a) for a in jax.device_get(fn(jnp.asarray(qpos))))
    d = mujoco.MjData(m)
    per_type: dict[str, tuple[PairModel, list, list]] = {}
    for i, q in enumerate(qpos):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        c_rows: dict[tuple[int, int], list] = {}
        for con in d.contact[: d.ncon]:
            if not con.exclude:
                key = tuple(sorted((int(con.geom1), int(con.geom2))))
                c_rows.setdefault(key, []).append(
                    np.concatenate([[con.dist], con.pos, con.frame]))
        j_rows: dict[tuple[int, int], list] = {}
        for r, g in zip(rows[i][active[i]], geoms[i][active[i]], strict=True):
            j_rows.setdefault(tuple(sorted(int(x) for x in g)), []).append(r)
        for key in set(c_rows) | set(j_rows):
            name = pair_name(m.geom_type[key[0]], m.geom_type[key[1]])
            _, cs, js = per_type.setdefault(name, (None, [], []))
            cs.append(np.array(c_rows.get(key, [])).reshape(-1, ROW))
            js.append(np.array(j_rows.get(key, [])).reshape(-1, ROW))
    out = {}
    for name, (_, cs, js) in per_type.items():
        t1, t2 = parse_pair(name)
        stub = PairModel(t1, t2, m, "")
        out[name] = compare(stub, cs, cs, js)
    return out
