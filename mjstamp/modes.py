"""Ground truth for coverage: sample a task's θ box in MuJoCo C and list its modes.

Shots over the box of θ are replayed in MuJoCo C with the scene's own solver
settings and decoded exactly as solved plans are (`verify.decode`); every task
plan that succeeds somewhere is listed with the share of the box it occupies.
Coverage of a solve = found task plans / feasible task plans occupying at least
`min_share` of the box.

Two samplers of the box:

* `sweep`: a regular grid, for boxes of at most 3 coordinates (billiards: the
  cue velocity);
* `monte_carlo`: seeded uniform draws, for any dimension and any kind of
  variable (boxes, angles, logits: uniform over the declared bounds, the
  range particles start in). A task plan with share p seen k times out of N
  has a share estimate k/N with standard error sqrt(p(1 − p)/N); N = 10⁵ sees
  a 0.1% task plan about 100 times (±10%).

Both are cached on disk (~/.cache/mjstamp/modes), keyed by the task
declaration, the scene's compiled model, the sampler's settings and a `salt`
for what the declaration cannot show (the code of controls, costs and success
predicates: pass a hash of it).

Random search in MuJoCo C, the baseline a planner should beat, is
`mjstamp.baselines.sampling.random_search`.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections import Counter
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from mjstamp import _moved, fileio, verify
from mjstamp.errors import MjstampError
from mjstamp.progress import Progress, ProgressLike

CACHE = Path.home() / ".cache" / "mjstamp" / "modes"
MIN_SHARE = 1e-3


def supports_sweep(task) -> bool:
    """Whether θ is a box of at most 3 coordinates (a grid sweep is affordable)."""
    return all(v.kind == "box" for v in task.variables) and task.dim <= 3


def _key(task, grid: int, salt: str = "") -> str:
    return _hash(task, f"grid={grid} v1" + (f" salt={salt}" if salt else ""))


def _hash(task, tail: str) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(task.describe(), sort_keys=True, default=str).encode())
    buffer = np.empty(mujoco.mj_sizeModel(task.scene.m), np.uint8)
    mujoco.mj_saveModel(task.scene.m, None, buffer)
    h.update(buffer.tobytes())
    h.update(tail.encode())
    return h.hexdigest()[:24]


def _bounds(task) -> tuple[np.ndarray, np.ndarray]:
    low = np.concatenate([v.low for v in task.variables])
    high = np.concatenate([v.high for v in task.variables])
    return low, high


def _read_cache(path: Path, cache: bool) -> dict | None:
    if cache and path.is_file():
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            return None  # a torn or foreign file: recompute
    return None


def _write_cache(path: Path, result: dict, cache: bool) -> None:
    if not cache:
        return
    try:
        CACHE.mkdir(parents=True, exist_ok=True)
        fileio.write_atomic(path, lambda f: f.write(json.dumps(result).encode()))
    except OSError:
        pass  # a read-only cache only costs time


def _count_plans(task, theta: np.ndarray, *, chunk: int, progress, desc: str):
    """Replays θ (N, d) in chunks; returns (Counter of successful plans, codes, successes)."""
    found: Counter = Counter()
    codes: dict[str, str] = {}
    ok_total = 0
    progress = Progress.of(progress).under("modes")
    starts = range(0, len(theta), chunk)
    every = max(1, len(starts) // 10)
    for i, start in enumerate(tqdm(starts, desc=desc, unit="chunk", disable=not progress.bar)):
        if progress.lines and (i % every == 0):  # a log sees lines, not a bar
            progress(f"{desc}: {start}/{len(theta)} shots replayed in MuJoCo C")
        part = theta[start : start + chunk]
        decoded = verify.decode(task, verify.simulate_c(task, part), part)
        ok_total += int(decoded.ok.sum())
        for plan, code, ok in zip(decoded.plan, decoded.code, decoded.ok, strict=True):
            if ok:
                found[plan] += 1
                codes[plan] = code
    return found, codes, ok_total


def _modes(found: Counter, codes: dict, shots: int) -> list[dict]:
    return [
        {"task_plan": p, "code": codes[p], "count": c, "share": c / shots,
         "share_stderr": float(np.sqrt(c / shots * (1 - c / shots) / shots))}
        for p, c in found.most_common()
    ]


def sweep(task, *, grid: int = 200, chunk: int = 4096, progress: ProgressLike = None,
          cache: bool = True, salt: str = "") -> dict:
    """Replays a grid over the task's box in MuJoCo C; returns its modes.

    Args:
      task: a `Task` whose variables are boxes (see `supports_sweep`).
      grid: points per coordinate (grid**dim shots).
      chunk: shots per batch.
      progress: tqdm bar; None shows it on a terminal, status lines otherwise.
      cache: read and write the on-disk cache.
      salt: extra cache key for what `task.describe()` cannot see.

    Returns:
      {"method": "grid", "grid", "shots", "success_share", "modes":
      [{"task_plan", "code", "count", "share", "share_stderr"}, ...] sorted by
      share}.
    """
    if not supports_sweep(task):
        raise MjstampError(
            f"task {task.name!r}: a grid sweep needs θ to be a box of at most 3 "
            f"coordinates; it has {task.dim} ({', '.join(v.kind for v in task.variables)}); "
            "use modes.monte_carlo"
        )
    path = CACHE / f"{task.name}-{_key(task, grid, salt)}.json"
    hit = _read_cache(path, cache)
    if hit is not None:
        return hit
    low, high = _bounds(task)
    axes = [np.linspace(lo, hi, grid) for lo, hi in zip(low, high, strict=True)]
    theta = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, task.dim)
    t0 = time.perf_counter()
    found, codes, ok_total = _count_plans(task, theta, chunk=chunk, progress=progress,
                                          desc=f"sweep {task.name}")
    shots = len(theta)
    result = {
        "task": task.name,
        "method": "grid",
        "grid": grid,
        "shots": shots,
        "box_low": low.tolist(),
        "box_high": high.tolist(),
        "success_share": ok_total / shots,
        "compute_s": time.perf_counter() - t0,
        "modes": _modes(found, codes, shots),
    }
    _write_cache(path, result, cache)
    return result


def uniform_theta(task, n: int, rng: np.random.Generator) -> np.ndarray:
    """Draws n shots uniform over the declared bounds of θ, as `Task.initial_particles`."""
    low, high = _bounds(task)
    return low + rng.uniform(size=(n, task.dim)) * (high - low)


def monte_carlo(task, *, shots: int = 100_000, seed: int = 0, chunk: int = 2048,
                progress: ProgressLike = None, cache: bool = True, salt: str = "") -> dict:
    """Replays `shots` uniform draws over θ's bounds in MuJoCo C; returns its modes.

    Works for any dimension and any kind of variable. The draws depend on
    `seed` and `shots` only (not on `chunk`), so a cached result is the one a
    recomputation would give.

    Args:
      task: a `Task`.
      shots: number of draws N.
      seed: seeds the draws.
      chunk: shots per batch (memory: a chunk's replay holds chunk·T poses).
      progress: tqdm bar; None shows it on a terminal, status lines otherwise.
      cache: read and write the on-disk cache.
      salt: extra cache key for what `task.describe()` cannot see.

    Returns:
      {"method": "uniform", "seed", "shots", "grid": None, "success_share",
      "modes": [{"task_plan", "code", "count", "share", "share_stderr"}, ...]
      sorted by share}.
    """
    shots = int(shots)
    if shots < 1:
        raise MjstampError(f"monte_carlo(shots={shots}) must be >= 1")
    tail = f"uniform shots={shots} seed={seed} v1" + (f" salt={salt}" if salt else "")
    path = CACHE / f"{task.name}-{_hash(task, tail)}.json"
    hit = _read_cache(path, cache)
    if hit is not None:
        return hit
    low, high = _bounds(task)
    theta = uniform_theta(task, shots, np.random.default_rng(seed))
    t0 = time.perf_counter()
    found, codes, ok_total = _count_plans(task, theta, chunk=chunk, progress=progress,
                                          desc=f"monte carlo {task.name}")
    result = {
        "task": task.name,
        "method": "uniform",
        "seed": int(seed),
        "grid": None,
        "shots": shots,
        "box_low": low.tolist(),
        "box_high": high.tolist(),
        "success_share": ok_total / shots,
        "compute_s": time.perf_counter() - t0,
        "modes": _modes(found, codes, shots),
    }
    _write_cache(path, result, cache)
    return result


def coverage(found_plans, modes: dict, *, min_share: float = MIN_SHARE) -> dict:
    """Found task plans over feasible ones occupying at least `min_share` of the box.

    Also how many task plans the sweep holds in all (`swept`, rarer ones
    included) and how many of those were found (`swept_found`).
    """
    feasible = [m["task_plan"] for m in modes["modes"] if m["share"] >= min_share]
    found = sorted(set(found_plans) & set(feasible))
    swept = {m["task_plan"] for m in modes["modes"]}
    return {
        "coverage": len(found) / len(feasible) if feasible else 1.0,
        "min_share": min_share,
        "feasible": feasible,
        "found": found,
        "missed": sorted(set(feasible) - set(found)),
        "swept": len(swept),
        "swept_found": len(swept & set(found_plans)),
        "grid": modes.get("grid"),
        "shots": modes.get("shots"),
        "method": modes.get("method", "grid"),
    }

# N.B. random_search moved to the baselines; its old name works for one release.
__getattr__ = _moved.moved_names(__name__, {"random_search": "mjstamp.baselines.sampling"})
