"""Plan playback in meshcat: live in a browser, or as one standalone HTML page.

The plans of a results directory play one after another on one timeline
(`Segment`s): each is replayed from its saved MuJoCo C states, holds its final
state for a moment, and hands over to the next. While a plan plays, the paths
of the task's `display.trace` bodies are drawn as lines and the contact force
of each `display.force` pair as an arrow (STAMP Fig. 6). Forces are not saved:
`mjstamp.geometry.replay_frames` reads them, with the poses, from one
`mj_forward` per shown state (its velocity and the control of the step from it),
as the PNG figures do.

The scene and animation are a list of meshcat commands; `play` sends them to
a meshcat server, `write_html` packs them, with meshcat's viewer script, into
a page that needs no server and no network.

References:
  STAMP Fig. 6 (pushing force arrows), Fig. 7 (billiards paths).
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import html as html_lib
import math
import os
import selectors
import subprocess
import sys
import time
import webbrowser
from pathlib import Path

import meshcat
import mujoco
import numpy as np
import umsgpack
import zmq
from meshcat import geometry as mg
from meshcat.animation import Animation, AnimationClip, AnimationTrack
from meshcat.commands import SetAnimation, SetObject, SetTransform
from meshcat.visualizer import ViewerWindow

from mjstamp import geometry, verify
from mjstamp.errors import MjstampError, valid_list
from mjstamp.fileio import write_atomic
from mjstamp.results import Results, load_results
from mjstamp.viz import scene as scene_mod
from mjstamp.viz.results import select_plans

FORCE_COLOR = 0xFF8C00  # orange: stands out on the grey and green tables of the tasks
# A typical force (90th percentile of the nonzero ones shown) draws an arrow this fraction of
# the scene radius; impacts can be 10-100x a steady push, so scaling by the largest would
# shrink every push to nothing. Longer arrows are capped at ARROW_CAP times that length.
ARROW_FRACTION = 0.2
ARROW_CAP = 2.0
SERVER_START_S = 30.0  # a cold Python start of tornado + zmq takes ~1 s; be patient on CI
GHOST_OPACITY = 0.25  # perturbed replays: see-through copies of the moving bodies
# A body gets see-through copies only where a perturbed replay moves some point of it this
# fraction of the scene radius off its nominal pose (0.5 mm on the Jaco's table, under a
# pixel of an 800-pixel view): a copy inside its opaque original cannot be seen, and a
# robot arm that follows its servos whatever the brick does would copy every link's mesh
# into the page once per replay (8 replays of 2 Jaco plans: 8.5 MB, 1.6 MB without).
GHOST_MIN_PARTING = 1e-3


@dataclasses.dataclass(frozen=True)
class Segment:
    """One plan on the playback timeline.

    Attributes:
      particle: particle index of the plan.
      task_plan: its task plan.
      verified: whether it verified in MuJoCo C.
      cost: its MJX cost.
      start: time (s) its motion starts.
      end: time (s) its motion ends (it then holds its last state).
      robustness: its robustness score (None: not scored).
      perturbed: how many of its perturbed replays play alongside, as translucent copies.
    """

    particle: int
    task_plan: str
    verified: bool
    cost: float
    start: float
    end: float
    robustness: float | None = None
    perturbed: int = 0

    def label(self) -> str:
        """One line: particle, task plan, cost, robustness and time window."""
        mark = "" if self.verified else " (failed)"
        score = "" if self.robustness is None else f", robustness {self.robustness:.2f}"
        ghosts = f", {self.perturbed} perturbed replays" if self.perturbed else ""
        return (f"particle {self.particle}: {self.task_plan}{mark}, cost {self.cost:.3g}"
                f"{score}{ghosts}, {self.start:.1f}-{self.end:.1f} s")


@dataclasses.dataclass
class Playback:
    """What `play` built and where it shows.

    Attributes:
      commands: the meshcat commands (scene, lines, arrows, animation).
      segments: the plans on the timeline, in order.
      force_scale: arrow length (m) per newton, or None without forces to draw. Arrows
        are capped at `ARROW_CAP` times a typical force's length.
      force_names: the drawn forces, e.g. "pusher on block".
      perturbed: perturbed replays shown per plan (translucent copies; 0: none).
      url: address of the live viewer (None for HTML only).
      html: the HTML page written (None for live playback).
      visualizer: the connected `meshcat.Visualizer` (live only).
    """

    commands: list
    segments: list[Segment]
    force_scale: float | None
    force_names: str = ""
    perturbed: int = 0
    url: str | None = None
    html: Path | None = None
    visualizer: meshcat.Visualizer | None = None
    _server: subprocess.Popen | None = dataclasses.field(default=None, repr=False)

    def close(self) -> None:
        """Stops the live meshcat server (no-op for HTML)."""
        if self.visualizer is not None:
            self.visualizer.window.close()
            self.visualizer = None
        if self._server is not None and self._server.poll() is None:
            self._server.terminate()
            try:
                self._server.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._server.kill()
                self._server.wait()
        self._server = None


class ServerUnavailable(MjstampError):
    """The meshcat server could not start; `html` is the page written instead."""

    def __init__(self, message: str, html: Path | None):
        super().__init__(message)
        self.html = html


# ----------------------------------------------------------------------------
# Replaying saved states.


def _states(T: int, stride: int) -> list[int]:
    """Every `stride`-th of the states 0..T (the initial one, then after each step), and T."""
    idx = list(range(0, T + 1, stride))
    if idx[-1] != T:
        idx.append(T)  # always show where the plan ends
    return idx


def _frames(m: mujoco.MjModel, results: Results, row: int, stride: int, pairs) -> geometry.Frames:
    """Poses and contact forces of one plan at every `stride`-th saved state and the last."""
    tr = results.trajectories
    idx = _states(len(tr["qpos"][row]), stride)
    return geometry.replay_frames(
        m, tr["qpos0"][row], tr["qpos"][row],
        qvel0=tr["qvel0"][row] if "qvel0" in tr else None,
        qvel=tr["qvel"][row] if "qvel" in tr else None,
        ctrl=tr["ctrl"][row] if "ctrl" in tr else None,
        pairs=pairs, states=idx,
    )


def _ghost_frames(m: mujoco.MjModel, results: Results, row: int, stride: int,
                  count: int) -> list[geometry.Frames]:
    """Poses of one plan in the first `count` perturbed replays of its robustness score."""
    tr = results.trajectories
    T = len(tr["qpos"][row])
    reps = verify.perturbed_replays(
        m, results.summary.get("robustness"), tr["qpos0"][row],
        tr["qvel0"][row] if "qvel0" in tr else np.zeros(m.nv),
        tr["ctrl"][row] if "ctrl" in tr else None, count, horizon=T,
        where=repr(str(results.path)))
    idx = _states(T, stride)
    return [geometry.replay_frames(m, reps["qpos0"][j], reps["qpos"][j], states=idx)
            for j in range(count)]


# ----------------------------------------------------------------------------
# Building the scene and its animation.


def _js_quat(wxyz) -> list[float]:
    """three.js order (x, y, z, w) of a MuJoCo quaternion."""
    return [float(wxyz[1]), float(wxyz[2]), float(wxyz[3]), float(wxyz[0])]


def _quat_y_to(v: np.ndarray) -> np.ndarray:
    """The wxyz quaternion turning +y (the arrow's axis) onto the unit vector v."""
    dot = float(v[1])
    if dot < -1 + 1e-9:
        return np.array([0.0, 1.0, 0.0, 0.0])  # half turn about x
    q = np.array([1.0 + dot, v[2], 0.0, -v[0]])  # (1 + y.v, y x v)
    return q / np.linalg.norm(q)


def _arrow() -> list[tuple[str, mg.Geometry, np.ndarray]]:
    """Unit arrow along +y from the origin: shaft and head, with their offsets."""
    shaft = mg.Cylinder(0.75, 0.035)
    head = mg.Cylinder(0.25, radiusTop=0.0, radiusBottom=0.09)
    return [("shaft", shaft, scene_mod.translation([0, 0.375, 0])),
            ("head", head, scene_mod.translation([0, 0.875, 0]))]


class _Tracks:
    """Keyframes of one meshcat path, built in time order."""

    def __init__(self):
        self.tracks: dict[str, AnimationTrack] = {}

    def key(self, frame: int, prop: str, jstype: str, value) -> None:
        track = self.tracks.setdefault(prop, AnimationTrack(prop, jstype))
        track.frames.append(int(frame))
        track.values.append(value)

    def clip(self, fps: float, last: int) -> AnimationClip:
        for track in self.tracks.values():
            if track.frames[-1] < last:  # every clip must last as long, or loops drift apart
                track.frames.append(last)
                track.values.append(track.values[-1])
        return AnimationClip(tracks=self.tracks, fps=fps)


def _resolve_pairs(m: mujoco.MjModel, results: Results) -> list[tuple[int, int]]:
    names = [m.geom(i).name for i in range(m.ngeom)]
    pairs = []
    for pair in results.display["force"]:
        ids = []
        for name in pair:
            gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, str(name))
            if gid < 0:
                raise MjstampError(
                    f"{str(results.path)!r}: display force geom {name!r} is not in scene.mjb; "
                    f"valid: {valid_list(n for n in names if n)}"
                )
            ids.append(gid)
        pairs.append((ids[0], ids[1]))
    return pairs


