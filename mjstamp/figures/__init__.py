"""Figures of a solve (STAMP Fig. 3-6, 9, 10), written by `solve --out DIR`.

    result = solve(task, config)
    save_figures(result, Path("out"))  # -> plans_histogram.png, plans_topdown.png,
                                       #    loss.png, svgd_diagnostics.png and,
                                       #    for 2-D θ, landscape.png

Each figure has a `*_figure(result) -> Figure` builder (inspectable in tests
and notebooks) and is saved through the Agg canvas directly: no pyplot, no
global backend switch, so importing or calling this module changes nothing for
a user's own matplotlib session.

`save_figures` and the PNG writer live here; each family of figures has its
module: `plans` (task plans, their colours, plans_histogram.png), `topdown`
(plans_topdown.png), `diagnostics` (loss.png, svgd_diagnostics.png),
`robustness` (robustness.png) and `landscape` (landscape.png). Their public
names, and the constants `FAILED_COLOR`, `FORCE_FRAMES`, `LANDSCAPE_BUDGET`,
`LANDSCAPE_MAX_BATCHES` and `Jit`, are importable from `mjstamp.figures`
itself (the constants are read where they are defined: set them there).
"""

from __future__ import annotations

import io
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mjstamp.figures.diagnostics import diagnostics_figure, loss_figure
from mjstamp.figures.landscape import LANDSCAPE_BUDGET as LANDSCAPE_BUDGET
from mjstamp.figures.landscape import LANDSCAPE_MAX_BATCHES as LANDSCAPE_MAX_BATCHES
from mjstamp.figures.landscape import (
    Jit,
    default_grid,
    landscape_cost,
    landscape_figure,
)
from mjstamp.figures.plans import FAILED_COLOR as FAILED_COLOR
from mjstamp.figures.plans import (
    best_verified,
    histogram_figure,
    particle_plans,
    plan_colors,
)
from mjstamp.figures.robustness import robustness_figure
from mjstamp.figures.topdown import FORCE_FRAMES as FORCE_FRAMES
from mjstamp.figures.topdown import (
    Arrows,
    Footprint,
    PlanDrawing,
    draw_topdown,
    plan_drawing,
    plan_frames,
    topdown_figure,
)
from mjstamp.fileio import write_atomic
from mjstamp.progress import ProgressLike

DPI = 150


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
