"""Ground truth for coverage: sweep a task's θ box in MuJoCo C and list its modes.

For a task whose θ is a low-dimensional box (billiards: the cue velocity), a
fine grid over the box is replayed in MuJoCo C with the scene's own solver
settings and decoded exactly as solved plans are (`plans.decode`); every task
plan that succeeds somewhere is listed with the share of the box it occupies.
Coverage of a solve = found task plans / feasible task plans occupying at least
`min_share` of the box.

Sweeps are cached on disk (~/.cache/mjstamp/modes), keyed by the task
declaration, the scene's model and the grid.
"""

from __future__ import annotations

import hashlib
import json
import sys
from collections import Counter
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from mjstamp import plans as plans_mod
from mjstamp.errors import MjstampError

CACHE = Path.home() / ".cache" / "mjstamp" / "modes"
MIN_SHARE = 1e-3


def supports_sweep(task) -> bool:
    """Whether θ is a box of at most 3 coordinates (a grid sweep is affordable)."""
    return all(v.kind == "box" for v in task.variables) and task.dim <= 3


def _key(task, grid: int) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(task.describe(), sort_keys=True, default=str).encode())
    buffer = np.empty(mujoco.mj_sizeModel(task.scene.m), np.uint8)
    mujoco.mj_saveModel(task.scene.m, None, buffer)
    h.update(buffer.tobytes())
    h.update(f"grid={grid} v1".encode())
    return h.hexdigest()[:24]


def sweep(task, *, grid: int = 200, chunk: int = 4096, progress: bool | None = None,
          cache: bool = True) -> dict:
    """Replays a grid over the task's box in MuJoCo C; returns its modes.

    Args:
      task: a `Task` whose variables are boxes (see `supports_sweep`).
      grid: points per coordinate (grid**dim shots).
      chunk: shots per batch.
      progress: tqdm bar; None shows it on a terminal.
      cache: read and write the on-disk cache.

    Returns:
      {"grid", "shots", "success_share", "modes": [{"task_plan", "code",
      "count", "share"}, ...] sorted by share}.
    """
    if not supports_sweep(task):
        raise MjstampError(
            f"task {task.name!r}: a grid sweep needs θ to be a box of at most 3 "
            f"coordinates; it has {task.dim} ({', '.join(v.kind for v in task.variables)})"
        )
    path = CACHE / f"{task.name}-{_key(task, grid)}.json"
    if cache and path.is_file():
        return json.loads(path.read_text())
    low = np.concatenate([v.low for v in task.variables])
    high = np.concatenate([v.high for v in task.variables])
    axes = [np.linspace(lo, hi, grid) for lo, hi in zip(low, high, strict=True)]
    theta = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, task.dim)
    found: Counter = Counter()
    codes: dict[str, str] = {}
    ok_total = 0
    show = sys.stderr.isatty() if progress is None else progress
    for start in tqdm(range(0, len(theta), chunk), desc=f"sweep {task.name}", unit="chunk",
                      disable=not show):
        part = theta[start : start + chunk]
        decoded = plans_mod.decode(task, plans_mod.simulate_c(task, part), part)
        ok_total += int(decoded.ok.sum())
        for plan, code, ok in zip(decoded.plan, decoded.code, decoded.ok, strict=True):
            if ok:
                found[plan] += 1
                codes[plan] = code
    shots = len(theta)
    result = {
        "task": task.name,
        "grid": grid,
        "shots": shots,
        "box_low": low.tolist(),
        "box_high": high.tolist(),
        "success_share": ok_total / shots,
        "modes": [
            {"task_plan": p, "code": codes[p], "count": c, "share": c / shots}
            for p, c in found.most_common()
        ],
    }
    if cache:
        try:
            CACHE.mkdir(parents=True, exist_ok=True)
            plans_mod.write_atomic(path, lambda f: f.write(json.dumps(result).encode()))
        except OSError:
            pass  # a read-only cache only costs time
    return result


def coverage(found_plans, modes: dict, *, min_share: float = MIN_SHARE) -> dict:
    """Found task plans over feasible ones occupying at least `min_share` of the box."""
    feasible = [m["task_plan"] for m in modes["modes"] if m["share"] >= min_share]
    found = sorted(set(found_plans) & set(feasible))
    return {
        "coverage": len(found) / len(feasible) if feasible else 1.0,
        "min_share": min_share,
        "feasible": feasible,
        "found": found,
        "missed": sorted(set(feasible) - set(found)),
        "grid": modes["grid"],
    }