def _resolve_traces(m: mujoco.MjModel, results: Results) -> list[int]:
    out = []
    for name in results.display["trace"]:
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, str(name))
        if b < 0:
            raise MjstampError(
                f"{str(results.path)!r}: display trace body {name!r} is not in scene.mjb; "
                f"valid: {valid_list(m.body(i).name for i in range(1, m.nbody))}"
            )
        out.append(b)
    return out


def _trace_color(m: mujoco.MjModel, b: int) -> int:
    geoms = np.flatnonzero(m.geom_bodyid == b)
    return scene_mod.hex_color(geometry.drawn_rgba(m, "geom", int(geoms[0]))) if len(
        geoms) else FORCE_COLOR


def build_playback(
    results: Results,
    entries: list[dict],
    *,
    hold: float = 0.5,
    max_fps: float = 50.0,
    loop: bool = True,
    perturbed: int = 0,
) -> Playback:
    """The meshcat commands that draw the scene and play `entries` one after another.

    Args:
      results: the opened results directory.
      entries: plans to play (entries of plans.json "plans", see `select_plans`).
      hold: seconds each plan rests on its final state before the next starts.
      max_fps: at most this many keyframes per second (states are subsampled).
      loop: repeat the whole timeline forever (else play it once).
      perturbed: with each plan, play this many of the perturbed replays behind
        its robustness score (`verify.perturbed_replays`) as translucent copies of
        the moving bodies they move off the plan's own (`GHOST_MIN_PARTING`); 0: none.

    Returns:
      A `Playback` holding the commands and the timeline (not shown anywhere yet).

    Raises:
      MjstampError: `perturbed` asked of a directory without robustness scores,
        or more than its plans were scored on.
    """
    perturbed = int(perturbed)
    if perturbed < 0:
        raise MjstampError(f"perturbed replays={perturbed} must be >= 0")
    m = results.model
    dt = results.timestep
    stride = max(1, math.ceil(1.0 / (dt * max_fps)))
    fps = 1.0 / (dt * stride)
    pairs = _resolve_pairs(m, results)
    traces = _resolve_traces(m, results)
    rows = [results.row(int(e["particle"])) for e in entries]
    replays = [_frames(m, results, r, stride, pairs) for r in rows]
    ghosts = [_ghost_frames(m, results, r, stride, perturbed) if perturbed else []
              for r in rows]
    first = replays[0].pose(0)
    commands = scene_mod.scene_commands(m, pose=first)
    _, radius = scene_mod.scene_bounds(m, first)
    magnitudes = np.concatenate([np.linalg.norm(r.force, axis=-1).ravel() for r in replays])
    magnitudes = magnitudes[magnitudes > 0]
    force_scale = None
    if pairs and len(magnitudes):
        force_scale = ARROW_FRACTION * radius / float(np.percentile(magnitudes, 90))

    parted = [_parted(m, frames, g, GHOST_MIN_PARTING * radius)
              for frames, g in zip(replays, ghosts, strict=True)]
    timeline = _Timeline(m, pairs, len(entries), force_scale, ARROW_CAP * ARROW_FRACTION * radius)
    segments = []
    for k, (entry, frames) in enumerate(zip(entries, replays, strict=True)):
        start, end = timeline.add(k, frames, hold_frames=max(1, round(hold * fps)),
                                  ghosts=ghosts[k], ghost_bodies=parted[k])
        commands += _trace_lines(m, k, frames, traces)
        commands += _ghost_objects(m, k, len(ghosts[k]), parted[k])
        score = entry.get("robustness")
        segments.append(Segment(
            particle=int(entry["particle"]), task_plan=str(entry["task_plan"]),
            verified=bool(entry["verified"]), cost=float(entry["cost"]),
            start=start / fps, end=end / fps,
            robustness=None if score is None else float(score), perturbed=len(ghosts[k]),
        ))
    commands += _arrow_objects(m, pairs)
    commands += timeline.commands(fps, loop=loop)
    names = ", ".join(f"{m.geom(a).name} on {m.geom(b).name}" for a, b in pairs)
    return Playback(commands=commands, segments=segments, force_scale=force_scale,
                    force_names=names, perturbed=perturbed)


