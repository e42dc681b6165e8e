"""plans_topdown.png (STAMP Fig. 3/6): the best plan of each task plan, seen from above.

Geom and site footprints (convex hulls in xy), body paths and contact-force
arrows, every panel on one frame and one force scale.

The top-down view reads the poses, colours and contact forces of a C replay
from `mjstamp.geometry`, the module the meshcat playback (`mjstamp.viz`) reads
them from, so a PNG and the playback of the same plan show the same things.
`plan_frames` → `plan_drawing` → `draw_topdown` are its steps, usable on any
replay (tests draw one without a solve).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import mujoco
import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Polygon

from mjstamp import geometry
from mjstamp.figures.plans import best_verified

FORCE_FRAMES = 5  # force arrows drawn per geom pair and plan


def topdown_figure(result, *, columns: int = 4) -> Figure:
    """One top-down panel per verified task plan: its best plan, scene and paths.

    Each panel draws the scene from the MjModel (geom footprints in xy, sites),
    the moving geoms at the start (faint) and at the end of the C replay, the
    paths of the bodies in `problem.display["trace"]` (default: every body
    with a joint), and for each geom pair (A, B) in `display["force"]`
    arrows of the contact force of A on B at a few frames. Poses, colours and
    forces come from `mjstamp.geometry`, as in the meshcat playback.

    Args:
      result: a `SolveResult`.
      columns: panels per row at most.

    Returns:
      The Figure.

    References: STAMP Fig. 3 (billiards), Fig. 6 (pushing: force arrows).
    """
    task = result.task
    m = task.scene.m
    chosen = best_verified(result)
    subtitle = "best-cost verified plan of each task plan"
    if not chosen:
        # Still draw the scene and the closest miss: a blank figure helps nobody.
        i = int(np.nanargmin(np.where(np.isfinite(result.cost), result.cost, np.inf)))
        chosen = [(f"{result.verified.plan[i]} (failed)", i)]
        subtitle = "no verified plan; lowest-cost particle shown"
    trace = [task.scene.body(b) for b in task.display.get("trace", [])]
    if not trace:
        trace = [b for b in range(1, m.nbody) if m.body_jntnum[b] > 0]
    pairs = [(task.scene.geom(a), task.scene.geom(b))
             for a, b in task.display.get("force", [])]
    drawings = [plan_drawing(m, plan_frames(result, i, pairs), trace) for _, i in chosen]
    titles = [f"{plan}\ncost {result.cost[i]:.3g} (particle {i})" for plan, i in chosen]
    return draw_topdown(m, drawings, titles, columns=columns,
                        title=f"{task.name}: {subtitle}\n(top-down view of the MuJoCo C replay)")


def plan_frames(result, i: int, pairs=()) -> geometry.Frames:
    """Poses (and contact forces of `pairs`) at every state of particle i's C replay."""
    task, replay = result.task, result.replay
    qpos0, qvel0, _ = task.inputs(result.theta[i : i + 1], xp=np)
    return geometry.replay_frames(
        task.scene.m, np.asarray(qpos0, np.float64)[0], replay.qpos[i],
        qvel0=np.asarray(qvel0, np.float64)[0],
        qvel=None if replay.qvel is None else replay.qvel[i],  # an MJX replay: positions only
        ctrl=None if replay.ctrl is None else replay.ctrl[i],
        pairs=pairs,
    )


class Footprint(NamedTuple):
    """The top-down shadow of one geom or site at one pose.

    Attributes:
      kind: "geom" or "site".
      id: its id in the model.
      plane: a plane (table, floor), drawn as its finite extent under everything.
      polygon: (k, 2) convex hull in xy, counter-clockwise.
      moving: whether its body moves (is not welded to the world).
      rgba: colour as drawn (`geometry.drawn_rgba`).
      top: its highest z (the drawing order of static geoms).
    """

    kind: str
    id: int
    plane: bool
    polygon: np.ndarray
    moving: bool
    rgba: tuple
    top: float


class Arrows(NamedTuple):
    """The contact-force arrows of one geom pair (a, b) in a top-down panel.

    Attributes:
      pair: (a, b) geom ids: the force of a on b.
      states: (k,) replay states drawn (up to `FORCE_FRAMES`, spread over
        those with contact).
      force: (k, 2) xy force at each.
      point: (k, 2) where it acts.
    """

    pair: tuple[int, int]
    states: np.ndarray
    force: np.ndarray
    point: np.ndarray


