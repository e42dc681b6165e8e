"""landscape.png (STAMP Fig. 9): the particles over the MJX cost C(θ) of a 2-D θ box.

Three panels: the particles at the start, at the end of SVGD and at the end
of SGD, coloured by the verified task plan of their final θ.

The cost grid stays within `LANDSCAPE_BUDGET` particle-steps of MJX rollouts
(`default_grid`), in batches of the solve's own particle count.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib import colormaps, ticker
from matplotlib import colors as mcolors
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from tqdm.auto import tqdm

from mjstamp.errors import MjstampError
from mjstamp.figures._common import _axis_names
from mjstamp.figures.plans import FAILED_COLOR, particle_plans, plan_colors
from mjstamp.progress import Progress, ProgressLike

# Particle-steps of MJX forward rollouts the landscape grid may cost: at about
# 5 us per particle-step on a 2-core CPU, 2.4e6 is about 12 s (billiards:
# 126 x 126 grid, 150 steps).
LANDSCAPE_BUDGET = 2.4e6
# Each batch is a call with its own overhead (~1 ms): small n would otherwise
# cost thousands of calls.
LANDSCAPE_MAX_BATCHES = 400
# How `landscape_cost` compiles: jit(fn, name, *example) -> compiled fn.
Jit = Callable[..., Callable]
# Low cost dark, but not black: particles' black edges must stay visible.
_COST_CMAP = mcolors.ListedColormap(colormaps["Greys_r"](np.linspace(0.2, 1.0, 256)))


def landscape_cost(
    task, n: int, low, high, grid: int, *, progress: ProgressLike = None, jit: Jit | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The task's MJX cost C(θ) on a grid × grid lattice over a 2-D box.

    Batches hold `n` particles, the solve's own batch size: one compiled
    function per task, n and `jit` (billiards: ~4 s to trace and compile the
    first time; JAX's compilation cache, and a caching `jit`, keep it across runs).

    Args:
      task: a `Task` with `task.dim == 2`.
      n: particles per batch.
      low: (2,) lower corner of the box.
      high: (2,) upper corner.
      grid: points per axis.
      progress: tqdm bar; None shows it on a terminal.
      jit: `jit(fn, name, *example) -> compiled fn`, e.g. one that goes through
        `mjstamp.tracecache.cached_jit` for a registered task; None: `jax.jit`.

    Returns:
      xs: (grid,) first coordinate.
      ys: (grid,) second coordinate.
      cost: (grid, grid) C at (ys[i], xs[j]) in row i, column j (NaN where the
        rollout is not finite).
    """
    if task.dim != 2:
        raise MjstampError(f"task {task.name!r}: a landscape needs 2-D θ; it has {task.dim}")
    xs = np.linspace(low[0], high[0], grid)
    ys = np.linspace(low[1], high[1], grid)
    gx, gy = np.meshgrid(xs, ys)
    points = np.stack([gx.ravel(), gy.ravel()], axis=1)
    pad = -len(points) % n
    # Padding repeats the last point: one compiled shape for every batch.
    points = np.concatenate([points, np.repeat(points[-1:], pad, axis=0)])

    fn = _cost_fn(task, n, jit)
    out = []
    for start in tqdm(range(0, len(points), n), desc=f"landscape {task.name}", unit="batch",
                      disable=not Progress.of(progress).bar):
        batch = jnp.asarray(points[start : start + n], task.scene.dtype)
        out.append(np.asarray(jax.device_get(fn(batch)), np.float64))
    values = np.concatenate(out)[: grid * grid].reshape(grid, grid)
    return xs, ys, np.where(np.isfinite(values), values, np.nan)


@functools.lru_cache(maxsize=8)
def _cost_fn(task, n: int, jit: Jit | None):
    """Compiled θ (n, d) -> C(θ) (n,), once per task, batch size and `jit`."""

    def cost(theta):
        _, values = task.evaluate(theta, hard=True)  # as result.cost: actions at Γ(θ)
        return task.cost_total(values)

    if jit is None:
        return jax.jit(cost)
    return jit(cost, f"landscape-cost n={n}", jnp.zeros((n, task.dim), task.scene.dtype))


def default_grid(task, n: int) -> int:
    """Landscape points per axis within `LANDSCAPE_BUDGET` particle-steps.

    At most `LANDSCAPE_MAX_BATCHES` batches of n particles; billiards (n = 128,
    150 steps) gets 126 × 126 points in 125 batches, ~9 s on a 2-core CPU plus
    its compile.
    """
    batches = max(1, min(int(LANDSCAPE_BUDGET / (n * task.horizon)), LANDSCAPE_MAX_BATCHES))
    grid = int(math.isqrt(batches * n))
    return int(np.clip(grid, 8, 400))