def _moving(m: mujoco.MjModel) -> list[int]:
    """Bodies that can move (not welded to the world)."""
    return [b for b in range(1, m.nbody) if m.body_weldid[b] != 0]


def _ghost_path(m: mujoco.MjModel, k: int, j: int, b: int):
    """Body b's copy in plan k's perturbed replay j (shown with plan k)."""
    return scene_mod.path_of("plans", f"{k:02d}", "ghosts", f"{j:02d}",
                             scene_mod.body_name(m, b))


def _parted(m: mujoco.MjModel, nominal: geometry.Frames, ghosts: list[geometry.Frames],
            tol: float) -> list[int]:
    """Moving bodies that some perturbed replay moves more than `tol` (m) off the nominal.

    A body's parting at a frame: its origin's distance plus the angle between its two
    orientations times its reach (the farthest point of its geoms from its origin), a
    bound on how far any point of it moved.
    """
    moving = _moving(m)
    if not ghosts or not moving:
        return []
    reach = np.zeros(m.nbody)
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        reach[b] = max(reach[b], float(np.linalg.norm(m.geom_pos[g]) + m.geom_rbound[g]))
    worst = np.zeros(m.nbody)
    for ghost in ghosts:
        shift = np.linalg.norm(ghost.xpos - nominal.xpos, axis=-1)  # (F, nbody)
        dot = np.clip(np.abs(np.sum(ghost.xquat * nominal.xquat, axis=-1)), 0.0, 1.0)
        worst = np.maximum(worst, (shift + 2 * np.arccos(dot) * reach).max(axis=0))
    return [b for b in moving if worst[b] > tol]