class PlanDrawing(NamedTuple):
    """What a top-down panel draws of one replay.

    Attributes:
      start: footprints at the first frame.
      end: footprints at the last frame.
      paths: {body id: (F, 2) xy path}.
      forces: one `Arrows` per geom pair of the frames.
      extent: ((2,) lower, (2,) upper corner) of what is drawn.
    """

    start: list[Footprint]
    end: list[Footprint]
    paths: dict[int, np.ndarray]
    forces: list[Arrows]
    extent: tuple[np.ndarray, np.ndarray]


def plan_drawing(m, frames: geometry.Frames, trace: Sequence[int]) -> PlanDrawing:
    """Footprints at the first and last frame, paths of `trace` bodies, force arrows.

    Args:
      m: the MjModel of the replay.
      frames: `geometry.Frames` of the replay (every state, for whole paths).
      trace: body ids whose paths to draw.
    """
    start, end = _footprints(m, frames.pose(0)), _footprints(m, frames.pose(-1))
    paths = {b: frames.xpos[:, b, :2] for b in trace}
    forces = [_force_arrows(pair, frames.states, frames.force[:, k], frames.point[:, k])
              for k, pair in enumerate(frames.pairs)]
    # Planes (tables, floors) may be far larger than where things happen: they
    # set the extent only when nothing else does.
    pts = [g.polygon for g in start + end if g.kind == "geom" and not g.plane]
    pts += [s.polygon for s in start if s.kind == "site"] + list(paths.values())
    pts = pts or [g.polygon for g in start if g.kind == "geom"] or [np.zeros((1, 2))]
    allpts = np.concatenate(pts)
    return PlanDrawing(start, end, paths, forces, (allpts.min(axis=0), allpts.max(axis=0)))


def _force_arrows(pair, states: np.ndarray, force: np.ndarray, point: np.ndarray) -> Arrows:
    """The `Arrows` of one pair at `FORCE_FRAMES` frames spread over those with contact.

    Args:
      pair: (a, b) geom ids.
      states: (F,) state index of each frame.
      force: (F, 3) force of a on b at every frame.
      point: (F, 3) where it acts, NaN where the geoms do not touch.
    """
    touching = np.flatnonzero(np.isfinite(point).all(axis=1)
                              & (np.linalg.norm(force[:, :2], axis=1) > 0))
    if len(touching):
        spread = np.linspace(0, len(touching) - 1, FORCE_FRAMES).round().astype(int)
        touching = touching[np.unique(spread)]
    return Arrows(pair, states[touching], force[touching, :2], point[touching, :2])


def draw_topdown(m, drawings: Sequence[PlanDrawing], titles: Sequence[str], *, title: str,
                 columns: int = 4) -> Figure:
    """A figure of top-down panels, one per drawing, on one frame and one force scale.

    Args:
      m: the MjModel the drawings are of.
      drawings: `plan_drawing`s, all with the same traced bodies and force pairs.
      titles: one panel title per drawing.
      title: the figure's title.
      columns: panels per row at most.
    """
    trace = list(drawings[0].paths)
    pairs = [arrows.pair for arrows in drawings[0].forces]
    lo = np.min([d.extent[0] for d in drawings], axis=0)
    hi = np.max([d.extent[1] for d in drawings], axis=0)
    margin = 0.03 * max(hi - lo)
    lo, hi = lo - margin, hi + margin
    # One scale for every force arrow: the largest is 15% of the scene's width.
    fmax = max([np.max(np.linalg.norm(a.force, axis=1)) for d in drawings for a in d.forces
                if len(a.force)], default=0.0)
    arrow_scale = 0.15 * max(hi - lo) / fmax if fmax > 0 else 0.0
    fig, axes, cols, legend_cols = _topdown_grid(len(drawings), columns, lo, hi,
                                                 len(trace) + 3 + len(pairs))
    trace_colors = {b: f"C{k % 10}" for k, b in enumerate(trace)}
    for k, (ax, panel_title, drawing) in enumerate(zip(axes, titles, drawings, strict=False)):
        _draw_plan(ax, m, drawing, trace_colors, arrow_scale)
        ax.set_title(panel_title, fontsize=9)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        # Axis labels on the outer panels only: every panel has the same frame.
        if k + cols >= len(drawings):  # no panel below
            ax.set_xlabel("x [m]", fontsize=8)
        if k % cols == 0:
            ax.set_ylabel("y [m]", fontsize=8)
    for ax in axes[len(drawings):]:
        ax.set_axis_off()
    fig.suptitle(title)
    fig.legend(handles=_topdown_legend(m, trace_colors, pairs, fmax),
               loc="outside lower center", ncols=legend_cols, fontsize=8)
    return fig


