"""Who is what: the task plans of a solve, their colours, and plans_histogram.png.

Each particle's verified task plan (`particle_plans`), one colour per task
plan (`plan_colors`), the bars of plans per task plan (`histogram_figure`,
STAMP Fig. 4/5), and the best verified plan of each task plan
(`best_verified`, the panels of plans_topdown.png).

`plan_colors` gives each verified task plan one color, in sorted plan order,
so that the same plan has the same color in figures of runs that found the same
plans; `FAILED_COLOR` is the gray of particles that have none.
"""

from __future__ import annotations

import textwrap

import numpy as np
from matplotlib import colors as mcolors
from matplotlib.figure import Figure

FAILED_COLOR = "#b0b0b0"  # particles that are not returned, or fail in MuJoCo C


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
# The plan of each task plan that plans_topdown.png draws.


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


__all__: list[str] = [
    "FAILED_COLOR",
    "best_verified",
    "histogram_figure",
    "particle_plans",
    "plan_colors",
]