def _ghost_objects(m: mujoco.MjModel, k: int, count: int, bodies: list[int]) -> list:
    """See-through copies of `bodies`' shown geoms, one set per perturbed replay."""
    if not count:
        return []
    bodies = set(bodies)
    objs = [o for o in scene_mod.scene_objects(m)
            if o.kind == "geom" and o.visible and o.body in bodies]
    out = []
    for j in range(count):
        for o in objs:
            path = _ghost_path(m, k, j, o.body).append(o.path[-1])
            material = mg.MeshPhongMaterial(color=scene_mod.hex_color(o.rgba),
                                            opacity=GHOST_OPACITY * float(o.rgba[3]),
                                            depthWrite=False)
            out.append(SetObject(mg.Mesh(o.geometry, material), path=path))
            out.append(SetTransform(o.transform, path))
    return out


def _force_path(m: mujoco.MjModel, pair: tuple[int, int]):
    a, b = pair
    return scene_mod.path_of("forces", f"{m.geom(a).name}_on_{m.geom(b).name}")


class _Timeline:
    """Keyframes of the moving bodies, the force arrows and which plan shows, plan by plan."""

    def __init__(self, m: mujoco.MjModel, pairs, plans: int, force_scale: float | None,
                 max_length: float):
        self.m = m
        self.pairs = pairs
        self.force_scale = force_scale
        self.max_length = max_length
        self.bodies = {b: _Tracks() for b in _moving(m)}
        self.ghosts: dict[tuple[int, int, int], _Tracks] = {}  # (plan, replay, body)
        self.arrows = {k: _Tracks() for k in range(len(pairs))}
        self.shown = {k: _Tracks() for k in range(plans)}
        self.plans = plans
        self.next = 0  # first frame of the next plan

    def add(self, k: int, frames: geometry.Frames, *, hold_frames: int,
            ghosts: list[geometry.Frames] = (), ghost_bodies: list[int] = ()) -> tuple[int, int]:
        """Keys plan k's frames, then holds the last; with its perturbed replays' too.

        `ghosts` are the replays' frames, `ghost_bodies` the bodies copied in them.

        Returns (first, last moving frame).
        """
        start, n = self.next, len(frames.states)
        keys = list(range(start, start + n)) + [start + n - 1 + hold_frames]
        states = list(range(n)) + [n - 1]
        for b, tracks in self.bodies.items():
            self._key_body(tracks, keys, states, frames, b)
        for j, ghost in enumerate(ghosts):
            for b in ghost_bodies:
                tracks = self.ghosts.setdefault((k, j, b), _Tracks())
                self._key_body(tracks, keys, states, ghost, b)
        for p, tracks in self.arrows.items():
            self._key_arrow(tracks, keys, frames.force[states, p], frames.point[states, p])
        if self.plans > 1:
            for j, tracks in self.shown.items():
                tracks.key(start, "visible", "bool", j == k)
        self.next = keys[-1] + 1
        return start, start + n - 1

    @staticmethod
    def _key_body(tracks: _Tracks, keys, states, frames: geometry.Frames, b: int) -> None:
        for f, s in zip(keys, states, strict=True):
            tracks.key(f, "position", "vector3", [float(x) for x in frames.xpos[s, b]])
            tracks.key(f, "quaternion", "quaternion", _js_quat(frames.xquat[s, b]))

    def _key_arrow(self, tracks: _Tracks, keys, force: np.ndarray, point: np.ndarray) -> None:
        last_pos, last_q = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]
        for f, vec, at in zip(keys, force, point, strict=True):
            mag = float(np.linalg.norm(vec))
            scale = [1e-6] * 3  # no contact: shrink the arrow to nothing, where it was
            if self.force_scale is not None and mag > 0.0 and not np.isnan(at).any():
                length = min(mag * self.force_scale, self.max_length)
                u = vec / mag
                # The tip touches the contact point: the arrow pushes on b from a's side.
                last_pos = [float(x) for x in at - length * u]
                last_q = _js_quat(_quat_y_to(u))
                scale = [length] * 3
            tracks.key(f, "position", "vector3", last_pos)
            tracks.key(f, "quaternion", "quaternion", last_q)
            tracks.key(f, "scale", "vector3", scale)

    def commands(self, fps: float, *, loop: bool) -> list:
        """The SetAnimation of every track (none when nothing moves)."""
        last = self.next - 1
        animation = Animation(default_framerate=fps)
        for b, tracks in self.bodies.items():
            animation.clips[scene_mod.body_path(self.m, b)] = tracks.clip(fps, last)
        for (k, j, b), tracks in self.ghosts.items():
            animation.clips[_ghost_path(self.m, k, j, b)] = tracks.clip(fps, last)
        for p, tracks in self.arrows.items():
            animation.clips[_force_path(self.m, self.pairs[p])] = tracks.clip(fps, last)
        for k, tracks in self.shown.items():
            if tracks.tracks:
                animation.clips[scene_mod.path_of("plans", f"{k:02d}")] = tracks.clip(fps, last)
        if not animation.clips:
            return []
        # N.B. repetitions=inf (a msgpack double) is three.js's own "loop forever".
        return [SetAnimation(animation, play=True, repetitions=math.inf if loop else 1)]


