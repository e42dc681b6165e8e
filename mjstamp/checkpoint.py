"""Checkpoints of a solve: written atomically while STAMP runs, read back by `--resume`.

A results directory being written holds `checkpoint.npz`: the STAMP loop's
`svgd.LoopSnapshot` (particles, optimizer state, PRNG key, every iteration's
record, re-draw counters) and a `meta` entry (JSON: task, fingerprint of the
declaration and scene, seed, settings, mjstamp version, phase, iteration).
`SolveResult.save` removes it once plans.json is written, so a directory with
a checkpoint and no plans.json is a solve that did not finish.

Resuming re-runs what comes before STAMP (the seeding screen and the
calibration are deterministic and cached), then continues the loop after the
checkpoint's iteration; the loop's steps are deterministic, so the plans are
the same as those of a run never stopped (`svgd.LoopSnapshot`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import signal
import threading
import time
import zipfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mjstamp import parallel
from mjstamp.config import FLAT_NAMES
from mjstamp.errors import MjstampError
from mjstamp.fileio import probe, write_atomic
from mjstamp.progress import Progress
from mjstamp.svgd import LoopSnapshot, StampDiagnostics
from mjstamp.version import __version__

__all__ = ["FILENAME", "Checkpointer", "Interrupted", "describe", "fingerprint", "load",
           "read_meta", "save"]

FILENAME = "checkpoint.npz"
FORMAT = 1
_PHASES = {0: "SVGD", 1: "SGD"}


class Interrupted(KeyboardInterrupt):
    """A solve stopped by SIGINT or SIGTERM once its checkpoint is written (says where)."""


def fingerprint(task_fingerprint: str, settings: Mapping[str, Any], seed: int) -> str:
    """Hash of what a resumed solve must share with the checkpointed one."""
    blob = json.dumps({"task": task_fingerprint, "settings": settings, "seed": seed,
                       "version": __version__, "format": FORMAT}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def _row_json(row: StampDiagnostics) -> dict:
    return {k: np.asarray(v).tolist() for k, v in row._asdict().items()}


def _row(data: dict) -> StampDiagnostics:
    wide = ("bandwidth", "displacement_per_coordinate")
    return StampDiagnostics(**{k: np.asarray(data[k], float) if k in wide else data[k]
                               for k in StampDiagnostics._fields})


def save(path: Path, snap: LoopSnapshot, meta: Mapping[str, Any]) -> None:
    """Writes `snap` and `meta` to `path` atomically (never half a checkpoint)."""
    arrays = {"particles": snap.particles, "key_data": snap.key_data}
    arrays.update({f"opt_{i:03d}": leaf for i, leaf in enumerate(snap.opt_leaves)})
    arrays.update({f"counter_{k}": v for k, v in snap.counters.items()})
    if snap.svgd_particles is not None:
        arrays["svgd_particles"] = snap.svgd_particles
    meta = {**meta, "format": FORMAT, "phase": int(snap.phase), "iteration": int(snap.iteration),
            "svgd_converged": snap.svgd_converged, "opt_leaves": len(snap.opt_leaves),
            "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S")}
    arrays["meta"] = np.asarray(json.dumps(meta))
    arrays["rows"] = np.asarray(json.dumps([_row_json(r) for r in snap.rows]))
    write_atomic(path, lambda f: np.savez(f, **arrays))


def _open(out: str | Path) -> tuple[Path, Any]:
    path = Path(out) / FILENAME
    if not probe(path.is_file, out):
        raise MjstampError(f"{str(Path(out))!r} holds no {FILENAME} (no unfinished solve to "
                           "resume there)")
    try:
        return path, np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise MjstampError(f"{str(path)!r} is not a readable checkpoint ({e}); delete it to "
                           "start afresh") from None


def read_meta(out: str | Path) -> dict:
    """The `meta` of the checkpoint in results directory `out` (one-line MjstampError if none)."""
    path, data = _open(out)
    try:
        with data:
            meta = json.loads(str(data["meta"]))
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise ValueError(f"format {meta.get('format') if isinstance(meta, dict) else '?'}")
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise MjstampError(f"{str(path)!r} is not a readable checkpoint ({e}); delete it to "
                           "start afresh") from None
    return meta


def load(out: str | Path, *, expect: Mapping[str, Any], settings: Mapping | None = None,
         seed: int | None = None) -> tuple[dict, LoopSnapshot]:
    """(meta, snapshot) of the checkpoint in `out`, checked against `expect`.

    Args:
      out: the results directory.
      expect: {"task", "fingerprint", "version", ...}: what the resuming solve
        is; the first key that differs from the checkpoint's is named.
      settings: the resuming solve's settings ({"task": ..., "solve": ...}) and
      seed: its seed; with a fingerprint that differs, the message names the
        first of them that changed.

    Raises:
      MjstampError: no checkpoint, an unreadable one, or one of another task,
        declaration, scene, settings, seed or mjstamp version (one line).
    """
    path, _ = _open(out)
    meta = read_meta(out)
    for key, value in expect.items():
        if meta.get(key) != value:
            what = {"fingerprint": "declaration, scene, settings or seed",
                    "version": "mjstamp version"}.get(key, key)
            changed = _first_change(meta, settings, seed)
            if key == "fingerprint" and changed:
                raise MjstampError(
                    f"{str(path)!r} is a checkpoint of another solve: {changed}; run with the "
                    "same task, settings and seed, or delete it to start afresh"
                )
            raise MjstampError(
                f"{str(path)!r} is a checkpoint of another {what} ({key} "
                f"{meta.get(key)!r}, this solve: {value!r}); run with the same task, settings "
                "and seed, or delete it to start afresh"
            )
    try:
        with np.load(path, allow_pickle=False) as data:
            rows = [_row(r) for r in json.loads(str(data["rows"]))]
            snap = LoopSnapshot(
                phase=int(meta["phase"]), iteration=int(meta["iteration"]),
                particles=data["particles"],
                opt_leaves=[data[f"opt_{i:03d}"] for i in range(int(meta["opt_leaves"]))],
                key_data=data["key_data"], rows=rows,
                svgd_particles=data["svgd_particles"] if "svgd_particles" in data else None,
                svgd_converged=meta["svgd_converged"],
                counters={k[len("counter_"):]: data[k] for k in data.files
                          if k.startswith("counter_")},
            )
    except (KeyError, ValueError, TypeError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise MjstampError(f"{str(path)!r} is not a readable checkpoint ({e}); delete it to "
                           "start afresh") from None
    return meta, snap


def _first_change(meta: Mapping[str, Any], settings, seed) -> str:
    """'setting devices was 2, is 1' for the first setting (or the seed) that differs; ''."""
    if seed is not None and meta.get("seed") != seed:
        return f"seed was {meta.get('seed')!r}, is {seed!r}"
    old = meta.get("settings") or {}
    for group in ("task", "solve"):
        for name, value in (settings or {}).get(group, {}).items():
            before = old.get(group, {}).get(name)
            if before != value:
                # N.B. solve settings are hashed by their flat names; say the dotted one.
                shown = FLAT_NAMES.get(name, name) if group == "solve" else name
                return f"{group} setting {shown} was {before!r}, is {value!r}"
    return ""


class Checkpointer:
    """The `run_stamp(checkpoint=...)` hook: a snapshot every `every_s` seconds and on signals.

    While `catch_signals()` is active, SIGINT and SIGTERM only set a flag; after
    the iteration under way the checkpointer writes its snapshot and raises
    `Interrupted` naming the file and how to continue (a second signal
    interrupts at once).

    Args:
      out: the results directory (it exists).
      meta: what `load` checks on resume (task, fingerprint, version, ...).
      every_s: seconds between checkpoints (0: after every iteration).
      resume_hint: the command that continues the solve, for the message.
      progress: status lines (`mjstamp.progress`; False: none).
    """

    def __init__(self, out: str | Path, meta: Mapping[str, Any], *, every_s: float = 30.0,
                 resume_hint: str = "", progress: Progress | bool = False):
        self.path = Path(out) / FILENAME
        self.meta = dict(meta)
        self.every_s = float(every_s)
        self.resume_hint = resume_hint
        self.say = Progress.of(progress or False, "checkpoint")  # N.B. None: silent, as before
        self.signal: int | None = None
        self.saved = 0
        self._last = time.monotonic()

    def __call__(self, make: Callable[[], LoopSnapshot]) -> None:
        """After an iteration: writes `make()` when one is due or a signal came (then raises)."""
        now = time.monotonic()
        if self.signal is None and now - self._last < self.every_s:
            return
        snap = make()
        if parallel.is_lead():  # N.B. several processes share one results directory
            save(self.path, snap, self.meta)
        self.saved += 1
        self._last = time.monotonic()
        where = f"{_PHASES[snap.phase]} iteration {snap.iteration}"
        self.say(f"checkpoint: {where} -> {self.path}")
        if self.signal is not None:
            name = signal.Signals(self.signal).name
            hint = f"; continue with {self.resume_hint}" if self.resume_hint else ""
            raise Interrupted(f"{name}: checkpoint of {where} written to {self.path}{hint}")

    @contextlib.contextmanager
    def catch_signals(self) -> Iterator[None]:
        """SIGINT / SIGTERM set a flag (the main thread only; elsewhere nothing changes)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def flag(signum, frame):
            if self.signal is not None:  # a second signal: stop now
                raise KeyboardInterrupt
            self.signal = signum

        previous = {s: signal.signal(s, flag) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for s, handler in previous.items():
                # N.B. None: a handler installed from C, which Python cannot reinstall.
                signal.signal(s, signal.SIG_DFL if handler is None else handler)
        if self.signal is not None:  # it came after the last iteration's checkpoint call
            name = signal.Signals(self.signal).name
            hint = f"; continue with {self.resume_hint}" if self.resume_hint else ""
            where = f"the last checkpoint, {self.path}" if self.saved else "no checkpoint yet"
            raise Interrupted(f"{name} as STAMP ended: {where}{hint}")


def describe(meta: Mapping[str, Any]) -> str:
    """'SVGD iteration 12 (saved 2026-12-02T01:02:03)' of a checkpoint's meta."""
    return (f"{_PHASES.get(meta.get('phase'), '?')} iteration {meta.get('iteration')} "
            f"(saved {meta.get('saved_at', '?')})")


def task_of(checkpoint: Path) -> object:
    """The task named in a checkpoint's `meta` (a JSON string), or None if unreadable."""
    try:
        with np.load(checkpoint, allow_pickle=False) as f:
            meta = f["meta"].item()
        meta = meta.decode() if isinstance(meta, bytes) else meta
        return json.loads(meta).get("task")
    except Exception:  # noqa: BLE001 - a damaged checkpoint only costs us the task's name
        return None
