"""Fuzzed inputs: random valid MJCF scenes through `Scene` and `mjstamp check`.

In the spirit of MJX's `test_util.create_mjcf`: random kinematic trees of
bodies with every joint type (free, ball, slide, hinge), every geom type
MuJoCo collides (plane and height field in the worldbody only; sphere,
capsule, ellipsoid, cylinder, box, and meshes as inline `<mesh vertex=...>`
assets), random sizes, masses, poses, contact settings (friction, solref,
solimp, condim, contype/conaffinity, margin, priority, `<pair>`, `<exclude>`),
options (timestep, integrator, solver, cone, gravity, iterations, fluid, flags)
and sometimes motor or position actuators on hinge and slide joints. Every
scene compiles in MuJoCo C; some use what MJX 3.17 lacks (an integrator, a
geom pair, a margin on a mesh), which mjstamp must refuse in one line.

Outcomes, per scene:

- ok: `Scene(path)` builds (and, when checked, `mjstamp check` exits 0);
- rejected: an `MjstampError`, i.e. `mjstamp check` exits 2 with exactly one
  line `mjstamp: error: ...` on stderr;
- unhealthy: `mjstamp check` exits 1 (a legitimate verdict on a scene);
- crash: any other exception, a traceback on stderr, or a rejection that is
  not one line.

With `--solve K` the first K scenes that build (and have a joint) also go
through a tiny solve in-process (`generic_task`, `SOLVE_CONFIG`): ok (a
`SolveResult`), rejected (an `MjstampError` of one line) or crash.

Usage: python -m tests.stress.fuzz --scenes N [--check K] [--solve K] [--cli N] [--seed S]
[--json]
(`--print-scene I` prints scene I's MJCF for seed S, to reproduce an example).
Scene i of seed S is `scene_mjcf(S, i)`. The CLI's own arguments will be fuzzed
by a `cli` section of this file; each section is one function returning a dict,
and `main` merges them into one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import subprocess
import sys
import tempfile
import time
import traceback
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

# Geom types a body may carry; planes and height fields are static ground only.
BODY_GEOMS = ("sphere", "capsule", "ellipsoid", "cylinder", "box", "mesh")
# "implicit" and "discrete" compile in MuJoCo C but are not stepped by MJX 3.17.
INTEGRATORS = ("Euler", "RK4", "implicitfast", "implicit", "discrete")
CONDIMS = (1, 3, 4, 6)
# Option flags a scene may flip: (attribute, value).
FLAGS = (
    ("contact", "disable"), ("gravity", "disable"), ("warmstart", "disable"),
    ("filterparent", "disable"), ("frictionloss", "disable"), ("limit", "disable"),
    ("actuation", "disable"), ("energy", "enable"), ("sleep", "enable"),
)
CHECK_ARGS = ("--particles", "4", "--horizon", "20", "--json")
OUTCOMES = ("ok", "rejected", "unhealthy", "crash")
# The tiny solve: a few particles and iterations, enough to compile and run every
# stage of `mjstamp.solve` (screen, calibration, STAMP's two phases, decode
# and C verification) once; min_iters > the iterations, so no phase ends early.
SOLVE_CONFIG = {"particles": 4,
                "stamp": {"svgd_max_iters": 2, "sgd_max_iters": 2, "min_iters": 100},
                "screen": {"candidates": 1}, "verify": {"repair": False},
                "calibration": {"allow_unfaithful": True}}
SOLVE_HORIZON = 20
SOLVE_OUTCOMES = ("ok", "rejected", "crash")


def _fmt(values) -> str:
    return " ".join(f"{float(v):.4g}" for v in np.atleast_1d(values))


def _p(rng: np.random.Generator, prob: float) -> bool:
    return bool(rng.random() < prob)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / max(np.linalg.norm(v), 1e-9)


def _axis(rng: np.random.Generator) -> str:
    """A coordinate axis mostly (as scenes are written), else a random unit vector."""
    if _p(rng, 0.6):
        return ("1 0 0", "0 1 0", "0 0 1")[rng.integers(3)]
    return _fmt(_unit(rng))


def _contact_attrs(rng: np.random.Generator) -> dict[str, str]:
    """Random contact settings of a geom (each present or left at its default)."""
    a = {}
    if _p(rng, 0.5):
        a["friction"] = _fmt([rng.uniform(0, 2), rng.uniform(0, 0.05), rng.uniform(0, 0.01)]
                             [: rng.integers(1, 4)])
    if _p(rng, 0.4):
        if _p(rng, 0.5):
            a["solref"] = _fmt([rng.uniform(0.002, 0.1), rng.uniform(0.1, 2)])
        else:  # direct stiffness and damping
            a["solref"] = _fmt([-rng.uniform(100, 1e5), -rng.uniform(1, 500)])
    if _p(rng, 0.3):
        dmin = rng.uniform(0.5, 0.95)
        a["solimp"] = _fmt([dmin, rng.uniform(dmin, 0.9999), rng.uniform(1e-4, 0.05),
                            rng.uniform(0.1, 0.9), rng.uniform(1, 6)])
    if _p(rng, 0.5):
        a["condim"] = str(CONDIMS[rng.integers(len(CONDIMS))])
    if _p(rng, 0.5):
        a["contype"] = str(rng.integers(0, 4))
        a["conaffinity"] = str(rng.integers(0, 4))
    if _p(rng, 0.1):
        a["margin"] = _fmt(rng.uniform(0.001, 0.02))
    if _p(rng, 0.05):
        a["gap"] = _fmt(rng.uniform(0, 0.005))
    if _p(rng, 0.1):
        a["priority"] = str(rng.integers(0, 3))
    return a


class _Builder:
    """Builds one random scene; names count up so messages can name things."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.root = ET.Element("mujoco", model="fuzz")
        ET.SubElement(self.root, "compiler", autolimits="true", angle="radian")
        self.option = ET.SubElement(self.root, "option")
        self.asset = ET.SubElement(self.root, "asset")
        self.world = ET.SubElement(self.root, "worldbody")
        self.geoms: list[tuple[str, str | None]] = []  # (geom name, body name)
        self.bodies: list[str] = []
        self.joints: list[tuple[str, str]] = []  # (joint name, type)
        self.meshes = 0
        self.hfields = 0
        # One palette per scene, so some scenes stay within what MJX collides.
        k = rng.integers(1, len(BODY_GEOMS) + 1)
        self.palette = tuple(rng.choice(BODY_GEOMS, size=k, replace=False))

    def options(self) -> None:
        rng, o = self.rng, self.option
        o.set("timestep", _fmt(rng.choice([0.002, 0.005, 0.01, 0.02]) * rng.uniform(0.5, 1)))
        weights = np.array([0.35, 0.2, 0.3, 0.1, 0.05])
        o.set("integrator", INTEGRATORS[rng.choice(len(INTEGRATORS), p=weights)])
        o.set("solver", ("PGS", "CG", "Newton")[rng.integers(3)])
        o.set("iterations", str(rng.integers(1, 60)))
        o.set("ls_iterations", str(rng.integers(1, 30)))
        if _p(rng, 0.3):
            o.set("cone", "elliptic")
        if _p(rng, 0.3):
            o.set("gravity", _fmt(rng.normal(0, 1, 3) + [0, 0, -rng.uniform(0, 12)]))
        if _p(rng, 0.2):
            o.set("tolerance", _fmt(10.0 ** rng.uniform(-10, -4)))
        if _p(rng, 0.08):
            o.set("density", _fmt(rng.uniform(0.5, 1.5)))
            o.set("viscosity", _fmt(rng.uniform(0, 2e-5)))
        if _p(rng, 0.05):
            o.set("wind", _fmt(rng.normal(0, 1, 3)))
        if _p(rng, 0.05):
            o.set("noslip_iterations", str(rng.integers(1, 5)))
        if _p(rng, 0.25):
            flag = ET.SubElement(o, "flag")
            for i in rng.choice(len(FLAGS), size=rng.integers(1, 3), replace=False):
                flag.set(*FLAGS[i])
        if _p(rng, 0.3):
            default = ET.SubElement(ET.SubElement(self.root, "default"), "geom")
            for key, value in _contact_attrs(rng).items():
                default.set(key, value)

    def mesh(self, scale: float) -> str:
        """An inline convex-ish point cloud: MuJoCo collides its convex hull."""
        rng = self.rng
        name = f"mesh{self.meshes}"
        self.meshes += 1
        n = rng.integers(5, 21)
        radii = scale * rng.uniform(0.4, 1.0, 3)
        points = np.stack([_unit(rng) for _ in range(n)]) * radii
        attrs = {"name": name, "vertex": _fmt(points.ravel())}
        if _p(rng, 0.15):
            attrs["scale"] = _fmt(rng.uniform(0.5, 1.5, 3))
        ET.SubElement(self.asset, "mesh", attrs)
        return name

    def hfield(self) -> str:
        rng = self.rng
        name = f"hfield{self.hfields}"
        self.hfields += 1
        nrow, ncol = rng.integers(2, 7, 2)
        size = [rng.uniform(0.3, 2), rng.uniform(0.3, 2), rng.uniform(0.01, 0.3),
                rng.uniform(0.01, 0.2)]
        ET.SubElement(self.asset, "hfield", name=name, nrow=str(nrow), ncol=str(ncol),
                      size=_fmt(size), elevation=_fmt(rng.uniform(0, 1, nrow * ncol)))
        return name

    def geom(self, parent: ET.Element, kind: str, body: str | None) -> None:
        rng = self.rng
        name = f"geom{len(self.geoms)}"
        self.geoms.append((name, body))
        s = rng.uniform(0.02, 0.25)
        a = {"name": name, "type": kind}
        if kind == "sphere":
            a["size"] = _fmt(s)
        elif kind in ("capsule", "cylinder"):
            if _p(rng, 0.2):
                a["fromto"] = _fmt(np.concatenate([rng.uniform(-s, s, 3), rng.uniform(-s, s, 3)]))
                a["size"] = _fmt(s * rng.uniform(0.1, 0.5))
            else:
                a["size"] = _fmt([s * rng.uniform(0.2, 1), s * rng.uniform(0.2, 2)])
        elif kind in ("ellipsoid", "box"):
            a["size"] = _fmt(s * rng.uniform(0.2, 1.5, 3))
        elif kind == "mesh":
            a["mesh"] = self.mesh(s)
        elif kind == "plane":
            a["size"] = _fmt([rng.uniform(0.5, 5), rng.uniform(0.5, 5), 0.1]
                             if _p(rng, 0.8) else [0, 0, 1])
        elif kind == "hfield":
            a["hfield"] = self.hfield()
        if "fromto" not in a and _p(rng, 0.5):
            a["pos"] = _fmt(rng.uniform(-0.1, 0.1, 3))
        if "fromto" not in a and kind != "plane" and _p(rng, 0.4):
            a["euler"] = _fmt(rng.uniform(-np.pi, np.pi, 3))
        if body is not None:
            if _p(rng, 0.4):
                a["mass"] = _fmt(rng.uniform(0.05, 5))
            elif _p(rng, 0.3):
                a["density"] = _fmt(rng.uniform(100, 5000))
        a.update(_contact_attrs(rng))
        ET.SubElement(parent, "geom", a)

    def joint(self, body: ET.Element, kind: str) -> None:
        rng = self.rng
        name = f"joint{len(self.joints)}"
        self.joints.append((name, kind))
        a = {"name": name, "type": kind}
        if kind in ("hinge", "slide"):
            a["axis"] = _axis(rng)
            if _p(rng, 0.4):
                half = rng.uniform(0.1, 3) if kind == "hinge" else rng.uniform(0.05, 1)
                a["range"] = _fmt([-half * rng.uniform(0.2, 1), half])
            if _p(rng, 0.2):
                a["stiffness"] = _fmt(rng.uniform(0, 50))
        if kind == "ball" and _p(rng, 0.2):
            a["range"] = _fmt([0, rng.uniform(0.2, 2)])
        if kind != "free" and _p(rng, 0.3):
            a["pos"] = _fmt(rng.uniform(-0.1, 0.1, 3))
        for key, high, prob in (("damping", 2, 0.5), ("armature", 0.1, 0.3),
                                ("frictionloss", 0.5, 0.1)):
            if _p(rng, prob):
                a[key] = _fmt(rng.uniform(0, high))
        ET.SubElement(body, "joint", a)

    def body(self, parent: ET.Element, depth: int, max_depth: int) -> None:
        rng = self.rng
        name = f"body{len(self.bodies)}"
        self.bodies.append(name)
        top = depth == 0
        pos = rng.uniform(-0.5, 0.5, 3) + ([0, 0, rng.uniform(0.1, 1)] if top else 0)
        a = {"name": name, "pos": _fmt(pos)}
        if _p(rng, 0.3):
            a["euler"] = _fmt(rng.uniform(-np.pi, np.pi, 3))
        body = ET.SubElement(parent, "body", a)
        # N.B. a free joint only on a child of the world, alone; a ball ends the stack.
        if top and _p(rng, 0.4):
            self.joint(body, "free")
        else:
            for _ in range(rng.integers(0, 4)):
                kind = ("ball", "slide", "hinge")[rng.choice(3, p=[0.2, 0.35, 0.45])]
                self.joint(body, kind)
                if kind == "ball":
                    break
        if _p(rng, 0.1):
            ET.SubElement(body, "inertial", pos=_fmt(rng.uniform(-0.05, 0.05, 3)),
                          mass=_fmt(rng.uniform(0.1, 2)),
                          diaginertia=_fmt(rng.uniform(1e-3, 1e-2) * rng.uniform(0.6, 1, 3)))
        for _ in range(rng.integers(1, 3)):
            self.geom(body, self.palette[rng.integers(len(self.palette))], name)
        if _p(rng, 0.3):
            ET.SubElement(body, "site", name=f"site_{name}", pos=_fmt(rng.uniform(-0.1, 0.1, 3)))
        # N.B. small trees (chains, a fork now and then): MJX compile time grows with
        # the bodies and the geom pairs, and `check` compiles each scene twice.
        if depth + 1 < max_depth:
            for _ in range(1 + _p(rng, 0.15)):
                self.body(body, depth + 1, max_depth)

    def worldbody(self) -> None:
        rng = self.rng
        if _p(rng, 0.7):
            self.geom(self.world, "plane", None)
            if _p(rng, 0.3):
                self.world[-1].set("euler", _fmt(rng.uniform(-0.3, 0.3, 3)))
        for _ in range(rng.integers(0, 3)):
            kinds = self.palette + (("hfield",) if _p(rng, 0.3) else ())
            self.geom(self.world, kinds[rng.integers(len(kinds))], None)
        if _p(rng, 0.3):
            ET.SubElement(self.world, "site", name="goal", pos=_fmt(rng.uniform(-1, 1, 3)),
                          size=_fmt(rng.uniform(0.01, 0.1)))
        for _ in range(1 + _p(rng, 0.4) + _p(rng, 0.1)):
            self.body(self.world, 0, rng.integers(1, 4))

    def contact(self) -> None:
        rng = self.rng
        contact = ET.Element("contact")
        for _ in range(rng.integers(0, 3) if len(self.geoms) > 1 and _p(rng, 0.3) else 0):
            i, j = rng.choice(len(self.geoms), size=2, replace=False)
            a = {"geom1": self.geoms[i][0], "geom2": self.geoms[j][0]}
            if _p(rng, 0.5):
                a["condim"] = str(CONDIMS[rng.integers(len(CONDIMS))])
            if _p(rng, 0.3):
                a["friction"] = _fmt([rng.uniform(0, 2), rng.uniform(0, 2), 0.005, 1e-4,
                                      1e-4])
            if _p(rng, 0.2):
                a["margin"] = _fmt(rng.uniform(0, 0.01))
            ET.SubElement(contact, "pair", a)
        if len(self.bodies) > 1 and _p(rng, 0.2):
            i, j = rng.choice(len(self.bodies), size=2, replace=False)
            ET.SubElement(contact, "exclude", body1=self.bodies[i], body2=self.bodies[j])
        if len(contact):
            self.root.append(contact)

    def actuators(self) -> None:
        rng = self.rng
        joints = [name for name, kind in self.joints if kind in ("hinge", "slide")]
        if not joints or not _p(rng, 0.4):
            return
        actuator = ET.SubElement(self.root, "actuator")
        for j in rng.choice(joints, size=rng.integers(1, len(joints) + 1), replace=False):
            a = {"name": f"act_{j}", "joint": str(j)}
            if _p(rng, 0.5):
                kind = "motor"
                a["gear"] = _fmt(rng.uniform(0.1, 10))
            else:
                kind = "position"
                a["kp"] = _fmt(rng.uniform(1, 100))
                if _p(rng, 0.3):
                    a["kv"] = _fmt(rng.uniform(0, 5))
            if _p(rng, 0.6):
                high = rng.uniform(0.1, 5)
                a["ctrlrange"] = _fmt([-high, high])
            if _p(rng, 0.2):
                a["forcerange"] = _fmt([-rng.uniform(1, 50), rng.uniform(1, 50)])
            ET.SubElement(actuator, kind, a)

    def anonymise(self) -> None:
        """Drops the names nothing refers to, as hand-written scenes often do."""
        used = {v for e in self.root.iter() if e.tag in ("pair", "exclude", "position", "motor")
                for k, v in e.attrib.items() if k in ("geom1", "geom2", "body1", "body2", "joint")}
        for e in self.root.iter():
            if e.tag in ("geom", "joint", "body") and e.get("name") not in used:
                e.attrib.pop("name", None)

    def build(self) -> str:
        self.options()
        self.worldbody()
        self.contact()
        self.actuators()
        if _p(self.rng, 0.2):
            self.anonymise()
        if not len(self.asset):
            self.root.remove(self.asset)
        ET.indent(self.root)
        return ET.tostring(self.root, encoding="unicode")