def _trace_lines(m: mujoco.MjModel, k: int, frames: geometry.Frames, traces) -> list:
    """Plan k's paths of the traced bodies, as lines under plans/<k>."""
    group = scene_mod.path_of("plans", f"{k:02d}")
    out = []
    for b in traces:
        line = frames.xpos[:, b, :].T.astype(np.float32)  # (3, F)
        out.append(SetObject(
            mg.Line(mg.PointsGeometry(line), mg.LineBasicMaterial(color=_trace_color(m, b))),
            path=group.append(f"trace/{scene_mod.body_name(m, b)}"),
        ))
    return out


def _arrow_objects(m: mujoco.MjModel, pairs) -> list:
    """The force arrows' meshes, shrunk to nothing until the animation scales them."""
    out = []
    for pair in pairs:
        base = _force_path(m, pair)
        for name, shape, offset in _arrow():
            path = base.append(name)
            out.append(SetObject(mg.Mesh(shape, mg.MeshPhongMaterial(color=FORCE_COLOR)),
                                 path=path))
            out.append(SetTransform(offset, path))
        out.append(SetTransform(np.diag([1e-6, 1e-6, 1e-6, 1.0]), base))
    return out


# ----------------------------------------------------------------------------
# Standalone HTML.


def _viewer_js() -> str:
    path = Path(meshcat.__file__).parent / "viewer" / "dist" / "main.min.js"
    # N.B. a literal "</script" would end the inline script early.
    return path.read_text(encoding="utf-8").replace("</script", "<\\/script")


