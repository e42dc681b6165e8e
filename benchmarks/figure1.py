"""Reproduces STAMP Figure 1: discrete-and-continuous SVGD on a labelled mixture.

Writes a before/after scatter plot (colour = class label Γ(a), contours = the
mixture) as a PNG and prints per-class statistics as JSON.

Usage:
  python benchmarks/figure1.py                       # writes figure1.png
  python benchmarks/figure1.py --out /tmp/fig1.png --seed 1 --n 300 --iters 500
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

if __package__ in (None, ""):
    # N.B. run as a script, Python puts benchmarks/ on sys.path, not the repository root
    # that `benchmarks.mixture` is found from.
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.mixture import (  # noqa: E402 - after the path set-up above
    component_log_densities,
    figure1_mixture,
    run_figure1,
)

COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


def class_statistics(mixture, theta: np.ndarray) -> dict:
    """Per-class share, mean and std of the particles, next to the truth."""
    labels = theta[:, 2:].argmax(axis=1)
    component = np.asarray(component_log_densities(mixture, jnp.asarray(theta[:, :2])))
    stats = {"label_matches_component": float(np.mean(labels == component.argmax(1)))}
    for c in range(mixture.num_classes):
        x = theta[labels == c, :2]
        stats[f"class_{c + 1}"] = {
            "share": float(np.mean(labels == c)),
            "true_share": float(mixture.weights[c]),
            "mean": x.mean(0).tolist() if len(x) else None,
            "true_mean": np.asarray(mixture.means[c]).tolist(),
            "std": x.std(0).tolist() if len(x) > 1 else None,
            "true_std": np.asarray(mixture.stds[c]).tolist(),
        }
    return stats


def plot(mixture, before: np.ndarray, after: np.ndarray, path: str, iters: int) -> None:
    """Draws the before/after scatter plots over the mixture contours to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = np.linspace(-7, 7, 200)
    gx, gy = np.meshgrid(grid, grid)
    pts = jnp.asarray(np.stack([gx.ravel(), gy.ravel()], 1))
    density = np.exp(jax.nn.logsumexp(component_log_densities(mixture, pts), -1))
    density = np.asarray(density).reshape(gx.shape)

    fig, axes = plt.subplots(1, 2, figsize=(10, 5), sharex=True, sharey=True)
    for ax, theta, title in (
        (axes[0], before, "random initialisation"),
        (axes[1], after, f"after {iters} updates"),
    ):
        levels = density.max() * np.array([0.01, 0.05, 0.1, 0.25, 0.5, 0.75])
        ax.contour(gx, gy, density, levels=levels, colors="0.6", linewidths=0.7)
        labels = theta[:, 2:].argmax(axis=1)
        for c in range(mixture.num_classes):
            sel = labels == c
            ax.scatter(
                theta[sel, 0],
                theta[sel, 1],
                s=8,
                color=COLOURS[c % len(COLOURS)],
                label=f"class {c + 1}",
            )
        ax.set_title(title)
        ax.set_aspect("equal")
        ax.set_xlim(-7, 7)
        ax.set_ylim(-7, 7)
    axes[1].legend(loc="upper right", fontsize=8)
    fig.suptitle(
        "Discrete-and-continuous SVGD on a labelled Gaussian mixture (STAMP Fig. 1)"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    """Runs the reproduction, writes the PNG and prints statistics; returns 0."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="figure1.png", help="PNG path to write")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n", type=int, default=300, help="number of particles")
    parser.add_argument("--iters", type=int, default=500, help="number of updates")
    args = parser.parse_args(argv)
    if args.n < 2:
        parser.error("--n must be >= 2")
    if args.iters < 1:
        parser.error("--iters must be >= 1")
    mixture = figure1_mixture()
    theta0, state, _ = run_figure1(
        jax.random.key(args.seed), n=args.n, iters=args.iters
    )
    before, after = np.asarray(theta0), np.asarray(state.particles)
    plot(mixture, before, after, args.out, args.iters)
    report = {"png": args.out, "seed": args.seed, "n": args.n, "iters": args.iters}
    report["after"] = class_statistics(mixture, after)
    json.dump(report, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