def _topdown_grid(panels: int, columns: int, lo, hi, legend_entries: int):
    """(figure, flat axes, columns, legend columns) sized for `panels` equal-aspect panels."""
    cols = min(columns, panels)
    rows = math.ceil(panels / cols)
    aspect = (hi[1] - lo[1]) / (hi[0] - lo[0])
    # Size the figure around data areas of at most 3.1 x 3.4 in, plus per panel
    # its tick labels and two-line title (~0.75 in each way), the two-line
    # suptitle and the legend: constrained layout overlaps texts when an
    # equal-aspect figure is too small for them.
    width = min(3.1, 3.4 / aspect)
    legend_cols = min(legend_entries, 6 if cols > 2 else 3)
    legend_rows = math.ceil(legend_entries / legend_cols)
    fig = Figure(figsize=(max(cols * (width + 0.75) + 0.3, 7.0),
                          rows * (width * aspect + 0.75) + 0.8 + 0.25 * legend_rows + 0.3),
                 layout="constrained")
    return fig, fig.subplots(rows, cols, squeeze=False).ravel(), cols, legend_cols


def _topdown_legend(m, trace_colors: dict, pairs, fmax: float) -> list:
    handles = [Line2D([], [], color=color, lw=1.5,
                      label=f"{mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)} path")
               for b, color in trace_colors.items()]
    handles += [
        Line2D([], [], ls="", marker="o", mfc="white", mec="k", label="start"),
        Line2D([], [], ls="", marker="X", mfc="k", mec="k", label="end"),
        Patch(facecolor="none", edgecolor="k", ls="--", alpha=0.5, label="bodies at start"),
    ]
    for a, b in pairs:
        name_a = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, a)
        name_b = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, b)
        handles.append(Line2D([], [], color="red", lw=2,
                              label=f"force of {name_a} on {name_b} (longest {fmax:.3g} N)"))
    return handles


def _gid(m, g: Footprint, prefix: str = "") -> str:
    """The patch's id ("geom/wall", "start/geom/puck"): which element a test or SVG sees."""
    name = mujoco.mj_id2name(m, getattr(mujoco.mjtObj, f"mjOBJ_{g.kind.upper()}"), g.id)
    return f"{prefix}{g.kind}/{name or f'{g.kind}{g.id}'}"


def _draw_plan(ax, m, drawing: PlanDrawing, trace_colors: dict, arrow_scale: float) -> None:
    static = [g for g in drawing.start if g.kind == "geom" and not g.moving]
    for g in sorted(static, key=lambda g: g.top):
        if g.plane:
            # Tables and floors are background: paled, so that geoms of the same
            # color (MuJoCo's default gray for both) stand out on them.
            face = (*(0.55 * np.asarray(g.rgba[:3]) + 0.45), g.rgba[3])
            ax.add_patch(Polygon(g.polygon, closed=True, facecolor=face, edgecolor="none",
                                 zorder=0.5, gid=_gid(m, g)))
        else:
            ax.add_patch(Polygon(g.polygon, closed=True, facecolor=g.rgba,
                                 edgecolor=_darker(g.rgba), lw=0.5, zorder=1 + 0.01 * g.top,
                                 gid=_gid(m, g)))
    # Sites on the world where they are; sites on moving bodies where they end.
    sites = [s for s in drawing.start if s.kind == "site" and not s.moving]
    sites += [s for s in drawing.end if s.kind == "site" and s.moving]
    for s in sites:
        ax.add_patch(Polygon(s.polygon, closed=True, facecolor=s.rgba, edgecolor="k", lw=0.5,
                             ls="--", zorder=1.5, gid=_gid(m, s)))
    for g in drawing.start:
        if g.kind == "geom" and g.moving:  # ghost at the start
            ax.add_patch(Polygon(g.polygon, closed=True, facecolor=(*g.rgba[:3], 0.25 * g.rgba[3]),
                                 edgecolor="k", ls="--", lw=0.6, zorder=2,
                                 gid=_gid(m, g, "start/")))
    for b, path in drawing.paths.items():
        color = trace_colors[b]
        ax.plot(path[:, 0], path[:, 1], color=color, lw=1.4, zorder=4)
        ax.plot(*path[0], ls="", marker="o", mfc="white", mec=color, ms=5, zorder=5)
        ax.plot(*path[-1], ls="", marker="X", mfc=color, mec="k", mew=0.4, ms=6, zorder=5)
    for g in drawing.end:
        if g.kind == "geom" and g.moving:
            ax.add_patch(Polygon(g.polygon, closed=True, facecolor=g.rgba, edgecolor="k", lw=0.6,
                                 zorder=3, gid=_gid(m, g)))
    for a in drawing.forces:
        if len(a.force) and arrow_scale > 0:
            ax.quiver(a.point[:, 0], a.point[:, 1], a.force[:, 0] * arrow_scale,
                      a.force[:, 1] * arrow_scale, angles="xy", scale_units="xy", scale=1,
                      color="red", width=0.008, zorder=6)