_PAGE = """<!DOCTYPE html>
<html>
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
body {{ margin: 0; overflow: hidden; }}
#meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}
#mjstamp-legend {{ position: absolute; left: 8px; top: 8px; max-height: 90vh; overflow: auto;
  font: 13px/1.4 sans-serif; color: #fff; background: rgba(0, 0, 0, 0.45);
  padding: 6px 10px; border-radius: 4px; }}
#mjstamp-legend ol {{ margin: 4px 0; padding-left: 20px; }}
#mjstamp-legend li.current {{ color: #ffd54f; font-weight: bold; }}
</style>
</head>
<body>
<div id="meshcat-pane"></div>
<div id="mjstamp-legend"><b>{heading}</b><ol>{items}</ol>{note}</div>
<script>
{viewer_js}
</script>
<script>
var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
const MJSTAMP_COMMANDS = [
{commands}
];
// Decoded synchronously, in order: meshcat's own static page uses fetch(), whose
// promises may apply an animation before the objects it moves exist.
function mjstampBytes(b64) {{
  const s = atob(b64);
  const out = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
  return out;
}}
let mjstampLoaded = 0;
for (const c of MJSTAMP_COMMANDS) {{
  viewer.handle_command_bytearray(mjstampBytes(c));
  mjstampLoaded++;
}}
document.body.dataset.mjstampLoaded = mjstampLoaded;
const mjstampItems = Array.from(document.querySelectorAll("#mjstamp-legend li"));
function mjstampTick() {{
  const t = viewer.animator.time;
  document.body.dataset.mjstampTime = t.toFixed(3);
  for (const li of mjstampItems) {{
    const on = t >= parseFloat(li.dataset.start) && t < parseFloat(li.dataset.next);
    li.classList.toggle("current", on);
    if (on) document.body.dataset.mjstampSegment = li.dataset.index;
  }}
  requestAnimationFrame(mjstampTick);
}}
// page.html#t=1.5 shows the frozen frame at 1.5 s (to link to a moment, or to test).
const mjstampAt = /[#&]t=([0-9.]+)/.exec(location.hash);
if (mjstampAt) {{
  viewer.animator.pause();
  viewer.animator.seek(parseFloat(mjstampAt[1]));
  viewer.animator.display_progress(parseFloat(mjstampAt[1]));
}}
mjstampTick();
</script>
</body>
</html>
"""


