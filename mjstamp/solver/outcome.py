"""What a solve produces: each evaluation's `Outcome`, the `SolveResult`, the plans found.

`problem_jit` compiles a problem's functions through the trace cache, keyed by
the problem; `loss_report` summarises the cost over the solve's phases.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from mjstamp import colliders, results, svgd, verify
from mjstamp.fileio import write_atomic
from mjstamp.progress import ProgressLike
from mjstamp.solver.summary import summarize, to_arrays
from mjstamp.tasks import Problem
from mjstamp.tracecache import cached_jit

#: The largest seed: JAX's PRNG keys take a signed 64-bit integer, NumPy's non-negative ones.
MAX_SEED = 2**63 - 1


@dataclasses.dataclass
class Outcome:
    """Particles θ (n, d) evaluated once: MJX cost and decode, MuJoCo C replay and decode."""

    cost: np.ndarray
    mjx_replay: verify.Replay
    predicted: verify.Decoded
    replay: verify.Replay
    verified: verify.Decoded

    @property
    def good(self) -> np.ndarray:
        """(n,) returned (success in MJX, finite cost) and verified (success in C)."""
        return self.predicted.ok & np.isfinite(self.cost) & self.verified.ok


@dataclasses.dataclass
class SolveResult:
    """Everything a solve produced (the results directory's format: `mjstamp.results`).

    Attributes:
      problem: the problem as solved (on its calibrated gradient model).
      config: {"seed", "task": the task's own settings, "solve": `SolveConfig`}.
      theta: (n, d) final particles (repaired ones replaced by their repair).
      returned: (n,) plans whose MJX rollout succeeds.
      repaired: (n,) returned plans that failed in MuJoCo C and were repaired.
      source: (n,) where each particle's plan comes from: "final", "landed"
        (`_land`), or "unpolished" / "svgd" / "initial" when an earlier state was kept,
        "screen" when a success of the screen was
        (`SolveConfig.verify.keep_visited`; `robust.select`).
      fidelity: the calibration (`Calibration.as_dict`) plus the divergence of
        MJX rollouts from their C replays, initial and final particles.
      screen: the seeding screen (`seeding.Screen.as_dict`) or None.
      rescue: with `SolveConfig.stamp.rescue_window` on, the re-draws and the
        task-plan counts (C replays) of the initial and final particles; None
        when off.
      loss: mean and median cost (MJX) of the particles at the start, at the
        end of SVGD and at the end, and the SVGD phase's share of the decrease
        (`loss_report`).
      devices: how many devices the particles were sharded over.
      robustness: each verified plan's score under the task's uncertain physics
        (`_robustness`), or None (`SolveConfig.verify.robustness_samples` = 0).
      compiles: the XLA compiles the solve did (`_Compiles.report`: count and
        seconds of those >= 0.5 s, the largest by function).
      polish: the precision polish (`_polish_report`), or None where it did
        not run (off, or no residual costs).
      found: {task plan: {"seconds", "source", "theta"}}, each task plan as it
        was first verified in MuJoCo C during the solve (`Found`): the
        screen's successes at once, then the landings', STAMP's, repair's.
      symbol_disagreements: how many returned plans the JAX signed distances
        (sd < 0) would decode to other symbols than MuJoCo C's colliders do;
        C's decode is the one verified (`verify.Replay.symbol_disagreements`;
        its seconds, a compile included the first time: `timings["symbols_s"]`).
    """

    problem: Problem
    config: dict
    theta: np.ndarray
    svgd_theta: np.ndarray
    initial_theta: np.ndarray
    cost: np.ndarray
    returned: np.ndarray
    repaired: np.ndarray
    predicted: verify.Decoded
    verified: verify.Decoded
    replay: verify.Replay
    diagnostics: svgd.StampDiagnostics
    stamp: svgd.StampResult
    rows: list[dict]
    timings: dict[str, float]
    fidelity: dict
    screen: dict | None
    source: np.ndarray
    rescue: dict | None = None
    loss: dict | None = None
    compiles: dict | None = None
    devices: int = 1
    robustness: dict | None = None
    polish: dict | None = None
    found: dict | None = None
    symbol_disagreements: int | None = None

    @property
    def task(self) -> Problem:
        """The problem (the name `figures` and notebooks read)."""
        return self.problem

    @property
    def verified_fraction(self) -> float:
        """Share of returned plans whose MuJoCo C replay succeeds."""
        n = int(self.returned.sum())
        return float((self.verified.ok & self.returned).sum() / n) if n else 0.0

    def verified_mask(self) -> np.ndarray:
        """(n,) returned and verified in MuJoCo C."""
        return self.returned & self.verified.ok

    def summary(self, coverage: dict | None = None) -> dict:
        """JSON-ready summary, the body of plans.json (`solver.summary.summarize`)."""
        return summarize(self, coverage)

    def arrays(self) -> dict[str, dict[str, np.ndarray]]:
        """Arrays of particles.npz and trajectories.npz (`solver.summary.to_arrays`)."""
        return to_arrays(self)

    def save(self, out: str | Path, *, figures: bool = True, coverage: dict | None = None,
             progress: ProgressLike = None) -> list[Path]:
        """Writes the results directory: plans.json, .npz files, scene.mjb[, figures].

        The files of the format are `results.write`'s (atomic, plans.json last;
        only process 0 of several writes); the figures are drawn from this
        result. `mjstamp.load(out)` reads it back; `mjstamp view` plays it.

        Returns:
          The paths written (none on other processes than 0).
        """
        from mjstamp import figures as figures_mod  # noqa: PLC0415 - matplotlib only here

        written = results.write(out, self.summary(coverage), self.arrays(),
                                model=self.problem.scene.m)
        if figures and written:
            written += figures_mod.save_figures(self, Path(out), progress=progress,
                                                jit=problem_jit(self.problem))
        return written


def problem_jit(problem: Problem):
    """`jit(fn, name, *example) -> compiled fn` through the trace cache, keyed by `problem`.

    The key is the problem's fingerprint (its whole declaration, the code of
    its costs included, and the scene) with the gradient model's options, so a
    re-run of a script or notebook skips tracing, and any change traces anew.
    """
    grad = dataclasses.asdict(problem.scene.grad_options)
    # N.B. robust planning's draws and the cost scale are constants of the trace: part of the key.
    consts = "" if problem.robust is None else f" robust={problem.robust.key()}"
    consts += "" if problem.cost_scale == 1 else f" cost_scale={problem.cost_scale!r}"
    # N.B. the collision table is read at trace time (MJX's own inside colliders.mjx_own).
    consts += f" collisions={colliders.table_version()}"

    def jit(fn, name: str, *example):
        # N.B. the label (the name's first word) names the function in compile reports.
        return cached_jit(fn, f"problem={problem.fingerprint} grad={grad}{consts} {name}",
                          *example, label=name.split()[0])

    return jit


class Found:
    """Task plans as they are first verified in MuJoCo C during a solve (plans stream).

    Each new task plan is said at once through the progress reporter and
    recorded with the seconds since the solve started, where it came from and
    its θ; `SolveResult.found` holds the record, and a solve interrupted while
    checkpointing writes it beside the checkpoint (`FOUND_FILE`) before it stops.
    """

    def __init__(self, say, started: float):
        self.say, self.started = say, started
        self.plans: dict[str, dict] = {}

    def add(self, plans, theta, source: str, seconds: dict[str, float] | None = None) -> None:
        """Records the task plans of verified plans (plans (m,) str, θ (m, d)) not seen yet.

        `seconds`: {task plan: when it was verified, since the solve started},
        where that was before now (the screen's chunks).
        """
        now = time.perf_counter() - self.started
        for plan, th in zip(plans, np.asarray(theta, np.float64), strict=True):
            plan = str(plan)
            if plan in self.plans:
                continue
            at = min(now, (seconds or {}).get(plan, now))
            self.plans[plan] = {"seconds": round(at, 3), "source": source,
                                "theta": [float(x) for x in th]}
            self.say(f"verified task plan {plan} at {at:.1f} s ({source}); "
                     f"{len(self.plans)} so far")

    def add_pools(self, pools: dict[str, np.ndarray], source: str,
                  seconds: dict[str, float] | None = None) -> None:
        """Records each task plan of {task plan: (m, d) verified plans, best first}."""
        for plan, pool in sorted(pools.items()):
            if len(pool):
                self.add([plan], np.asarray(pool)[:1], source, seconds)

    def as_dict(self) -> dict[str, dict]:
        """{task plan: {"seconds", "source", "theta"}}, first found first."""
        return dict(sorted(self.plans.items(), key=lambda kv: kv[1]["seconds"]))

    def save(self, directory) -> None:
        """Writes the record to `directory`/FOUND_FILE (atomically)."""
        payload = json.dumps(self.as_dict(), indent=2).encode()
        write_atomic(Path(directory) / FOUND_FILE, lambda f: f.write(payload))


FOUND_FILE = "verified_so_far.json"
"""What an interrupted solve verified before it stopped, beside its checkpoint (`Found.save`)."""


def loss_report(costs: dict[str, np.ndarray]) -> dict:
    """Mean and median cost (MJX, actions at Γ) at the start, the end of SVGD and the end.

    Over the particles whose cost is finite at all three; `svgd_share` is the
    SVGD phase's share of the decrease of the mean, (initial - svgd) /
    (initial - final), None when the mean did not decrease: negative when
    SVGD raised the mean, above 1 when SGD did. "final" is STAMP's own end,
    before `keep_visited` and repair. The two earlier snapshots are evaluated
    whether or not `keep_visited` is on (one MJX forward and C replay each).
    """
    finite = np.all([np.isfinite(c) for c in costs.values()], axis=0)
    out: dict = {"particles": int(finite.sum())}
    for stat, fn in (("mean", np.mean), ("median", np.median)):
        out[stat] = {k: float(fn(c[finite])) if finite.any() else None for k, c in costs.items()}
    mean = out["mean"]
    drop = None if mean["initial"] is None else mean["initial"] - mean["final"]
    out["svgd_share"] = (mean["initial"] - mean["svgd"]) / drop if drop and drop > 0 else None
    return out


