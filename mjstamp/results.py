"""The results directory: its schema, writing it, loading and checking it, its table.

What `SolveResult.save` and `mjstamp solve --out DIR` write, and `mjstamp.load`,
`mjstamp view` and the figures read, in one place (the solver makes the
summary and the arrays from a solve, `mjstamp.solver.summary`):

    plans.json        the summary (`summarize`): counts, timings, fidelity, the
                      table's rows (`group`), every returned plan; written last,
                      so a directory with one is complete
    particles.npz     one row per particle (`PER_PARTICLE`) and per-iteration
                      diagnostics
    trajectories.npz  the MuJoCo C replay of every returned plan
    scene.mjb         the compiled scene, so a directory plays back without the
                      task's code or MJCF files

`load` is the one check of those files: any damage is one `MjstampError` line
naming the file, what is wrong and what to do. `load_results` opens a
directory as a `Results`; `format_table` prints the table `mjstamp solve` prints.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shlex
import tempfile
from pathlib import Path

import mujoco
import numpy as np

from mjstamp import _moved, parallel
from mjstamp.checkpoint import FILENAME as CHECKPOINT_FILENAME
from mjstamp.checkpoint import task_of as checkpoint_task
from mjstamp.errors import MjstampError, valid_list
from mjstamp.fileio import probe, write_atomic
from mjstamp.scenes.fidelity import describe

__all__ = ["PER_PARTICLE", "ROW_KEYS", "SCHEMA_VERSION", "Results", "check_writable",
           "format_table", "load", "load_model", "load_results", "save", "write"]

# ----------------------------------------------------------------------------
# The schema.

# 2: scene.mjb, qpos0/qvel0/qvel/ctrl in trajectories.npz; 3: config split into task
# and solve settings, fidelity, screen, repaired and source per plan.
SCHEMA_VERSION = 3

# What readers of a results directory rely on (playback, `select_plans`,
# `mjstamp.load`), checked once by `load` and `load_model`; `summarize` and
# `to_arrays` write all of it and more. {key: type}, optional keys checked when
# present.
_SUMMARY = {"task": str, "plans": list, "task_plans": list}
_SUMMARY_OPTIONAL = {"particles": int, "config": dict, "declaration": dict}
_PLAN = {"particle": int, "task_plan": str, "verified": bool, "cost": float}
_PLAN_OPTIONAL = {"predicted_task_plan": str, "repaired": bool, "motion_plan": dict}
_ROW = {"task_plan": str}
# The keys of plans.json's "task_plans" rows: `group`'s rows without their particles.
ROW_KEYS = ("task_plan", "code", "plans", "verified", "repaired", "verified_share",
             "best_cost", "robustness_best", "robustness_median")
# trajectories.npz: required arrays, and the shape of each (symbols bind on first use).
_TRAJECTORIES = ("particle", "qpos0", "qpos")
_TRAJECTORY_SHAPES = {
    "particle": ("rows",), "qpos": ("rows", "T", "nq"), "qpos0": ("rows", "nq"),
    "qvel0": ("rows", "nv"), "qvel": ("rows", "T", "nv"), "ctrl": ("rows", "T", "nu"),
    "xpos": ("rows", "T", "nbody", 3), "timestep": (),
}
#: particles.npz: the arrays with one row per particle (the rest are per iteration).
PER_PARTICLE = ("theta", "svgd_theta", "initial_theta", "cost", "returned", "verified",
                "repaired", "source", "task_plan", "predicted_task_plan")
_FILES = ("particles.npz", "trajectories.npz", "scene.mjb")
_NAME = re.compile(r"[A-Za-z0-9_.-]+")
_KINDS = {dict: "an object", list: "a list", str: "a string", bool: "true/false",
          int: "an integer", float: "a number", type(None): "null"}


def _task_word(task: object) -> str:
    """A task name fit for a suggested command line, else the placeholder TASK."""
    return task if isinstance(task, str) and _NAME.fullmatch(task) else "TASK"


def _rerun(path: Path, task: object) -> str:
    return f"re-run `mjstamp solve {_task_word(task)} --out {shlex.quote(str(path))}`"


def _damaged(file: Path, what: str, task: object) -> MjstampError:
    """One line: the file, what is wrong with it, and the solve that writes it anew."""
    what = " ".join(what.split())  # exception texts may span lines
    return MjstampError(f"{str(file)!r} {what}; {_rerun(file.parent, task)}")


def _is(value: object, kind: type) -> bool:
    """Whether a JSON value is of `kind` (a bool is no number; an integer is a float)."""
    if isinstance(value, bool) and kind is not bool:
        return False
    return isinstance(value, int | float) if kind is float else isinstance(value, kind)


def _check_fields(obj: dict, where: str, required: dict, optional: dict, bad) -> None:
    for key in required:
        if key not in obj:
            bad(f"has no {key!r} in {where}" if where else f"lacks {key!r}")
    for key, kind in {**required, **optional}.items():
        if key in obj and not _is(obj[key], kind):
            label = f"{where}.{key}" if where else repr(key)
            bad(f"has {label} {_KINDS[type(obj[key])]}, not {_KINDS[kind]}")


def _check_summary(plans: Path, summary: dict) -> None:
    """The shape of plans.json that readers rely on (`_SUMMARY` and below)."""
    task = summary.get("task")

    def bad(what: str):
        raise _damaged(plans, what, task)

    _check_fields(summary, "", _SUMMARY, _SUMMARY_OPTIONAL, bad)
    seen = set()
    for i, entry in enumerate(summary["plans"]):
        if not isinstance(entry, dict):
            bad(f"has plans[{i}] {_KINDS[type(entry)]}, not an object")
        _check_fields(entry, f"plans[{i}]", _PLAN, _PLAN_OPTIONAL, bad)
        if entry["particle"] < 0 or entry["particle"] in seen:
            bad(f"has plans[{i}].particle {entry['particle']} "
                + ("twice" if entry["particle"] in seen else "< 0"))
        seen.add(entry["particle"])
    for i, row in enumerate(summary["task_plans"]):
        if not isinstance(row, dict):
            bad(f"has task_plans[{i}] {_KINDS[type(row)]}, not an object")
        _check_fields(row, f"task_plans[{i}]", _ROW, {}, bad)
    display = summary.get("declaration", {}).get("display") or {}
    if not isinstance(display, dict):
        bad(f"has declaration.display {_KINDS[type(display)]}, not an object")
    trace, force = display.get("trace", []), display.get("force", [])
    if not (isinstance(trace, list) and all(isinstance(b, str) for b in trace)):
        bad("has declaration.display.trace that is not a list of body names")
    if not (isinstance(force, list) and all(
            isinstance(p, list) and len(p) == 2 and all(isinstance(g, str) for g in p)
            for p in force)):
        bad("has declaration.display.force that is not a list of [geom, geom] pairs")


# ----------------------------------------------------------------------------
# Writing.


def check_writable(out: str | os.PathLike) -> Path:
    """Creates `out` if needed and checks a file can be written there, up front."""
    path = Path(out)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path, prefix=".write-test-")
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise MjstampError(
            f"results directory {str(path)!r} is not writable: {e.strerror or e}"
        ) from None
    return path


def save(
    out: Path, summary: dict, arrays: dict[str, dict[str, np.ndarray]], *, model=None
) -> list[Path]:
    """Writes plans.json, one .npz per entry of `arrays` and scene.mjb, each atomically.

    scene.mjb is the task's compiled MjModel (meshes and textures included), so
    a results directory plays back without the task's code or MJCF files.
    plans.json is written last: a directory with a plans.json is complete.
    """
    written = []
    if model is not None:
        target = out / "scene.mjb"
        size = mujoco.mj_sizeModel(model)
        buffer = np.empty(size, np.uint8)
        mujoco.mj_saveModel(model, None, buffer)
        write_atomic(target, lambda f: f.write(buffer.tobytes()))
        written.append(target)
    for name, data in arrays.items():
        target = out / f"{name}.npz"
        write_atomic(target, lambda f, d=data: np.savez_compressed(f, **d))
        written.append(target)
    target = out / "plans.json"
    payload = json.dumps({"schema_version": SCHEMA_VERSION, **summary}, indent=2).encode()
    write_atomic(target, lambda f: f.write(payload))
    written.append(target)
    return written


def write(out: str | os.PathLike, summary: dict, arrays: dict[str, dict[str, np.ndarray]], *,
          model=None) -> list[Path]:
    """Writes a solve's results directory: plans.json, the .npz files and scene.mjb.

    Every file is written atomically, plans.json last (a directory with one
    is complete); the solve's checkpoint, now spent, is removed.

    N.B. in a solve over several processes (`mjstamp.parallel.join_processes`)
    every process holds the same result and only process 0 writes.

    Args:
      out: the results directory (created if needed).
      summary: the body of plans.json (`mjstamp.solver.summary.summarize`).
      arrays: {file stem: {name: array}} (`mjstamp.solver.summary.to_arrays`).
      model: the compiled scene, written as scene.mjb.

    Returns:
      The paths written (none on other processes than 0).
    """
    if not parallel.is_lead():
        return []
    out = check_writable(out)
    written = save(out, summary, arrays, model=model)
    # N.B. plans.json is written: the solve is complete, its checkpoint spent.
    (out / CHECKPOINT_FILENAME).unlink(missing_ok=True)
    return written


# ----------------------------------------------------------------------------
# Loading.


def _read_summary(path: Path) -> dict:
    """plans.json, parsed and checked: one MjstampError line for any damage."""
    plans = path / "plans.json"
    if not probe(plans.is_file, path, "results directory "):
        checkpoint = path / "checkpoint.npz"
        if checkpoint.is_file():
            task = _task_word(checkpoint_task(checkpoint))
            raise MjstampError(
                f"{str(path)!r} holds a checkpoint.npz but no plans.json: the solve did not "
                f"finish; `mjstamp solve {task} --resume {shlex.quote(str(path))}` continues it"
            )
        raise MjstampError(f"{str(path)!r} holds no plans.json (not a results directory; "
                           "`mjstamp solve TASK --out DIR` writes one)")
    try:
        raw = plans.read_bytes()
    except OSError as e:
        raise _damaged(plans, f"cannot be read ({e.strerror or e})", None) from None
    text = raw.decode(errors="replace")
    found = re.search(r'"task":\s*"([^"\\]*)"', text)  # the task, even if JSON fails
    try:
        summary = json.loads(raw.decode())
    except (ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError
        raise _damaged(plans, f"is not valid JSON (truncated or overwritten?): {e}",
                       found and found.group(1)) from None
    if not isinstance(summary, dict):
        raise _damaged(plans, f"holds {_KINDS[type(summary)]}, not an object with "
                       "schema_version, task and plans", None)
    version = summary.get("schema_version")
    if version != SCHEMA_VERSION:
        raise MjstampError(
            f"{str(plans)!r} has schema_version {version!r}; this mjstamp reads "
            f"{SCHEMA_VERSION} ({_rerun(path, summary.get('task'))})"
        )
    _check_summary(plans, summary)
    return summary


def _read_npz(file: Path, task: str) -> dict[str, np.ndarray]:
    try:
        f = np.load(file, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - BadZipFile, EOFError, ValueError, OSError...
        raise _damaged(file, f"is truncated or not an .npz archive ({type(e).__name__}: {e})",
                       task) from None
    if not isinstance(f, np.lib.npyio.NpzFile):
        raise _damaged(file, "holds one .npy array, not an .npz archive", task)
    try:
        with f:
            return {k: f[k] for k in f.files}
    except Exception as e:  # noqa: BLE001 - a corrupt member: zlib.error, BadZipFile (CRC)...
        raise _damaged(file, f"is corrupt ({type(e).__name__}: {e})", task) from None


def _shape_error(arrays: dict, dims: dict, bound: set[str]) -> str | None:
    """What is wrong with the shapes of trajectories.npz's arrays, or None.

    Args:
      arrays: the arrays.
      dims: sizes of the symbols in `_TRAJECTORY_SHAPES` known so far; filled
        in by the first array that has each.
      bound: the symbols whose sizes come from scene.mjb (named in the error).
    """
    for key, spec in _TRAJECTORY_SHAPES.items():
        if key not in arrays:
            continue
        a = arrays[key]
        numeric = "iu" if key == "particle" else "fiu"
        if a.dtype.kind not in numeric:
            return f"has {key} of dtype {a.dtype}, not numbers"
        expected = f"has {key} of shape {a.shape}, not ({', '.join(map(str, spec))})"
        if a.ndim != len(spec):
            return expected
        for size, sym in zip(a.shape, spec, strict=True):
            want = sym if isinstance(sym, int) else dims.setdefault(sym, size)
            if size != want and isinstance(sym, int):
                return expected
            if size != want:
                if sym in bound:
                    return (f"has {key} of shape {a.shape} but scene.mjb has {sym}={want} "
                            "(files from different runs?)")
                return (f"has {key} of shape {a.shape}, where {sym}={want} "
                        "(files from different runs?)")
    if dims.get("T") == 0:
        return "has trajectories of no steps"
    if "timestep" in arrays and not float(arrays["timestep"]) > 0:
        return f"has timestep {float(arrays['timestep'])}, not > 0"
    return None


def load(out: str | os.PathLike) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """Loads what `save` wrote: (plans.json contents, {npz name: arrays}).

    The one check of a results directory's files (playback and `mjstamp.load`
    go through here and `load_model`): every damage is one `MjstampError`
    line naming the file, what is wrong and what to do.

    Returns:
      The summary and {"particles": ..., "trajectories": ...}.

    Raises:
      MjstampError: no plans.json (with a checkpoint.npz: an unfinished
        solve), plans.json not JSON, of another schema version or of the wrong
        shape; a file missing, truncated, not an .npz, missing arrays or with
        arrays of the wrong shape (fewer rows than plans.json's plans).
    """
    path = Path(out)
    summary = _read_summary(path)
    task = summary["task"]
    missing = [name for name in _FILES if not (path / name).is_file()]
    if missing:
        raise MjstampError(f"{str(path)!r} lacks {valid_list(missing)} (an incomplete copy?); "
                           f"{_rerun(path, task)}")
    listed = sorted(e["particle"] for e in summary["plans"])

    file = path / "particles.npz"
    particles = _read_npz(file, task)
    count = summary.get("particles")
    for key in PER_PARTICLE:
        if key not in particles:
            continue
        a = particles[key]
        if a.ndim == 0:
            raise _damaged(file, f"has {key} of shape (), not one row per particle", task)
        n = a.shape[0]
        count = n if count is None else count  # no count in plans.json: the first sets it
        if n != count or (listed and n <= listed[-1]):
            raise _damaged(file, f"has {key} of {n} rows, but plans.json has " + (
                f"{count} particles" if n != count else f"a plan of particle {listed[-1]}"),
                task)

    file = path / "trajectories.npz"
    traj = _read_npz(file, task)
    absent = [k for k in _TRAJECTORIES if k not in traj]
    if absent:
        raise _damaged(file, f"lacks {valid_list(absent)}", task)
    error = _shape_error(traj, {}, set())
    if error:
        raise _damaged(file, error, task)
    unsaved = sorted(set(listed) - set(traj["particle"].tolist()))
    if unsaved:
        raise _damaged(file, f"has no trajectory of particle {valid_list(unsaved)}, which "
                       "plans.json lists (fewer rows than plans?)", task)
    return summary, {"particles": particles, "trajectories": traj}


def load_model(out: str | os.PathLike, *, trajectories: dict[str, np.ndarray] | None = None,
               task: str | None = None) -> mujoco.MjModel:
    """The compiled scene saved with a results directory (scene.mjb).

    Args:
      out: the results directory.
      trajectories: its trajectories.npz arrays (from `load`), whose sizes
        (nq, nv, nu, nbody) must be the scene's.
      task: its task, for the advice in errors.

    Raises:
      MjstampError: no scene.mjb, not a MuJoCo model, or another scene's.
    """
    path = Path(out) / "scene.mjb"
    if not path.is_file():
        raise MjstampError(f"{str(path.parent)!r} holds no scene.mjb (not a results directory; "
                           f"{_rerun(path.parent, task)})")
    # N.B. MuJoCo prints why a model file is unreadable on stderr (a second line
    # and a blank one); the warning handler puts it into our one line instead.
    warnings: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(warnings.append)
    try:
        m = mujoco.MjModel.from_binary_path(str(path))
    except Exception as e:  # noqa: BLE001 - MuJoCo raises a bare Exception/ValueError
        why = "; ".join(warnings) or str(e)
        raise _damaged(path, f"is not a readable MuJoCo model ({why})", task) from None
    finally:
        mujoco.set_mju_user_warning(previous)
    if trajectories is not None:
        sizes = {"nq": m.nq, "nv": m.nv, "nu": m.nu, "nbody": m.nbody}
        error = _shape_error(trajectories, dict(sizes), set(sizes))
        if error:
            raise _damaged(path.parent / "trajectories.npz", error, task)
    return m


@dataclasses.dataclass(frozen=True)
class Results:
    """What `mjstamp solve --out DIR` wrote, as `mjstamp.load` and playback open it.

    Attributes:
      path: the directory.
      summary: contents of plans.json.
      model: the compiled scene (scene.mjb).
      trajectories: arrays of trajectories.npz: particle (r,), qpos0 (r, nq),
        qvel0 (r, nv), qpos (r, T, nq), qvel (r, T, nv), ctrl (r, T, nu), ...
    """

    path: Path
    summary: dict
    model: mujoco.MjModel
    trajectories: dict[str, np.ndarray]

    @property
    def task(self) -> str:
        """Name of the task that wrote the directory."""
        return str(self.summary.get("task", "?"))

    @property
    def display(self) -> dict:
        """Drawing hints of the task: {"trace": [body], "force": [[geom_a, geom_b]]}."""
        hints = self.summary.get("declaration", {}).get("display") or {}
        return {"trace": list(hints.get("trace", [])), "force": list(hints.get("force", []))}

    @property
    def timestep(self) -> float:
        """Seconds between two saved states."""
        if "timestep" in self.trajectories:
            return float(self.trajectories["timestep"])
        return float(self.model.opt.timestep)

    def row(self, particle: int) -> int:
        """Index in trajectories.npz of a returned particle's plan."""
        rows = np.flatnonzero(self.trajectories["particle"] == particle)
        if len(rows) == 0:
            raise MjstampError(
                f"{str(self.path)!r}: particle {particle} has no saved trajectory; valid: "
                + valid_list(self.trajectories["particle"].tolist())
            )
        return int(rows[0])


def load_results(path: str | os.PathLike, *, task: str | None = None) -> Results:
    """Opens a results directory (`mjstamp.load`), checking it is complete and current.

    Args:
      path: directory written by `mjstamp solve TASK --out DIR`.
      task: if given, the task the directory must belong to.

    Raises:
      MjstampError: the directory does not exist or belongs to another task;
        any damage to its files (`load`, `load_model`: one line
        naming the file, what is wrong and what to do).
    """
    path = Path(path)
    if not probe(path.exists, path, "results directory "):
        raise MjstampError(f"results directory {str(path)!r} does not exist")
    if not path.is_dir():
        raise MjstampError(f"{str(path)!r} is not a directory (expected a results directory)")
    summary, arrays = load(path)
    if task is not None and summary["task"] != task:
        raise MjstampError(
            f"{str(path)!r} holds plans of task {summary['task']!r}, not {task!r}"
        )
    traj = arrays["trajectories"]
    m = load_model(path, trajectories=traj, task=summary["task"])
    return Results(path=path, summary=summary, model=m, trajectories=traj)


# ----------------------------------------------------------------------------
# The table.


def _chaos_note(verdict: dict) -> str:
    """', within the scene's own chaos (...)' when MJX was judged by C's spread."""
    if verdict.get("judged_by") != "chaos":
        return ""
    return (f", over it but within the scene's own chaos: C against itself nudged by 1e-9 m "
            f"p95 {verdict['chaos_p95_m']:.2g} m")


def _parting_note(verdict: dict | None) -> str:
    """', parting at box-box contacts ('crate'/'ledge')' from a verdict's JSON view."""
    pairs = ((verdict or {}).get("parting") or {}).get("pairs") or []
    if not pairs:
        return ""
    def named(p):
        geoms = (repr(g) if g else f"#{i}" for g, i in zip(p["geoms"], p["ids"], strict=True))
        return f"{'-'.join(p['types'])} {'/'.join(geoms)}"

    return f", parting at contacts of {', '.join(named(p) for p in pairs[:3])}"


def _particles_line(summary: dict) -> str:
    """A line 'particles: ...' (verified share, the mean cost per phase, re-draws), or ''."""
    loss = summary.get("loss")
    if not loss or loss["mean"]["initial"] is None or "verified_particle_share" not in summary:
        return ""
    m = loss["mean"]
    line = (f"\nparticles: {summary['verified_particle_share']:.0%} end as verified plans; mean "
            f"cost {m['initial']:.3g} at the start, {m['svgd']:.3g} after SVGD, "
            f"{m['final']:.3g} at the end")
    if loss.get("svgd_share") is not None:
        line += f" (SVGD: {loss['svgd_share']:.0%} of the decrease)"
    rescue = summary.get("rescue")
    if rescue:
        line += f"; {rescue['redraws']} stalled particles re-drawn"
    return line + _polish_line(summary.get("polish"))


def _polish_line(polish: dict | None) -> str:
    """A line 'polish: ...' (the gradient model's polish, the landings in C), or ''."""
    if not polish:
        return ""
    parts = []
    early = polish.get("early")
    if early:
        parts.append(f"the screen's {early['particles']} candidates landed in C: {early['ok']} "
                     f"succeed ({early['task_plans']} task plans), {early['landed']} within "
                     f"tolerance")
    grad = polish.get("gradient")
    if grad:
        parts.append(f"Levenberg–Marquardt in MJX: {grad['landed']} of {grad['particles']} "
                     f"within tolerance, median {grad['iterations_median']:g} iterations")
    land = polish.get("landing")
    if land:
        parts.append(f"Gauss–Newton in C: {land['ok']} of {land['particles']} succeed, "
                     f"{land['landed']} within tolerance, median "
                     f"{land['iterations_median']:g} iterations")
    return "\npolish: " + "; ".join(parts) if parts else ""


def _robustness_line(robust: dict | None) -> str:
    """A line 'robustness: ...' (what was perturbed, how many replays), or ''."""
    if not robust:
        return ""
    parts = []
    for u in robust["uncertain"]:
        what = (f"{u['spread'] * 1000:.3g} mm" if u["kind"] == "position"
                else f"±{u['spread']:.0%}")
        if u["distribution"] == "normal":
            what = "σ " + what.lstrip("±")
        count = len(u["names"])
        parts.append(f"{u['kind']} {what} ({count} {'element' if count == 1 else 'elements'})")
    source = "declared" if robust["declared"] else "the default uncertainty"
    median = robust.get("median")
    return (f"\nrobustness: success share of {robust['samples']} perturbed MuJoCo C replays per "
            f"verified plan, {source}: {', '.join(parts) or 'nothing'}"
            + ("" if median is None else f"; median {median:.0%}")
            + f" ({robust['seconds']:.1f} s)")


def format_table(summary: dict, *, markdown: bool = False) -> str:
    """The table of task plans `mjstamp solve` prints, from a solve's summary.

    Args:
      summary: `SolveResult.summary()` or the contents of plans.json.
      markdown: a Markdown table (for notebooks) instead of aligned text.

    Returns:
      The table, a header line above it and a line of totals below it.
    """
    header = ("task plan", "plans found", "verified", "repaired", "best cost", "verified share")
    body = [
        (r["task_plan"], str(r["plans"]), str(r["verified"]), str(r.get("repaired", 0)),
         "-" if r["best_cost"] is None else f"{r['best_cost']:.3g}",
         f"{r['verified_share']:.0%}")
        for r in summary["task_plans"]
    ]
    robust = summary.get("robustness")
    if robust:  # N.B. results written before robustness scores have none
        header += ("robust best/median",)
        body = [b + ("-" if r.get("robustness_best") is None else
                     f"{r['robustness_best']:.0%}/{r['robustness_median']:.0%}",)
                for b, r in zip(body, summary["task_plans"], strict=True)]
    title = (f"task {summary['task']}: {summary['particles']} particles, "
             f"{summary['wall_time_s']:.1f} s; {summary['returned_plans']} plans returned, "
             f"{summary['verified_fraction']:.0%} verified in MuJoCo C")
    codes = (f" (symbol codes: {summary['distinct_verified_codes']})"
             if summary["declaration"]["symbols"] else "")
    footer = f"distinct verified task plans: {summary['distinct_verified_task_plans']}{codes}"
    if summary.get("repaired_plans"):
        footer += f"; {summary['repaired_plans']} plans verified only after repair in MuJoCo C"
    fid = summary.get("fidelity") or {}
    if "iterations" in fid and "mjx_divergence_p95_m" in fid:
        tol = fid.get("tolerance_m")
        footer += (
            f"\ngradient model: {describe(fid.get('gradient', 'unrolled'), fid['iterations'])}; "
            "MJX vs MuJoCo C "
            f"divergence p95 {fid['mjx_divergence_p95_m']:.2g} m"
            + (f" (tolerance {tol:.2g} m" + ("" if fid.get("faithful", True) else
                                             ", NOT faithful: allow_unfaithful")
               + _chaos_note(fid.get("mjx_final") or {})
               + ("" if fid.get("faithful_at_end", True) else
                  ", over it at the final particles" + _parting_note(fid.get("mjx_final"))
                  + ": their plans are verified in C") + ")"
               if tol is not None else "")
        )
    footer += _particles_line(summary) + _robustness_line(robust)
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "| --- |" + " ---: |" * (len(header) - 1)]
        lines += ["| `" + b[0] + "` | " + " | ".join(b[1:]) + " |" for b in body]
        return "\n\n".join([title, "\n".join(lines), footer])
    widths = [max(len(h), *(len(b[i]) for b in body)) if body else len(h)
              for i, h in enumerate(header)]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    rows = ["  ".join(c.ljust(w) for c, w in zip(b, widths, strict=True)).rstrip()
            for b in body]
    return "\n".join([title, line, "-" * len(line), *rows, footer])

# N.B. the summary of a solve moved to the solver; its old names work for one release.
__getattr__ = _moved.moved_names(
    __name__, dict.fromkeys(("summarize", "to_arrays", "group"), "mjstamp.solver.summary"))