def landscape_figure(result, *, grid: int | None = None, progress: ProgressLike = None,
                     jit: Jit | None = None) -> Figure:
    """Particles over the cost landscape: initial, end of SVGD, end of SGD (Fig. 9).

    Particles are colored by the task plan their final θ verifies in MuJoCo C
    (gray: not returned, or failed in C), so the left panel shows where each
    mode's particles started.

    Args:
      result: a `SolveResult` of a task with 2-D θ.
      grid: points per axis of the cost grid; None: `default_grid`.
      progress: tqdm bar over the grid; None shows it on a terminal.
      jit: compiles the cost function (see `landscape_cost`).

    Returns:
      The Figure (three panels, a colorbar, a legend of task plans).
    """
    task = result.task
    if task.dim != 2:
        raise MjstampError(f"task {task.name!r}: a landscape needs 2-D θ; it has {task.dim}")
    n = result.theta.shape[0]
    low = np.concatenate([v.low for v in task.variables])
    high = np.concatenate([v.high for v in task.variables])
    grid = default_grid(task, n) if grid is None else int(grid)
    if grid < 2:
        raise MjstampError(f"landscape grid={grid} must be >= 2")
    xs, ys, cost = landscape_cost(task, n, low, high, grid, progress=progress, jit=jit)

    plans = particle_plans(result)
    colors = plan_colors(result)
    legend_rows = math.ceil((len(colors) + 1) / 6)
    # Three square panels, their titles and labels, then the legend's rows: a
    # figure too small for these makes constrained layout overlap the texts.
    fig = Figure(figsize=(15, 5.7 + 0.25 * legend_rows), layout="constrained")
    axes = fig.subplots(1, 3, sharex=True, sharey=True)
    finite = cost[np.isfinite(cost)]
    positive, levels, norm = _cost_levels(finite)
    phase = np.asarray(result.diagnostics.phase)
    iters = (int(np.sum(phase == 0)), int(np.sum(phase == 1)))
    panels = (
        ("initial (uniform)", result.initial_theta),
        (f"end of SVGD ({iters[0]} iterations)", result.svgd_theta),
        (f"end of SGD ({iters[1]} iterations)", result.theta),
    )
    names = _axis_names(task)
    contour = None
    for ax, (title, theta) in zip(axes, panels, strict=True):
        if finite.size:
            contour = ax.contourf(xs, ys, cost, levels=levels, norm=norm, cmap=_COST_CMAP)
        _scatter_by_plan(ax, theta, plans, colors)
        ax.set_title(title)
        ax.set_xlabel(names[0])
        ax.set_xlim(low[0], high[0])
        ax.set_ylim(low[1], high[1])
        ax.set_aspect("equal" if np.isclose(high[0] - low[0], high[1] - low[1]) else "auto")
    axes[0].set_ylabel(names[1])
    if contour is not None:
        bar = fig.colorbar(contour, ax=axes, shrink=0.8, pad=0.01)
        bar.set_label("cost C(θ) (MJX rollout; dark = low)")
        if positive:
            bar.locator = ticker.LogLocator(subs=(1.0, 2.0, 5.0))
            bar.formatter = ticker.LogFormatter(labelOnlyBase=False)
            bar.update_ticks()
    fig.suptitle(f"{task.name}: particles over the cost landscape ({grid}×{grid} grid), "
                 "colored by the verified task plan of their final θ")
    handles = [Line2D([], [], ls="", marker="o", mfc=colors[p], mec="k", mew=0.4,
                      label=f"{p} ({int(np.sum(plans == p))})") for p in colors]
    missing = int(np.sum(plans == None))  # noqa: E711 - elementwise on an object array
    handles.append(Line2D([], [], ls="", marker="o", mfc=FAILED_COLOR, mec="k", mew=0.4,
                          label=f"not returned / failed ({missing})"))
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 6),
               fontsize=8, title="verified task plan of the final particle (count)",
               title_fontsize=8)
    return fig


def _cost_levels(finite: np.ndarray):
    """(log scale?, contour levels, norm) for the finite costs of a landscape."""
    positive = bool(finite.size and finite.min() > 0)
    if positive:
        # Costs span decades (a pocketed shot vs. a miss): log levels show both.
        levels = np.geomspace(finite.min(), finite.max(), 25)
        return positive, levels, mcolors.LogNorm(levels[0], levels[-1])
    return positive, (np.linspace(finite.min(), finite.max(), 25) if finite.size else 25), None


def _scatter_by_plan(ax, theta, plans, colors) -> None:
    theta = np.asarray(theta)
    failed = np.array([p is None for p in plans])
    ax.scatter(theta[failed, 0], theta[failed, 1], s=14, c=FAILED_COLOR, edgecolors="k",
               linewidths=0.3, zorder=3)
    for p, color in colors.items():
        mask = plans == p
        ax.scatter(theta[mask, 0], theta[mask, 1], s=18, color=color, edgecolors="k",
                   linewidths=0.4, zorder=4)


__all__: list[str] = [
    "LANDSCAPE_BUDGET",
    "LANDSCAPE_MAX_BATCHES",
    "Jit",
    "default_grid",
    "landscape_cost",
    "landscape_figure",
]
