"""Figures of a solve (STAMP Fig. 3-6, 9, 10), written by `solve --out DIR`.

    result = solve(task, config)
    save_figures(result, Path("out"))  # -> plans_histogram.png, plans_topdown.png,
                                       #    loss.png, svgd_diagnostics.png and,
                                       #    for 2-D θ, landscape.png

Each figure has a `*_figure(result) -> Figure` builder (inspectable in tests
and notebooks) and is saved through the Agg canvas directly: no pyplot, no
global backend switch, so importing or calling this module changes nothing for
a user's own matplotlib session.

`plan_colors` gives each verified task plan one color, in sorted plan order,
so that the same plan has the same color in figures of runs that found the same
plans.

The top-down view reads the poses, colours and contact forces of a C replay
from `mjstamp.geometry`, the module the meshcat playback (`mjstamp.viz`) reads
them from, so a PNG and the playback of the same plan show the same things.
`plan_frames` → `plan_drawing` → `draw_topdown` are its steps, usable on any
replay (tests draw one without a solve).
"""

from __future__ import annotations

import functools
import io
import math
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from matplotlib import colormaps, ticker
from matplotlib import colors as mcolors
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Polygon
from tqdm.auto import tqdm

from mjstamp import geometry
from mjstamp.errors import MjstampError
from mjstamp.fileio import write_atomic
from mjstamp.progress import Progress, ProgressLike

DPI = 150
FAILED_COLOR = "#b0b0b0"  # particles that are not returned, or fail in MuJoCo C
# Particle-steps of MJX forward rollouts the landscape grid may cost: at about
# 5 us per particle-step on a 2-core CPU, 2.4e6 is about 12 s (billiards:
# 126 x 126 grid, 150 steps).
LANDSCAPE_BUDGET = 2.4e6
# Each batch is a call with its own overhead (~1 ms): small n would otherwise
# cost thousands of calls.
LANDSCAPE_MAX_BATCHES = 400
FORCE_FRAMES = 5  # force arrows drawn per geom pair and plan
# How `landscape_cost` compiles: jit(fn, name, *example) -> compiled fn.
Jit = Callable[..., Callable]
# Low cost dark, but not black: particles' black edges must stay visible.
_COST_CMAP = mcolors.ListedColormap(colormaps["Greys_r"](np.linspace(0.2, 1.0, 256)))