def _darker(rgba) -> tuple:
    return (*(0.6 * np.asarray(rgba[:3])), rgba[3])


def _footprints(m, pose) -> list[Footprint]:
    """Footprints in xy of the shown geoms, then sites, at a pose.

    Args:
      m: the MjModel.
      pose: a `geometry.Pose` (or an MjData after kinematics).
    """
    out = []
    for kind, count in (("geom", m.ngeom), ("site", m.nsite)):
        for i in range(count):
            rgba = geometry.drawn_rgba(m, kind, i)
            if rgba[3] == 0 or not geometry.shown(m, kind, i):
                continue
            world = _world_points(m, int(getattr(m, f"{kind}_type")[i]),
                                  getattr(m, f"{kind}_size")[i], getattr(pose, f"{kind}_xpos")[i],
                                  getattr(pose, f"{kind}_xmat")[i], i if kind == "geom" else None)
            if world is None:
                continue
            plane = kind == "geom" and m.geom_type[i] == mujoco.mjtGeom.mjGEOM_PLANE
            moving = m.body_weldid[getattr(m, f"{kind}_bodyid")[i]] != 0
            out.append(Footprint(kind, i, bool(plane), _hull(world[:, :2]), bool(moving),
                                 tuple(float(c) for c in rgba), float(world[:, 2].max())))
    return out


def _world_points(m, kind: int, size, pos, xmat, geom: int | None) -> np.ndarray | None:
    """(k, 3) world points whose xy convex hull is the object's top-down footprint.

    Args:
      m: the MjModel (meshes and height fields).
      kind: an mjtGeom type.
      size: (3,) geom or site size.
      pos: (3,) world position.
      xmat: (9,) world orientation, row-major.
      geom: geom id (meshes and height fields), None for sites.
    """
    t = mujoco.mjtGeom
    rot = np.asarray(xmat).reshape(3, 3)
    phi = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    ring = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    if kind in (t.mjGEOM_SPHERE, t.mjGEOM_CAPSULE):
        # A ball's shadow is a disc whatever its orientation: ring in world xy
        # around each end of the segment (a sphere's segment has length 0).
        half = size[1] if kind == t.mjGEOM_CAPSULE else 0.0
        ends = pos + np.outer([-half, half], rot[:, 2])
        return np.concatenate([end + size[0] * ring for end in ends])
    local = None
    if kind == t.mjGEOM_CYLINDER:
        r, h = size[0], size[1]
        local = np.concatenate([r * ring + [0, 0, h], r * ring - [0, 0, h]])
    elif kind == t.mjGEOM_ELLIPSOID:
        u, v = np.meshgrid(np.linspace(0, np.pi, 13), phi)
        pts = np.stack([np.sin(u) * np.cos(v), np.sin(u) * np.sin(v), np.cos(u)], -1)
        local = pts.reshape(-1, 3) * np.asarray(size[:3])
    elif kind == t.mjGEOM_BOX:
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        local = corners * np.asarray(size[:3])
    elif kind == t.mjGEOM_PLANE:
        if size[0] <= 0 or size[1] <= 0:
            return None  # infinite plane: no extent to draw
        local = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * [*size[:2], 0]
    elif kind == t.mjGEOM_MESH and geom is not None:
        mesh = m.geom_dataid[geom]
        start, count = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
        verts = np.asarray(m.mesh_vert[start : start + count], float)
        local = verts[:: max(1, len(verts) // 2000)]  # the hull needs no more
    elif kind == t.mjGEOM_HFIELD and geom is not None:
        sx, sy = m.hfield_size[m.geom_dataid[geom]][:2]
        local = np.array([[-sx, -sy, 0], [sx, -sy, 0], [sx, sy, 0], [-sx, sy, 0]])
    if local is None:
        return None
    return pos + local @ rot.T


def _hull(points: np.ndarray) -> np.ndarray:
    """Convex hull (k, 2) of 2-D points, counter-clockwise (Andrew's monotone chain)."""
    pts = np.unique(np.round(points, 12), axis=0)
    if len(pts) <= 2:
        return pts

    def half(seq):
        out: list = []
        for p in seq:
            while len(out) >= 2:
                (ax, ay), (bx, by) = out[-1] - out[-2], p - out[-2]
                if ax * by - ay * bx > 0:
                    break
                out.pop()
            out.append(p)
        return out[:-1]

    return np.array(half(pts) + half(pts[::-1]))


__all__: list[str] = [
    "FORCE_FRAMES",
    "Arrows",
    "Footprint",
    "PlanDrawing",
    "draw_topdown",
    "plan_drawing",
    "plan_frames",
    "topdown_figure",
]
