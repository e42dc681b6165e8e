"""MuJoCo model -> meshcat scene: every geom and site with its shape, size, pose and color.

The loader reads a compiled `MjModel` (so it works the same for an MJCF file,
a results directory's scene.mjb or a `Scene.m`) and turns it into meshcat
commands: one group per body (`bodies/<body>`), posed in the world, and under it
one object per geom (`geoms/<geom>`) and per site (`sites/<site>`), posed
relative to the body exactly as MuJoCo poses them (`geom_pos`, `geom_quat`).
Shapes follow MuJoCo's size conventions (half-sizes, radius then half-length).
Colors, opacity and which groups show come from `mjstamp.geometry` (as in the
PNG figures): MuJoCo's renderer's colour, sites semi-transparent since they
mark regions (pockets, goals), not matter; geoms and sites in groups that
MuJoCo hides by default (3-5, e.g. collision duplicates) are drawn but start
hidden.

Commands are plain meshcat command objects (`SetObject`, `SetTransform`,
`SetProperty`): the same list goes to a live meshcat server or into a
standalone HTML page (see `mjstamp.viz.play`).
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
from meshcat import geometry as mg
from meshcat.commands import SetObject, SetProperty, SetTransform
from meshcat.path import Path

from mjstamp import geometry
from mjstamp.geometry import SITE_OPACITY

__all__ = [
    "ROOT",
    "SITE_OPACITY",
    "SceneObject",
    "body_name",
    "body_path",
    "capsule_mesh",
    "clean_name",
    "hex_color",
    "mesh_arrays",
    "path_of",
    "pose_matrix",
    "scene_bounds",
    "scene_commands",
    "scene_objects",
    "shape",
    "translation",
]

ROOT = ("meshcat", "mjstamp")  # every object of ours lives under this path


def clean_name(name: str, fallback: str) -> str:
    """A meshcat path element: '/' separates paths, so it cannot be in a name."""
    name = (name or fallback).replace("/", "_")
    return name


def body_name(m: mujoco.MjModel, b: int) -> str:
    """Path element of body `b` (its name, or body<b> when unnamed)."""
    return clean_name(m.body(b).name, f"body{b}")


def pose_matrix(pos, quat) -> np.ndarray:
    """(4, 4) homogeneous transform of a position (3,) and a MuJoCo quaternion (4,) wxyz."""
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    out = np.eye(4)
    out[:3, :3] = mat.reshape(3, 3)
    out[:3, 3] = pos
    return out


def hex_color(rgba) -> int:
    """0xRRGGBB of an rgba in [0, 1]."""
    r, g, b = (int(round(float(np.clip(c, 0.0, 1.0)) * 255)) for c in rgba[:3])
    return (r << 16) | (g << 8) | b


class ZCylinder(mg.Cylinder):
    """A cylinder along z (MuJoCo's axis); three.js builds cylinders along y."""

    def intrinsic_transform(self):
        """Rotation by +90 degrees about x: three.js y becomes MuJoCo z.

        N.B. returned transposed: meshcat flattens this matrix row by row, but
        three.js reads it column by column.
        """
        rot_x = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
        return rot_x.T


def _revolve(profile: np.ndarray, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of a profile (k, 2) of (radius, z) points revolved about z."""
    k = len(profile)
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    rho, z = profile[:, 0:1], profile[:, 1:2]
    vertices = np.stack(
        [rho * np.cos(phi), rho * np.sin(phi), np.broadcast_to(z, (k, segments))], axis=-1
    ).reshape(-1, 3)
    faces = []
    for i in range(k - 1):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            faces += [(a, c, b), (b, c, d)]
    return vertices, np.asarray(faces, np.uint32)


def capsule_mesh(radius: float, half_length: float, segments: int = 24):
    """(vertices (n, 3), faces (f, 3)) of a capsule along z (three.js here has no capsule).

    Args:
      radius: radius of the cylinder and its hemispherical caps.
      half_length: half the length of the cylindrical part.
      segments: points per ring (the caps get segments // 4 rings each).
    """
    rings = max(segments // 4, 2)
    top = np.linspace(0.0, np.pi / 2, rings + 1)
    bottom = np.linspace(np.pi / 2, np.pi, rings + 1)
    profile = np.concatenate([
        np.stack([radius * np.sin(top), half_length + radius * np.cos(top)], -1),
        np.stack([radius * np.sin(bottom), -half_length + radius * np.cos(bottom)], -1),
    ])
    return _revolve(profile, segments)


def _plane_mesh(hx: float, hy: float):
    vertices = np.array([[-hx, -hy, 0], [hx, -hy, 0], [hx, hy, 0], [-hx, hy, 0]], np.float32)
    return vertices, np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def _hfield_mesh(m: mujoco.MjModel, h: int):
    rx, ry, top, _ = m.hfield_size[h]
    nrow, ncol = int(m.hfield_nrow[h]), int(m.hfield_ncol[h])
    adr = int(m.hfield_adr[h])
    z = np.asarray(m.hfield_data[adr : adr + nrow * ncol]).reshape(nrow, ncol) * top
    x, y = np.meshgrid(np.linspace(-rx, rx, ncol), np.linspace(-ry, ry, nrow))
    vertices = np.stack([x, y, z], -1).reshape(-1, 3)
    faces = []
    for r in range(nrow - 1):
        for c in range(ncol - 1):
            a = r * ncol + c
            faces += [(a, a + 1, a + ncol + 1), (a, a + ncol + 1, a + ncol)]
    return vertices, np.asarray(faces, np.uint32)


def mesh_arrays(m: mujoco.MjModel, mesh: int) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3), faces (f, 3)) of mesh `mesh`, in the geom frame.

    N.B. the compiler has already scaled and re-centred the vertices so that
    the geom's own pose places them: nothing else is applied.
    """
    v0, nv = int(m.mesh_vertadr[mesh]), int(m.mesh_vertnum[mesh])
    f0, nf = int(m.mesh_faceadr[mesh]), int(m.mesh_facenum[mesh])
    return np.array(m.mesh_vert[v0 : v0 + nv]), np.array(m.mesh_face[f0 : f0 + nf])


def shape(
    m: mujoco.MjModel, gtype: int, size: np.ndarray, dataid: int = -1, *, plane_half: float = 1.0
) -> mg.Geometry | None:
    """The meshcat geometry of a MuJoCo shape, in the element's own frame.

    Args:
      m: the model (meshes and height fields are read from it).
      gtype: `mujoco.mjtGeom` value.
      size: (3,) MuJoCo size of the element.
      dataid: mesh or height-field id (mesh and hfield types).
      plane_half: half-size drawn for an infinite plane (size 0).

    Returns:
      The geometry, or None for a type it cannot draw (e.g. an SDF without mesh).
    """
    t = mujoco.mjtGeom
    sx, sy, sz = (float(s) for s in size)
    if gtype == t.mjGEOM_PLANE:
        return mg.TriangularMeshGeometry(*_plane_mesh(sx or plane_half, sy or plane_half))
    if gtype == t.mjGEOM_SPHERE:
        return mg.Sphere(sx)
    if gtype == t.mjGEOM_CAPSULE:
        return mg.TriangularMeshGeometry(*capsule_mesh(sx, sy))
    if gtype == t.mjGEOM_ELLIPSOID:
        return mg.Ellipsoid([sx, sy, sz])
    if gtype == t.mjGEOM_CYLINDER:
        return ZCylinder(2 * sy, sx)
    if gtype == t.mjGEOM_BOX:
        return mg.Box([2 * sx, 2 * sy, 2 * sz])
    if gtype == t.mjGEOM_HFIELD and dataid >= 0:
        return mg.TriangularMeshGeometry(*_hfield_mesh(m, dataid))
    if gtype in (t.mjGEOM_MESH, t.mjGEOM_SDF) and dataid >= 0:
        return mg.TriangularMeshGeometry(*mesh_arrays(m, dataid))
    return None


@dataclasses.dataclass
class SceneObject:
    """One drawn geom or site.

    Attributes:
      kind: "geom" or "site".
      id: its id in the model.
      body: id of its body.
      path: meshcat path below `ROOT`, e.g. ("bodies", "cue", "geoms", "cue").
      geometry: meshcat geometry in the element's frame.
      rgba: (4,) color and opacity as drawn.
      transform: (4, 4) pose relative to its body.
      visible: whether it starts shown (MuJoCo's default group visibility).
    """

    kind: str
    id: int
    body: int
    path: tuple[str, ...]
    geometry: mg.Geometry
    rgba: np.ndarray
    transform: np.ndarray
    visible: bool

    def material(self) -> mg.Material:
        """Phong material of its color; see-through ones do not hide what is behind."""
        opacity = float(self.rgba[3])
        extra = {"depthWrite": False} if opacity < 1 else {}
        return mg.MeshPhongMaterial(color=hex_color(self.rgba), opacity=opacity, **extra)


def scene_objects(m: mujoco.MjModel) -> list[SceneObject]:
    """Every geom and site of `m` as a `SceneObject` (types it cannot draw are skipped)."""
    plane_half = 2.0 * max(float(m.stat.extent), 1e-3)
    out = []
    for kind in ("geom", "site"):
        count = m.ngeom if kind == "geom" else m.nsite
        for i in range(count):
            gtype = int(getattr(m, f"{kind}_type")[i])
            dataid = int(m.geom_dataid[i]) if kind == "geom" else -1
            drawn = shape(m, gtype, getattr(m, f"{kind}_size")[i], dataid, plane_half=plane_half)
            if drawn is None:
                continue
            b = int(getattr(m, f"{kind}_bodyid")[i])
            name = clean_name(getattr(m, kind)(i).name, f"{kind}{i}")
            out.append(SceneObject(
                kind=kind, id=i, body=b, path=("bodies", body_name(m, b), f"{kind}s", name),
                geometry=drawn, rgba=geometry.drawn_rgba(m, kind, i),
                transform=pose_matrix(getattr(m, f"{kind}_pos")[i],
                                      getattr(m, f"{kind}_quat")[i]),
                visible=geometry.shown(m, kind, i),
            ))
    return out


def _site_half(m: mujoco.MjModel, i: int) -> np.ndarray:
    """(3,) half-extents of site `i` in its own frame (MuJoCo's size conventions)."""
    t = mujoco.mjtGeom
    r, h, z = (float(x) for x in m.site_size[i])
    gtype = m.site_type[i]
    if gtype == t.mjGEOM_SPHERE:
        return np.full(3, r)
    if gtype == t.mjGEOM_CAPSULE:
        return np.array([r, r, r + h])
    if gtype == t.mjGEOM_CYLINDER:
        return np.array([r, r, h])
    return np.array([r, h, z])  # box, ellipsoid


def scene_bounds(m: mujoco.MjModel, d) -> tuple[np.ndarray, float]:
    """(center (3,), radius) of a sphere around what the scene is about, at the pose in `d`.

    `d` is an MjData after kinematics or a `geometry.Pose`. The box bounds every
    geom but planes, and every shown site (goal regions); planes count only in
    a scene with nothing else. N.B. a floor is not what a plan is about:
    dm_control's arena is a 2 m square under a 1 m arm and a 5 cm brick, and
    framing it put the brick at a few pixels (`Scene.length_scale` leaves
    planes out for the same reason). Not `m.stat` either, nor the geoms'
    bounding spheres: both count a long wall as a ball as wide as it is long
    and put the camera far from a small table. The geoms' own boxes
    (`geom_aabb`), turned into the world, fit closely.
    """
    plane = mujoco.mjtGeom.mjGEOM_PLANE
    boxes, planes = [], []
    for i in range(m.ngeom):
        rot = d.geom_xmat[i].reshape(3, 3)
        center, half = m.geom_aabb[i][:3], np.array(m.geom_aabb[i][3:])
        if m.geom_type[i] == plane:  # its box is infinite: its drawn size instead
            center, half = np.zeros(3), np.array([m.geom_size[i][0], m.geom_size[i][1], 0.0])
            if not half[:2].all():
                continue
        mid = d.geom_xpos[i] + rot @ center
        reach = np.abs(rot) @ half
        (planes if m.geom_type[i] == plane else boxes).append((mid - reach, mid + reach))
    for i in range(m.nsite):
        if geometry.shown(m, "site", i):
            reach = np.abs(d.site_xmat[i].reshape(3, 3)) @ _site_half(m, i)
            boxes.append((d.site_xpos[i] - reach, d.site_xpos[i] + reach))
    boxes = boxes or planes
    if not boxes:
        return np.asarray(m.stat.center, np.float64), max(float(m.stat.extent), 0.1)
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    return (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 0.05)


def path_of(*parts: str) -> Path:
    """The meshcat Path of `ROOT` + parts."""
    return Path(ROOT + tuple(parts))


def body_path(m: mujoco.MjModel, b: int) -> Path:
    """The meshcat Path of body `b`'s group (posed in the world)."""
    return path_of("bodies", body_name(m, b))


def translation(p) -> np.ndarray:
    """(4, 4) translation by p (3,)."""
    out = np.eye(4)
    out[:3, 3] = p
    return out


def scene_commands(m: mujoco.MjModel, qpos: np.ndarray | None = None, *,
                   pose: geometry.Pose | None = None,
                   view: tuple[float, float, float] = (0.0, -0.7, 1.0)) -> list:
    """The meshcat commands that draw `m` at `qpos`, with a camera on the whole scene.

    Args:
      m: the model.
      qpos: (nq,) pose to draw (default `m.qpos0`).
      pose: the `geometry.Pose` to draw instead of qpos's, when it is at hand
        (a replay's first frame): nothing is computed twice.
      view: direction from the scene centre to the camera, in world coordinates.

    Returns:
      List of meshcat commands. N.B. the root group is shifted by minus the
      scene centre: meshcat's orbit controls turn about the world origin, so
      this centres the view on the scene without moving the camera rig.
    """
    d = geometry.pose(m, m.qpos0 if qpos is None else qpos) if pose is None else pose
    center, radius = scene_bounds(m, d)
    cmds: list = [
        SetProperty("visible", False, Path(("Grid",))),  # z-fights with planes at z = 0
        SetProperty("visible", False, Path(("Axes",))),
        SetTransform(translation(-center), path_of()),
    ]
    for b in range(m.nbody):
        cmds.append(SetTransform(pose_matrix(d.xpos[b], d.xquat[b]), body_path(m, b)))
    for obj in scene_objects(m):
        path = path_of(*obj.path)
        cmds.append(SetObject(mg.Mesh(obj.geometry, obj.material()), path=path))
        cmds.append(SetTransform(obj.transform, path))
        if not obj.visible:
            cmds.append(SetProperty("visible", False, path))
    # meshcat's camera sits in a y-up frame rotated +90 degrees about x: world (x, y, z) is
    # (x, z, -y) there. Distance: the scene sphere fills the 75-degree field of view.
    v = np.asarray(view, np.float64)
    v = v / np.linalg.norm(v) * radius / math.tan(math.radians(75 / 2)) * 1.05
    cmds.append(SetProperty("position", [float(v[0]), float(v[2]), float(-v[1])],
                            Path(("Cameras", "default", "rotated", "<object>"))))
    return cmds