def save_figures(
    result,
    out: str | Path,
    *,
    landscape: bool = True,
    grid: int | None = None,
    progress: ProgressLike = None,
    jit: Jit | None = None,
) -> list[Path]:
    """Writes the figures of a solve into `out`, each PNG atomically.

    Args:
      result: a `mjstamp.solver.SolveResult`.
      out: a writable folder (created if missing).
      landscape: draw landscape.png when θ is two-dimensional (it costs about
        `LANDSCAPE_BUDGET` particle-steps of MJX rollouts, ~12 s on a CPU).
      grid: landscape points per axis; None picks one within the budget.
      progress: tqdm bar over the landscape grid; None shows it on a terminal.
      jit: compiles the landscape's cost function (see `landscape_cost`).

    Returns:
      Paths of the files written, in the order plans_histogram.png,
      plans_topdown.png, loss.png, svgd_diagnostics.png[, robustness.png when
      the solve scored its plans][, landscape.png].
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figures = [
        ("plans_histogram.png", lambda: histogram_figure(result)),
        ("plans_topdown.png", lambda: topdown_figure(result)),
        ("loss.png", lambda: loss_figure(result)),
        ("svgd_diagnostics.png", lambda: diagnostics_figure(result)),
    ]
    if getattr(result, "robustness", None) is not None:
        figures.append(("robustness.png", lambda: robustness_figure(result)))
    if landscape and result.task.dim == 2:
        figures.append(
            ("landscape.png",
             lambda: landscape_figure(result, grid=grid, progress=progress, jit=jit))
        )
    written = []
    for name, build in figures:
        target = out / name
        _save(build(), target)
        written.append(target)
    return written


def _save(fig: Figure, path: Path) -> None:
    """Renders with the Agg canvas into memory, then writes the PNG atomically."""
    FigureCanvasAgg(fig)  # attaches itself as fig.canvas
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    write_atomic(path, lambda f: f.write(buffer.getvalue()))


# ----------------------------------------------------------------------------
# Who is what: verified task plans and their colors.


def particle_plans(result) -> np.ndarray:
    """(n,) verified task plan of each particle; None where not returned or failed."""
    ok = result.returned & result.verified.ok
    return np.array([p if good else None for p, good in zip(result.verified.plan, ok,
                                                            strict=True)], dtype=object)


def plan_colors(result) -> dict[str, tuple]:
    """{verified task plan: RGBA}, from tab20 in sorted plan order (cycles past 20)."""
    found = sorted({p for p in particle_plans(result) if p is not None})
    palette = [mcolors.to_rgba(c) for c in (*_TAB20_STRONG, *_TAB20_LIGHT)]
    return {p: palette[k % len(palette)] for k, p in enumerate(found)}


# tab20 reordered, strong colors first, so a few plans never get two shades of
# one hue; its grays are left out: gray means "not returned or failed".
_TAB20_STRONG = [f"C{k}" for k in (0, 1, 2, 3, 4, 5, 6, 8, 9)]
_TAB20_LIGHT = ["#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5",
                "#c49c94", "#f7b6d2", "#dbdb8d", "#9edae5"]


# ----------------------------------------------------------------------------
# plans_histogram.png (Fig. 4/5).


def histogram_figure(result) -> Figure:
    """Bars of plans per task plan: verified in MuJoCo C, and failed (STAMP Fig. 4/5).

    Rows come from `result.rows`: a verified plan counts under the task plan of
    its C replay, a failed one under its MJX-predicted task plan, "(failed)".
    """
    task = result.task
    rows = result.rows
    n = result.theta.shape[0]
    width = max(6.0, 0.45 * len(rows) + 2.0)
    fig = Figure(figsize=(width, 4.5), layout="constrained")
    ax = fig.add_subplot()
    verified_total = int(result.verified_mask().sum())
    ax.set_title(
        f"{task.name}: verified plans per task plan\n"
        f"{verified_total} verified of {int(result.returned.sum())} returned, "
        f"{n} particles, seed {result.config.get('seed', 0)}"
    )
    symbols = ", ".join(c.name for c in task.contacts)
    # Wrapped: with four symbols the label is wider than a narrow figure.
    ax.set_xlabel(
        textwrap.fill(f"task plan (bits: {symbols}; then actions and success label)", 60)
        if symbols else "task plan"
    )
    ax.set_ylabel("plans")
    if not rows:
        ax.text(0.5, 0.5, "no plans returned", ha="center", va="center",
                transform=ax.transAxes, fontsize=12)
        ax.set_xticks([])
        return fig
    x = np.arange(len(rows))
    verified = np.array([r["verified"] for r in rows])
    failed = np.array([r["plans"] - r["verified"] for r in rows])
    bars = ax.bar(x, verified, color="C0", label="verified in MuJoCo C")
    ax.bar_label(bars, labels=[str(v) if v else "" for v in verified], padding=2, fontsize=8)
    if failed.any():
        some = failed > 0  # a zero-height bar would still draw its edge
        bars = ax.bar(x[some], failed[some], bottom=verified[some], color="#f4a6a6",
                      edgecolor="C3", hatch="//", linewidth=0.5,
                      label="returned by MJX, failed in MuJoCo C")
        ax.bar_label(bars, labels=[str(v) for v in failed[some]], padding=2, fontsize=8)
    ax.set_xticks(x, [r["task_plan"] for r in rows], rotation=45, ha="right",
                  rotation_mode="anchor", fontsize=8)
    ax.set_xlim(-0.6, len(rows) - 0.4)
    ax.set_ylim(0, (verified + failed).max() * 1.15 + 0.5)
    ax.yaxis.get_major_locator().set_params(integer=True)
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    ax.legend(loc="upper right")
    return fig


# ----------------------------------------------------------------------------
# robustness.png: success share under uncertain physics, per task plan.


def robustness_figure(result) -> Figure:
    """Each verified plan's robustness score, one row per task plan (best and median marked).

    The score is the share of perturbed MuJoCo C replays in which the plan
    still succeeds (`verify.robustness`).
    """
    rob = result.robustness
    success = np.asarray(rob["success"], float)
    plans = particle_plans(result)
    colors = plan_colors(result)
    rows = [p for p in colors if np.isfinite(success[plans == p]).any()]
    fig = Figure(figsize=(7, 2.4 + 0.32 * max(len(rows), 1)), layout="constrained")
    ax = fig.add_subplot()
    robust = result.config.get("solve", {}).get("robust") or 0
    if isinstance(robust, dict):  # N.B. a nested config: {"draws": K, "cvar": A}
        robust = robust.get("draws") or 0
    how = f"robust planning, K = {robust}" if robust else "nominal planning"
    # N.B. two lines: one ran off a 7-inch figure's right edge ("…32 perturbed repla").
    ax.set_title(f"{result.task.name}: plans under uncertain physics\n"
                 f"{how}; {rob['samples']} perturbed replays each")
    ax.set_xlabel("robustness: share of perturbed replays that still succeed")
    ax.set_xlim(-0.03, 1.03)
    if not rows:
        ax.text(0.5, 0.5, "no verified plan to score", ha="center", va="center",
                transform=ax.transAxes)
        ax.set_yticks([])
        return fig
    jitter = np.random.default_rng(0)
    for k, p in enumerate(rows):
        s = success[(plans == p) & np.isfinite(success)]
        y = k + jitter.uniform(-0.18, 0.18, len(s))
        ax.scatter(s, y, s=14, color=colors[p], edgecolor="black", linewidth=0.4, zorder=3)
        ax.plot([np.median(s)] * 2, [k - 0.32, k + 0.32], color="black", linewidth=1.5,
                zorder=4, label="median" if k == 0 else None)
        ax.scatter([s.max()], [k], marker="D", s=36, facecolor="none", edgecolor="C3",
                   linewidth=1.4, zorder=5, label="best" if k == 0 else None)
    ax.set_yticks(range(len(rows)), [str(p) for p in rows])
    ax.set_ylim(len(rows) - 0.5, -0.5)
    ax.set_ylabel("task plan")
    ax.grid(axis="x", alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    return fig


# ----------------------------------------------------------------------------
# loss.png (Fig. 10).


def loss_figure(result) -> Figure:
    """Mean and best loss C(θ) = −log ρ(θ) per iteration, SVGD and SGD phases shaded.

    References: STAMP Fig. 10.
    """
    d = result.diagnostics
    mean = -np.asarray(d.logdensity_mean, float)
    best = -np.asarray(d.logdensity_max, float)
    phase = np.asarray(d.phase)
    it = np.arange(1, len(phase) + 1)
    fig = Figure(figsize=(7, 4.2), layout="constrained")
    ax = fig.add_subplot()
    ax.set_title(f"{result.task.name}: loss over STAMP iterations "
                 f"({result.theta.shape[0]} particles)")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss  C(θ) = −log ρ(θ)")
    if len(it) == 0:
        ax.text(0.5, 0.5, "no iterations run", ha="center", va="center",
                transform=ax.transAxes)
        return fig
    _shade_phases(ax, phase)
    ax.plot(it, mean, color="C0", label="mean over particles")
    ax.plot(it, best, color="C3", label="best particle")
    finite = np.concatenate([mean[np.isfinite(mean)], best[np.isfinite(best)]])
    if finite.size and finite.min() > 0:
        ax.set_yscale("log")
        # Headroom for the phase labels at the top.
        ax.set_ylim(finite.min() / 1.5, finite.max() * 3)
    elif finite.size:
        span = finite.max() - finite.min() or 1.0
        ax.set_ylim(finite.min() - 0.05 * span, finite.max() + 0.3 * span)
    ax.set_xlim(0.5, it[-1] + 0.5)
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    return fig


def _shade_phases(ax, phase: np.ndarray, *, label: bool = True) -> None:
    """Shades the SVGD and SGD iterations of an axes over iterations 1..T, and names them."""
    names = {0: ("SVGD", "#dbe9f6"), 1: ("SGD", "#fde5cc")}
    it = np.arange(1, len(phase) + 1)
    # Contiguous runs of one phase (SVGD then SGD; either may be empty).
    edges = np.flatnonzero(np.diff(phase)) + 1
    for run in np.split(np.arange(len(phase)), edges):
        name, color = names.get(int(phase[run[0]]), (f"phase {phase[run[0]]}", "#eeeeee"))
        lo, hi = it[run[0]] - 0.5, it[run[-1]] + 0.5
        ax.axvspan(lo, hi, color=color, zorder=0)
        if label:
            ax.text((lo + hi) / 2, 0.97, f"{name}\n{len(run)} iterations", ha="center",
                    va="top", transform=ax.get_xaxis_transform(), fontsize=9)


# ----------------------------------------------------------------------------
# svgd_diagnostics.png: why particles move, or do not.


def diagnostics_figure(result) -> Figure:
    """What drives the particles at each iteration, SVGD and SGD phases shaded.

    Four panels over iterations: the norms of the driving term
    D_i = Σ_j a_j k_ji ∇log ρ(θ_j) and of the repulsive term R_i = Σ_j a_j ∇_{θ_j} k_ji
    (mean and median over particles, with the median score norm ‖∇log ρ(θ_i)‖
    for scale); the kernel bandwidth of each group; the step the optimizer
    took, mean ‖Δθ_i‖ and per coordinate, next to ε · mean ‖φ_i‖, the step of
    plain gradient ascent (their ratio is the optimizer's gain; ε is the rate
    the optimizer state exposes, so for an Adam chained with a rescaling, as
    solve's box-relative steps are, this line is off by that scale); and the
    share of particles whose score is near zero (`StampDiagnostics.near_zero_share`),
    with the median share of a particle's own score in its driving term
    (`StampDiagnostics.self_weight_median`) and the share of particles whose
    last step was taken back (`StampDiagnostics.backtracked`).

    Args:
      result: anything with `diagnostics` (a `StampDiagnostics`): a
        `SolveResult` or a `StampResult`; a `task` gives the title and the
        coordinate names.

    Returns:
      The Figure (2 × 2 panels).

    References:
      STAMP eq. (1), (4) (the two terms), App. B-C (bandwidths), Fig. 10.
    """
    d = result.diagnostics
    phase = np.asarray(d.phase)
    it = np.arange(1, len(phase) + 1)
    task = getattr(result, "task", None)
    fig = Figure(figsize=(12, 7.5), layout="constrained")
    axes = fig.subplots(2, 2, sharex=True)
    (terms, bands), (steps, stalled) = axes
    title = "SVGD diagnostics"
    if task is not None:
        title = f"{task.name}: {title}"
    fig.suptitle(f"{title} ({d.displacement_per_coordinate.shape[1]}-D θ)")
    titles = (
        (terms, "driving term ‖Σ a_j k_ji ∇log ρ_j‖ vs repulsive term ‖Σ a_j ∇k_ji‖",
         "norm"),
        (bands, "kernel bandwidth per group", "bandwidth s_g"),
        (steps, "step after the optimizer", "step  ‖Δθ‖  (θ units)"),
        (stalled, "scores near zero; own score's share of the driving term", "share"),
    )
    for ax, name, ylabel in titles:
        ax.set_title(name, fontsize=10)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    for ax in (steps, stalled):
        ax.set_xlabel("iteration")
    if len(it) == 0:
        for ax in axes.ravel():
            ax.text(0.5, 0.5, "no iterations run", ha="center", va="center",
                    transform=ax.transAxes)
        return fig
    for ax in axes.ravel():
        _shade_phases(ax, phase, label=ax is terms or ax is bands)
        ax.set_xlim(0.5, it[-1] + 0.5)
    _terms_panel(terms, it, d)
    _bandwidth_panel(bands, it, d)
    _steps_panel(steps, it, d, task)
    particles = getattr(result, "theta", getattr(result, "particles", None))
    _stalled_panel(stalled, it, d, None if particles is None else int(np.shape(particles)[0]))
    return fig


def _line(ax, it, y, **kw) -> np.ndarray:
    """Plots y over iterations where any of it is finite; returns y as floats."""
    y = np.asarray(y, float)
    if np.any(np.isfinite(y)):
        ax.plot(it, y, **kw)
    return y


def _terms_panel(ax, it, d) -> None:
    drawn = [
        _line(ax, it, d.driving_norm_mean, color="C0", label="driving, mean"),
        _line(ax, it, d.driving_norm_median, color="C0", ls="--", label="driving, median"),
        _line(ax, it, d.repulsion_norm_mean, color="C3", label="repulsive, mean"),
        _line(ax, it, d.repulsion_norm_median, color="C3", ls="--",
              label="repulsive, median"),
        _line(ax, it, d.score_norm_median, color="0.35", ls=":",
              label="score ‖∇log ρ(θ_i)‖, median"),
    ]
    _log_axis(ax, np.concatenate(drawn))
    ax.legend(loc="lower left", fontsize=8)


def _bandwidth_panel(ax, it, d) -> None:
    bandwidth = np.asarray(d.bandwidth, float)
    if bandwidth.shape[1] and np.any(np.isfinite(bandwidth)):
        for g in range(bandwidth.shape[1]):
            _line(ax, it, bandwidth[:, g], color=f"C{g}", label=f"group {g}")
        _log_axis(ax, bandwidth.ravel())
        ax.legend(loc="lower left", fontsize=8)
    else:
        ax.text(0.5, 0.5, "no kernel", ha="center", va="center", transform=ax.transAxes)


def _steps_panel(ax, it, d, task) -> None:
    per_coordinate = np.asarray(d.displacement_per_coordinate, float)
    names = _axis_names(task) if task is not None else []
    if len(names) != per_coordinate.shape[1]:
        names = [f"θ[{k}]" for k in range(per_coordinate.shape[1])]
    drawn = [_line(ax, it, d.displacement, color="k", lw=1.8, label="mean ‖Δθ_i‖")]
    plain = np.asarray(d.learning_rate, float) * np.asarray(d.direction_norm_mean, float)
    drawn.append(_line(ax, it, plain, color="k", ls="--", lw=1.2,
                       label="ε · mean ‖φ_i‖ (plain gradient step)"))
    shown = min(per_coordinate.shape[1], 8)  # more lines than colors say nothing
    for k in range(shown):
        drawn.append(_line(ax, it, per_coordinate[:, k], color=f"C{k}", lw=0.8, alpha=0.8,
                           label=f"mean |Δ{names[k]}|"))
    _log_axis(ax, np.concatenate(drawn))
    ax.legend(loc="lower left", fontsize=7, ncols=2)


def _stalled_panel(ax, it, d, n: int | None) -> None:
    share = _line(ax, it, d.near_zero_share, color="C2",
                  label="particles with ‖∇log ρ(θ_i)‖ ≤ τ "
                        "(τ = 1e-3 × median nonzero score at phase start)")
    own = _line(ax, it, d.self_weight_median, color="C4", ls="--",
                label="a_i k_ii / Σ_j a_j k_ji, median (1/n: a particle follows the crowd)")
    back = getattr(d, "backtracked", None)
    if n and back is not None and np.any(np.asarray(back) > 0):
        _line(ax, it, np.asarray(back, float) / n, color="C1", ls=":",
              label="particles whose last step was taken back (backtrack)")
    ax.set_ylim(-0.02, 1.02)
    if np.any(np.isfinite(share)) or np.any(np.isfinite(own)):
        ax.legend(loc="upper left", fontsize=8)


def _log_axis(ax, values: np.ndarray, *, decades: float = 6.0) -> None:
    """Log y scale when the positive finite values span more than a decade.

    The axis shows at most `decades` below the largest value: a median score of
    1e-18 (most particles on a plateau) would squeeze every other line flat; the
    near-zero panel says how many particles are down there.
    """
    v = values[np.isfinite(values) & (values > 0)]
    if v.size and v.max() > 10 * v.min():
        ax.set_yscale("log")
        ax.set_ylim(max(v.min(), v.max() * 10.0**-decades) / 2, v.max() * 2)


# ----------------------------------------------------------------------------
# landscape.png (Fig. 9).


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


def _axis_names(task) -> list[str]:
    """Names of θ's coordinates: 'name[k]' for multi-coordinate variables."""
    names = []
    for v in task.variables:
        names += [v.name] if v.size == 1 else [f"{v.name}[{k}]" for k in range(v.size)]
    return names


def _scatter_by_plan(ax, theta, plans, colors) -> None:
    theta = np.asarray(theta)
    failed = np.array([p is None for p in plans])
    ax.scatter(theta[failed, 0], theta[failed, 1], s=14, c=FAILED_COLOR, edgecolors="k",
               linewidths=0.3, zorder=3)
    for p, color in colors.items():
        mask = plans == p
        ax.scatter(theta[mask, 0], theta[mask, 1], s=18, color=color, edgecolors="k",
                   linewidths=0.4, zorder=4)


# ----------------------------------------------------------------------------
# plans_topdown.png (Fig. 3/6).


def best_verified(result) -> list[tuple[str, int]]:
    """(task plan, particle) of the lowest-cost verified plan of each task plan.

    In the order of `result.rows` (most verified plans first).
    """
    ok = result.verified_mask()
    out = []
    for r in result.rows:
        good = [i for i in r["particles"] if ok[i]]
        if good:
            out.append((r["task_plan"], min(good, key=lambda i: result.cost[i])))
    return out


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
    "Arrows",
    "Footprint",
    "PlanDrawing",
    "best_verified",
    "default_grid",
    "diagnostics_figure",
    "draw_topdown",
    "histogram_figure",
    "landscape_cost",
    "landscape_figure",
    "loss_figure",
    "particle_plans",
    "plan_colors",
    "plan_drawing",
    "plan_frames",
    "save_figures",
    "topdown_figure",
]