def html_page(playback: Playback, *, title: str) -> str:
    """A self-contained page: meshcat's viewer script and every command, inlined.

    The page sets `data-mjstamp-loaded` (commands applied) and
    `data-mjstamp-time` (animation clock, s) on its body, for tests and scripts.
    """
    encoded = ",\n".join(
        '"' + base64.b64encode(umsgpack.packb(c.lower())).decode("ascii") + '"'
        for c in playback.commands
    )
    segs = playback.segments
    items = "".join(
        f'<li data-index="{i}" data-start="{s.start:.4f}" '
        f'data-next="{f"{segs[i + 1].start:.4f}" if i + 1 < len(segs) else "Infinity"}">'
        f"{html_lib.escape(s.label())}</li>"
        for i, s in enumerate(segs)
    )
    note = ""
    if playback.force_scale is not None:
        note = (f"<div>orange arrows: contact forces ({html_lib.escape(playback.force_names)}), "
                f"1 N = {100 * playback.force_scale:.3g} cm</div>")
    if playback.perturbed:
        note += (f"<div>translucent copies: {playback.perturbed} perturbed replays of each "
                 "plan (draws of its robustness score)</div>")
    return _PAGE.format(
        title=html_lib.escape(title), heading=html_lib.escape(title), items=items,
        note=note, viewer_js=_viewer_js(), commands=encoded,
    )


def _open(results: Results | str | os.PathLike, task: str | None) -> Results:
    if isinstance(results, Results):
        if task is not None and results.task != task:
            raise MjstampError(
                f"{str(results.path)!r} holds plans of task {results.task!r}, not {task!r}"
            )
        return results
    return load_results(results, task=task)


def _title(results: Results) -> str:
    return f"mjstamp {results.task}: {results.path.name}"


def write_html(
    results: Results | str | os.PathLike,
    path: str | os.PathLike,
    *,
    plan: int | list[int] | None = None,
    task_plan: str | None = None,
    task: str | None = None,
    loop: bool = True,
    hold: float = 0.5,
    perturbed: int = 0,
) -> Playback:
    """Writes a standalone HTML page that plays the plans offline.

    Args:
      results: a results directory (or `Results`).
      path: the page to write.
      plan: particle index(es) of the plans to play (see `select_plans`).
      task_plan: play the plans of this task plan.
      task: if given, the task the directory must belong to.
      loop: repeat the timeline forever.
      hold: seconds each plan rests on its final state.
      perturbed: play this many perturbed replays of each plan beside it
        (translucent copies; see `build_playback`).

    Returns:
      The `Playback`, with `html` set to the page written.
    """
    res = _open(results, task)
    target = Path(path)
    if not target.parent.is_dir():
        raise MjstampError(f"cannot write {str(target)!r}: directory "
                           f"{str(target.parent)!r} does not exist")
    playback = build_playback(res, select_plans(res, plan=plan, task_plan=task_plan),
                              loop=loop, hold=hold, perturbed=perturbed)
    page = html_page(playback, title=_title(res)).encode("utf-8")
    try:
        write_atomic(target, lambda f: f.write(page))
    except OSError as e:
        raise MjstampError(f"cannot write {str(target)!r}: {e.strerror or e}") from None
    playback.html = target
    return playback


# ----------------------------------------------------------------------------
# Live meshcat server.


class _Window(ViewerWindow):
    """meshcat's ViewerWindow on a server we started, without its prints, with timeouts."""

    def __init__(self, zmq_url: str, web_url: str, timeout_ms: int = 20000):
        self.server_proc = None
        self.zmq_url = zmq_url
        self.web_url = web_url
        self.zmq_socket = self.context.socket(zmq.REQ)
        # N.B. without a timeout a dead server leaves recv() waiting forever.
        self.zmq_socket.setsockopt(zmq.RCVTIMEO, timeout_ms)
        self.zmq_socket.setsockopt(zmq.LINGER, 0)
        self.zmq_socket.connect(zmq_url)

    def close(self) -> None:
        self.zmq_socket.close()


