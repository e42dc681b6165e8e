"""How the particles moved: loss.png and svgd_diagnostics.png, per iteration.

loss.png is STAMP Fig. 10 (mean and best loss); svgd_diagnostics.png shows
the driving and repulsive terms, the kernel bandwidths, the optimizer's steps
and the stalled particles. Both shade the SVGD and SGD phases.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from mjstamp.figures._common import _axis_names

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


__all__: list[str] = ["diagnostics_figure", "loss_figure"]