def random_mjcf(rng: np.random.Generator) -> str:
    """A random MJCF scene that MuJoCo C compiles (MJX may not support all of it).

    Args:
      rng: the source of randomness; the same state gives the same scene.

    Returns:
      The MJCF XML text, with meshes and height fields inline (no files).
    """
    return _Builder(rng).build()


def scene_mjcf(seed: int, index: int) -> str:
    """Scene `index` of a fuzz run with `seed`: `random_mjcf` on rng (seed, index)."""
    return random_mjcf(np.random.default_rng([seed, index]))


def mjcf_scenes():
    """A hypothesis strategy of `random_mjcf` scenes, one per 64-bit seed."""
    from hypothesis import strategies as st  # a test extra: only the tests import this

    return st.integers(0, 2**64 - 1).map(lambda s: random_mjcf(np.random.default_rng(s)))


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def build_scene(path: str | Path) -> tuple[str, str, bool]:
    """Builds `Scene(path)` in-process; returns (outcome, message, traceback).

    The outcome is "ok", "rejected" (an `MjstampError` of one line) or "crash"
    (any other exception, or an `MjstampError` spanning several lines);
    traceback is whether an exception other than `MjstampError` escaped, which
    the CLI would print as a traceback.
    """
    from mjstamp.scenes import Scene

    try:
        scene = Scene(path)
        scene.length_scale  # noqa: B018 - what check derives its tolerance from
    except Exception as e:  # noqa: BLE001 - any other exception is what the fuzzer hunts
        return _raised(e)
    return "ok", "", False


