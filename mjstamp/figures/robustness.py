"""robustness.png: each verified plan's success share under uncertain physics, per task plan."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from mjstamp.figures.plans import particle_plans, plan_colors


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


__all__: list[str] = ["robustness_figure"]