def start_server(port: int | None = None, timeout: float = SERVER_START_S):
    """Starts a meshcat server process; returns (process, zmq_url, web_url).

    Raises:
      ServerUnavailable: it could not start (e.g. the port is in use); its
        `html` is None here.
    """
    script = Path(__file__).with_name("_server.py")
    args = [sys.executable, "-u", str(script), "-" if port is None else str(port),
            str(os.getpid())]
    try:
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    except OSError as e:
        raise ServerUnavailable(f"cannot run {sys.executable}: {e.strerror or e}", None) from None
    urls: dict[str, str] = {}
    buffer = b""
    deadline = time.monotonic() + timeout
    fd = proc.stdout.fileno()
    with selectors.DefaultSelector() as sel:
        # N.B. raw os.read, not readline: a buffered reader may swallow both lines at
        # once and leave select() waiting for data that already came.
        sel.register(fd, selectors.EVENT_READ)
        while len(urls) < 2:
            while b"\n" in buffer and len(urls) < 2:
                line, buffer = buffer.split(b"\n", 1)
                key, _, value = line.decode("utf-8", "replace").strip().partition("=")
                if key == "error":
                    proc.wait()
                    where = f"port {port}" if port is not None else "any port from 7000"
                    raise ServerUnavailable(f"cannot listen on {where}: {value}", None)
                urls[key] = value
            if len(urls) == 2:
                break
            left = deadline - time.monotonic()
            if left <= 0 or not sel.select(timeout=left):
                proc.kill()
                proc.wait()
                raise ServerUnavailable(f"no answer within {timeout:.0f} s", None)
            chunk = os.read(fd, 4096)
            if not chunk:
                proc.wait()
                raise ServerUnavailable(f"it exited with status {proc.returncode}", None)
            buffer += chunk
    proc.stdout.close()  # the server sends its later output to /dev/null
    return proc, urls["zmq_url"], urls["web_url"]


def play(
    results: Results | str | os.PathLike,
    *,
    plan: int | list[int] | None = None,
    task_plan: str | None = None,
    task: str | None = None,
    html: str | os.PathLike | None = None,
    port: int | None = None,
    open_browser: bool = False,
    loop: bool = True,
    hold: float = 0.5,
    perturbed: int = 0,
) -> Playback:
    """Plays the verified plans of a results directory in meshcat.

    By default one plan per task plan (its least-cost verified plan), one
    after another; `plan` or `task_plan` choose others. Live playback starts
    a meshcat server (kept until `Playback.close()` or the end of this
    process); with `html`, writes a standalone page instead.

    Args:
      results: a results directory (or `Results`).
      plan: particle index(es) of the plans to play.
      task_plan: play the plans of this task plan.
      task: if given, the task the directory must belong to.
      html: write this standalone page instead of starting a server.
      port: web port of the meshcat server (default: the first free from 7000).
      open_browser: open the viewer in the default browser.
      loop: repeat the timeline forever.
      hold: seconds each plan rests on its final state.
      perturbed: play this many perturbed replays of each plan beside it
        (translucent copies; see `build_playback`).

    Returns:
      The `Playback` (`url` for live, `html` for a page).

    Raises:
      MjstampError: bad directory, plan or task plan.
      ServerUnavailable: the server could not start; the page was written
        next to the results (plans.html) instead and `html` says where.
    """
    res = _open(results, task)
    kwargs = dict(plan=plan, task_plan=task_plan, loop=loop, hold=hold, perturbed=perturbed)
    if html is not None:
        return write_html(res, html, **kwargs)
    playback = build_playback(res, select_plans(res, plan=plan, task_plan=task_plan),
                              loop=loop, hold=hold, perturbed=perturbed)
    try:
        proc, zmq_url, web_url = start_server(port)
    except ServerUnavailable as e:
        fallback = res.path / "plans.html"
        try:
            write_html(res, fallback, **kwargs)
        except MjstampError as e2:
            raise ServerUnavailable(f"meshcat server could not start ({e}), and {e2}",
                                    None) from None
        raise ServerUnavailable(
            f"meshcat server could not start ({e}); wrote {fallback} instead", fallback
        ) from None
    window = _Window(zmq_url, web_url)
    vis = meshcat.Visualizer(window=window)
    try:
        for command in playback.commands:
            window.send(command)
    except zmq.ZMQError as e:
        with contextlib.suppress(Exception):
            proc.kill()
        raise ServerUnavailable(f"meshcat server stopped answering: {e}", None) from None
    playback.url, playback.visualizer, playback._server = web_url, vis, proc
    if open_browser:
        webbrowser.open(web_url, new=2)
    return playback