def _raised(e: Exception) -> tuple[str, str, bool]:
    """(outcome, message, traceback) of an exception a step raised.

    A one-line MjstampError is a rejection; a several-line or empty one, and any
    other exception (named with where it was raised), a crash.
    """
    from mjstamp.errors import MjstampError

    if isinstance(e, MjstampError):
        if "\n" in str(e) or not str(e).strip():
            return "crash", f"MjstampError not on one line: {str(e)!r}", False
        return "rejected", str(e), False
    frame = traceback.extract_tb(e.__traceback__)[-1]
    where = f"{Path(frame.filename).name}:{frame.lineno}"
    return "crash", f"{type(e).__name__} at {where}: {_one_line(e)}", True


def classify_check(code: int, stdout: str, stderr: str) -> tuple[str, str, bool]:
    """Classifies one `mjstamp check --json` run; returns (outcome, message, traceback).

    Exit 0 or 1 must print one JSON object on stdout; exit 2 one line
    `mjstamp: error: ...`, the last on stderr; no exit may leave a traceback.
    """
    if "Traceback" in stderr:
        lines = [ln for ln in stderr.strip().splitlines() if ln.strip()]
        return "crash", f"traceback on stderr: {_one_line(lines[-1])}", True
    if code in (0, 1):
        try:
            report = json.loads(stdout)
        except ValueError:
            return "crash", f"exit {code} without one JSON object on stdout", False
        if code == 0:
            return "ok", "", False
        return "unhealthy", "; ".join(report.get("problems", [])), False
    # N.B. stderr also holds `check`'s status lines, MuJoCo C's warnings and XLA's
    # logs; what `main` prints last is the error, so a message spilling onto
    # more lines shows as lines after the one that starts "mjstamp: error: ".
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    errors = [k for k, ln in enumerate(lines) if ln.startswith("mjstamp: error: ")]
    if code == 2:
        if len(errors) == 1 and errors[0] == len(lines) - 1:
            return "rejected", lines[-1], False
        tail = lines[errors[0]:] if errors else lines[-3:]
        return "crash", f"exit 2 without a one-line error last on stderr: {tail[:3]!r}", False
    return "crash", f"exit {code}: {_one_line(' / '.join(lines[-3:]))}", False


class _Echo(io.StringIO):
    """Captured stderr that passes `check`'s status lines on to `stream` as well."""

    def __init__(self, stream):
        super().__init__()
        self._stream = stream

    def write(self, text: str) -> int:
        if self._stream is not None and text.startswith("[check] "):
            self._stream.write(f"[fuzz]   {text.rstrip()}\n")
            self._stream.flush()
        return super().write(text)


def check_in_process(path: str | Path, *, echo: bool = False) -> tuple[str, str, bool]:
    """`mjstamp.cli.main(["check", path, ...])` in-process, stdout and stderr captured.

    An exception escaping `main` is what would print a traceback in a shell.
    `echo` passes the check's status lines on to this process's stderr.
    """
    from mjstamp.cli import main

    out, err = io.StringIO(), _Echo(sys.stderr if echo else None)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["check", str(path), *CHECK_ARGS])
    except Exception as e:  # noqa: BLE001 - the crash the fuzzer hunts
        frame = traceback.extract_tb(e.__traceback__)[-1]
        where = f"{Path(frame.filename).name}:{frame.lineno}"
        return "crash", f"traceback: {type(e).__name__} at {where}: {_one_line(e)}", True
    return classify_check(code, out.getvalue(), err.getvalue())


def check_subprocess(path: str | Path, *, timeout: float = 1800) -> tuple[str, str, bool]:
    """The `mjstamp` console script of this interpreter on `path`, as a user runs it.

    A check of 4 particles over 20 steps that runs past `timeout` counts as a crash.
    """
    script = Path(sys.executable).with_name("mjstamp")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "mjstamp.cli"]
    try:
        proc = subprocess.run([*cmd, "check", str(path), *CHECK_ARGS], capture_output=True,
                              text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "crash", f"mjstamp check ran past {timeout:g} s", False
    return classify_check(proc.returncode, proc.stdout, proc.stderr)


def _final_distance2(body: int | str, target: np.ndarray):
    """Cost ‖x_T − g‖²: squared distance of the body's centre to a point g at the final step."""
    import jax.numpy as jnp  # N.B. not at import: `main` configures JAX first

    def cost(r):
        goal = jnp.asarray(target, r.scene.dtype)
        return jnp.sum((r.body_pos(body)[:, -1] - goal) ** 2, axis=-1)

    return cost


def _ends_near(body: int | str, target: np.ndarray, radius: float):
    """Success predicate: the body's centre ends within `radius` of the point `target`."""

    def predicate(replay):
        ok = np.linalg.norm(replay.body_pos(body)[:, -1] - target, axis=-1) < radius
        return ok, np.full(len(ok), "", dtype=object)

    return predicate


def generic_task(scene, *, horizon: int = SOLVE_HORIZON, coordinates: int = 3):
    """A task any scene with a joint admits, declared with the public task API.

    θ: the initial velocities, in [−1, 1], of up to `coordinates` joint
    coordinates, one per joint in joint order (a free joint gives vx and vy):
    each joint by its name, or by its id where it has none. Cost: the squared
    distance of the first such joint's body to a point a fifth of the scene's
    size (`Scene.length_scale`) along +x of where it starts, at the final step;
    success: ending within a tenth of the scene's size of it. No sites, no
    symbols: nothing a random scene may lack.

    Returns:
      The `Task`, or None for a scene without joints (nothing to vary).
    """
    import mujoco

    from mjstamp.tasks import Task

    m = scene.m
    free = int(mujoco.mjtJoint.mjJNT_FREE)
    refs = []
    for j in range(m.njnt):
        ref = m.joint(j).name or j
        refs += [(ref, 0), (ref, 1)] if int(m.jnt_type[j]) == free else [ref]
    refs = refs[:coordinates]
    if not refs:
        return None
    body = int(m.jnt_bodyid[0])  # joint 0 is the first coordinate's
    body_ref = m.body(body).name or body
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    target = d.xpos[body] + [0.2 * scene.length_scale, 0.0, 0.0]
    task = Task("fuzz", scene, horizon=horizon)
    task.box("v", low=[-1.0] * len(refs), high=[1.0] * len(refs), initial_qvel=refs)
    task.cost("reach", _final_distance2(body_ref, target), weight=10.0 / scene.length_scale**2)
    task.success(_ends_near(body_ref, target, 0.1 * scene.length_scale))
    return task


def solve_in_process(path: str | Path) -> tuple[str, str, bool]:
    """`generic_task` on `Scene(path)` through the tiny solve (`SOLVE_CONFIG`), in-process.

    Returns (outcome, message, traceback): "ok" (a `SolveResult`; the message
    counts its plans), "rejected" (an `MjstampError` of one line), "skipped"
    (a scene without joints) or "crash" (any other exception, an
    `MjstampError` of several lines, or "Traceback" printed while solving).
    """
    from mjstamp import solve
    from mjstamp.scenes import Scene

    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            task = generic_task(Scene(path))
            if task is None:
                return "skipped", "no joints to vary", False
            result = solve(task, SOLVE_CONFIG, progress=False)
    except Exception as e:  # noqa: BLE001 - any other exception is what the fuzzer hunts
        return _raised(e)
    printed = out.getvalue() + err.getvalue()
    if "Traceback" in printed:
        return "crash", f"printed a traceback: {_one_line(printed[-300:])}", True
    ok = np.asarray(result.verified.ok)
    return "ok", f"{int(ok.sum())}/{len(ok)} plans verified", False


def fuzz_scenes(n: int, *, check: int = 0, subprocesses: int = 2, solve: int = 0,
                seed: int = 0, examples: int = 5, progress=None) -> dict:
    """Tries `n` random scenes through `Scene`, the first `check` through `mjstamp check`.

    The first `solve` scenes that build a `Scene` and have a joint also go
    through the tiny solve (`solve_in_process`).

    Args:
      n: scenes to build in-process (cheap: no compilation).
      check: of those, how many (the first ones) also go through `mjstamp check
        --particles 4 --horizon 20 --json` (each compiles MJX rollouts: tens of
        seconds to minutes on a CPU).
      subprocesses: of the checked scenes, how many (the first ones) run the
        `mjstamp` console script in a subprocess instead of `cli.main` in-process.
      solve: how many scenes (the first that build, with a joint) go through
        `generic_task` and `mjstamp.solve(task, SOLVE_CONFIG)` in-process
        (each compiles a solve: about a minute on a CPU).
      seed: scene i is `scene_mjcf(seed, i)`.
      examples: how many crash messages to keep.
      progress: callable(str) for status lines, or None.

    Returns:
      A JSON-ready dict: scenes_tried, scenes_checked, crashes, tracebacks
      (crashes where an exception escaped: a traceback in a shell),
      one_line_rejections, outcomes ({outcome: count} over the scenes, a
      checked scene counted by its check), scene_outcomes (the `Scene` pass
      alone), examples ([{seed, index, stage, message}]), checked (the verdict
      of each checked scene: [{index, via, outcome, message, wall_s}]),
      scenes_solved, solve_outcomes ({ok, rejected, crash}: count), solved
      ([{index, outcome, message, wall_s}]), solve_skipped (indices of built
      scenes without joints passed over) and wall_s. crashes, tracebacks and
      one_line_rejections count the solves' too.
    """
    say = progress or (lambda _: None)
    t0 = time.perf_counter()
    final = {k: 0 for k in OUTCOMES}
    built = {k: 0 for k in ("ok", "rejected", "crash")}
    crashes = tracebacks = rejections = checked = 0
    kept: list[dict] = []
    verdicts: list[dict] = []
    solves = {k: 0 for k in SOLVE_OUTCOMES}
    solved: list[dict] = []
    skipped: list[int] = []
    with tempfile.TemporaryDirectory(prefix="mjstamp-fuzz-") as tmp:
        for i in range(n):
            path = Path(tmp) / f"scene_{seed}_{i}.xml"
            path.write_text(scene_mjcf(seed, i))
            outcome, message, had_tb = build_scene(path)
            built[outcome] += 1
            scene_built = outcome == "ok"
            stage = "Scene"
            if i < check:
                via = "subprocess" if i < subprocesses else "in-process"
                say(f"scene {i}: Scene {outcome}; mjstamp check ({via})")
                stage, t1 = f"check ({via})", time.perf_counter()
                if i < subprocesses:
                    c_outcome, c_message, c_tb = check_subprocess(path)
                else:
                    c_outcome, c_message, c_tb = check_in_process(path, echo=progress is not None)
                checked += 1
                if outcome == "crash" and c_outcome != "crash":
                    # The CLI got past what crashed in-process: keep the Scene's crash.
                    stage = "Scene"
                else:
                    outcome, message, had_tb = c_outcome, c_message, c_tb
                verdicts.append({"index": i, "via": via, "outcome": c_outcome,
                                 "message": c_message.replace(tmp + "/", "")[:400],
                                 "wall_s": round(time.perf_counter() - t1, 1)})
            final[outcome] += 1
            rejections += outcome == "rejected"
            tracebacks += had_tb
            if outcome == "crash":
                crashes += 1
                if len(kept) < examples:
                    kept.append({"seed": seed, "index": i, "stage": stage,
                                 "message": message.replace(tmp + "/", "")})
            if outcome in ("crash", "rejected", "unhealthy") and i < check:
                say(f"scene {i}: {outcome}: {message[:200]}")
            if scene_built and len(solved) < solve:
                say(f"scene {i}: tiny solve")
                t1 = time.perf_counter()
                s_outcome, s_message, s_tb = solve_in_process(path)
                s_message = s_message.replace(tmp + "/", "")
                if s_outcome == "skipped":
                    skipped.append(i)
                else:
                    solves[s_outcome] += 1
                    solved.append({"index": i, "outcome": s_outcome, "message": s_message[:400],
                                   "wall_s": round(time.perf_counter() - t1, 1)})
                    rejections += s_outcome == "rejected"
                    tracebacks += s_tb
                    if s_outcome == "crash":
                        crashes += 1
                        if len(kept) < examples:
                            kept.append({"seed": seed, "index": i, "stage": "solve",
                                         "message": s_message})
                say(f"scene {i}: solve {s_outcome}: {s_message[:200]}")
            if (i + 1) % 50 == 0 or i + 1 == n:
                say(f"{i + 1}/{n} scenes: {final}")
    return {
        "scenes_tried": n,
        "scenes_checked": checked,
        "crashes": crashes,
        "tracebacks": tracebacks,
        "one_line_rejections": rejections,
        "outcomes": final,
        "scene_outcomes": built,
        "examples": kept,
        "checked": verdicts,
        "scenes_solved": len(solved),
        "solve_outcomes": solves,
        "solved": solved,
        "solve_skipped": skipped,
        "seed": seed,
        "check_args": list(CHECK_ARGS),
        "solve_config": {**SOLVE_CONFIG, "horizon": SOLVE_HORIZON},
        "wall_s": round(time.perf_counter() - t0, 1),
    }


# Worst difference allowed per field against C: C's analytic routines are ported
# to rounding; its GJK/EPA pairs (mjc_Convex) stop at its own ccd_tolerance.
CONTACT_TOL = {"analytic": 1e-9, "ccd": 1e-6}
_CCD = {"ellipsoid", "mesh"}


def _contact_tolerance(pair: str) -> float:
    a, b = pair.split("-")
    convex = ({a, b} & _CCD or "cylinder" in (a, b) and {a, b} - {"plane", "sphere"})
    return CONTACT_TOL["ccd" if convex else "analytic"]


def _states(m, rng: np.random.Generator, n: int = 24, steps: int = 60) -> np.ndarray:
    """(n, nq) states along C rollouts from random velocities: bodies meet and rest."""
    import mujoco

    d = mujoco.MjData(m)
    out = []
    for _ in range(4):
        mujoco.mj_resetData(m, d)
        d.qvel[:] = rng.uniform(-2, 2, size=m.nv)
        for t in range(steps):
            mujoco.mj_step(m, d)
            if not np.isfinite(d.qpos).all():
                break
            if t % (steps // (n // 4)) == 0:
                out.append(d.qpos.copy())
    return np.array(out[:n]).reshape(-1, m.nq)


def fuzz_contacts(n: int, *, seed: int = 0, progress=None) -> dict:
    """Each scene that builds: its contacts in MJX against C's at states along C rollouts.

    Per geom-type pair over all scenes: the states whose number of active
    contacts differs, and the worst field difference, against `CONTACT_TOL`.
    Scenes with a geom gap are counted apart (MJX ignores `gap`: it includes
    contacts up to the margin, C up to margin - gap). Every port is measured:
    `contacts.exact_meshes()` is on (mesh pairs MJX collides itself by default
    use C's GJK/EPA here).
    """
    import mujoco

    from mjstamp import colliders
    from mjstamp.colliders import compare
    from mjstamp.scenes import Scene

    colliders.exact_meshes()

    say = progress or (lambda _msg: None)
    rng = np.random.default_rng(seed)
    pairs: dict[str, dict] = {}
    compared, gapped, t0 = 0, 0, time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i, xml in enumerate(mjcf_scenes_n(seed, n)):
            path = Path(tmp) / f"scene_{i}.xml"
            path.write_text(xml)
            if build_scene(path)[0] != "ok":
                continue
            m = Scene(path).m_grad  # N.B. its solver is one MJX takes; contacts are the same
            if m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT or m.nv == 0:
                continue
            if (m.geom_gap > 0).any() or (m.npair and (m.pair_gap > 0).any()):
                gapped += 1
                continue
            states = _states(m, rng)
            if not len(states):
                continue
            compared += 1
            for name, r in compare.compare_states(m, states).items():
                row = pairs.setdefault(name, {"states": 0, "count_mismatches": 0, "dist": 0.0,
                                              "pos": 0.0, "frame": 0.0, "examples": []})
                row["states"] += r.draws
                row["count_mismatches"] += r.count_mismatches
                for f in ("dist", "pos", "frame"):
                    row[f] = max(row[f], getattr(r, f))
                tol = _contact_tolerance(name)
                if (r.count_mismatches or max(r.dist, r.pos, r.frame) > tol) and len(
                        row["examples"]) < 3:
                    row["examples"].append(i)
            if (i + 1) % 20 == 0:
                say(f"contacts: {i + 1}/{n} scenes, {compared} compared")
    for name, row in pairs.items():
        row["tolerance"] = _contact_tolerance(name)
        row["within"] = (row["count_mismatches"] == 0
                         and max(row["dist"], row["pos"], row["frame"]) <= row["tolerance"])
    return {"contact_scenes_compared": compared, "contact_scenes_with_gap": gapped,
            "contact_pairs": dict(sorted(pairs.items())),
            "contact_mismatched_pairs": sorted(k for k, v in pairs.items() if not v["within"]),
            "contact_wall_s": round(time.perf_counter() - t0, 1)}


def mjcf_scenes_n(seed: int, n: int):
    """The first n scenes of seed `seed` (`scene_mjcf`)."""
    return (scene_mjcf(seed, i) for i in range(n))


def main(argv: list[str] | None = None) -> int:
    """Runs the fuzz sections and prints their merged report; exit 1 on any crash."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=100, help="random scenes to build")
    parser.add_argument("--check", type=int, default=0,
                        help="of those, how many also go through `mjstamp check`")
    parser.add_argument("--subprocess", type=int, default=2, dest="subprocesses",
                        help="of the checked, how many via the console script")
    parser.add_argument("--solve", type=int, default=0, metavar="K",
                        help="of the scenes that build, how many (the first K with a joint) "
                             "go through a tiny solve in-process")
    parser.add_argument("--contacts", type=int, default=0, metavar="N",
                        help="of the scenes, how many (that build) compare their contacts "
                             "in MJX with MuJoCo C's at states along C rollouts")
    parser.add_argument("--cli", type=int, default=0, metavar="N",
                        help="random command lines to try (tests/stress/fuzz_cli.py)")
    parser.add_argument("--cli-subprocesses", type=int, default=20, metavar="K",
                        help="of the rejected command lines, how many to rerun as processes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="one JSON object on stdout")
    parser.add_argument("--print-scene", type=int, metavar="I",
                        help="print scene I's MJCF for --seed and exit")
    args = parser.parse_args(argv)
    if args.print_scene is not None:
        print(scene_mjcf(args.seed, args.print_scene))
        return 0
    if args.scenes < 0 or args.check < 0 or args.solve < 0:
        parser.error("--scenes, --check and --solve must be >= 0")

    import mjstamp

    mjstamp.configure()  # the CLI's settings, so in-process Scenes match what `check` builds

    def say(msg: str) -> None:
        print(f"[fuzz] {msg}", file=sys.stderr, flush=True)

    report = {"benchmark": "fuzz"}
    report.update(fuzz_scenes(args.scenes, check=min(args.check, args.scenes),
                              subprocesses=args.subprocesses, solve=args.solve,
                              seed=args.seed, progress=say))
    if args.contacts:
        report.update(fuzz_contacts(args.contacts, seed=args.seed, progress=say))
    if args.cli:
        from tests.stress.fuzz_cli import fuzz_cli  # noqa: PLC0415

        cli = fuzz_cli(args.cli, seed=args.seed, subprocesses=args.cli_subprocesses, say=say)
        report.update(cli)
        # N.B. the totals cover both sections; scene_* and cli_* keep them apart.
        report["crashes"] += cli["cli_crashes"]
        report["tracebacks"] += cli["cli_tracebacks"]
        report["one_line_rejections"] += cli["cli_one_line_rejections"]
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        for key, value in report.items():
            print(f"{key:20} {value}")
    return 1 if report["crashes"] else 0


if __name__ == "__main__":
    sys.exit(main())
