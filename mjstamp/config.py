"""Solve settings (`SolveConfig`): validated on construction, unknown keys an error.

Kept apart from a task's own settings (`mjstamp.tasks`), as mujoco_playground
keeps an environment's config apart from its training config. Imports nothing
heavy, so the registry and the CLI can type and check settings up front.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
from collections.abc import Mapping
from typing import Any

from mjstamp.errors import MjstampError, valid_list

#: Most particles a solve takes: the n x n kernel of 65536 in float64 is 32 GiB.
MAX_PARTICLES = 65536


@dataclasses.dataclass(frozen=True)
class SolveConfig:
    """Settings of `solve`, validated on construction (unknown keys are an error).

    Defaults are meant to work on a task nobody tuned: step sizes follow each
    variable's box, iteration caps keep a solve to minutes, and the gradient
    model is calibrated against the scene's own physics before STAMP starts.

    Attributes:
      particles: n >= 2 particles (candidate plans).
      svgd_max_iters: cap on SVGD iterations (Algorithm 1 line 3-7).
      sgd_max_iters: cap on SGD iterations (line 8-10).
      min_iters: iterations each phase runs before the convergence test may end it.
      window: W of the convergence test (`svgd.has_converged`).
      rtol: its relative tolerance on the mean log posterior.
      motion_tol: its bound on the mean displacement per iteration, in units
        of θ; None: 1e-4 of the mean box width.
      svgd_learning_rate: Adam step of the SVGD phase in units of θ (one
        number for every coordinate); None: `svgd_step` of each coordinate's
        box width.
      sgd_learning_rate: likewise for the SGD phase; None: `sgd_step`.
      svgd_step: SVGD step as a fraction of each coordinate's box width (when
        `svgd_learning_rate` is None): 0.01, so 50 iterations can cross half
        the box.
      sgd_step: SGD step as a fraction of the box width: 0.003, finer, to
        settle into narrow modes.
      jacobian: 'auto', 'fwd' or 'rev' (see `svgd.StampConfig`).
      calibrate: pick the gradient solver's iterations so the MJX rollouts
        follow the scene's own physics (`scenes.fidelity.calibrate`).
      fidelity_tolerance: divergence allowed to 95% of the particles, metres;
        None: 1e-3 of the scene's size.
      max_solver_iterations: calibration budget (solver iterations); None:
        the MJCF's own `opt.iterations`.
      allow_unfaithful: solve even when no setting within budget is faithful
        (the result is then marked so).
      repair: refine returned plans whose MuJoCo C replay fails, in C.
      repair_rounds: rounds of the local search per plan.
      repair_samples: candidates per plan and round.
      screen: seed the particles from `screen · particles` candidates of the
        prior replayed in MuJoCo C, spread over the task plans they reach
        (`mjstamp.seeding`); 1 draws them from the prior directly. 64: a
        forward C replay costs ~1.4 µs a step against 25-400 µs for STAMP's
        value and gradient, so 64 candidates per particle cost a few per cent
        of STAMP's 100+ iterations on any scene, and find task plans as rare
        as 1/3000 of the box (billiards: all 16 at seeds 0-2, against 15 with
        16 candidates).
      keep_visited: a particle whose final state is not a verified plan, or
        duplicates another's task plan, returns the plan it held at the end
        of SVGD or at the start if that one was (no plan found is lost).
      rescue_window: 0 (off, the default) or R >= 1: a particle that feels no
        gradient and sits at or below the median log posterior for R
        consecutive SVGD iterations is re-drawn (see `rescue_near`)
        (`svgd.StampConfig.rescue_window`); the summary reports re-draws and
        the task-plan counts of the initial and final particles. Off by
        default: not yet measured on the scene suite.
      rescue_near: share of the re-drawn particles (stall rescue and
        non-finite ones) placed near a success of the seeding screen, with
        noise of `svgd_step` box widths, their task plan chosen uniformly
        among the screen's task plans (`seeding.Redraw`); the rest, and all
        when the screen found none, are drawn from the prior. In [0, 1].
      nonfinite_redraw: a particle whose log posterior, score or features are
        not finite is frozen for the iteration and left out of the kernel of
        the others; after this many such iterations in a row (>= 1; 0: never)
        it is re-drawn (see `rescue_near`) (`svgd.StampConfig.nonfinite_redraw`).
      backtrack: in SVGD, take back a step that leaves a particle's log
        density more than max(1, d/2) nats below the highest it held in the
        phase and halve that particle's step;
        in SGD, end each particle at the best point it visited
        (`svgd.StampConfig.backtrack`); False: every optimizer update as given
        and the last iterate returned (Algorithm 1 as written).
      robustness_samples: M perturbed MuJoCo C replays per verified plan under
        the task's uncertain physics (`Task.uncertain`, the defaults when it
        declared none), for its robustness score (`verify.robustness`); 0: no
        score. The same draws for every plan, seeded by the solve's seed.
      robust: plan for uncertain physics: every particle is rolled out in K =
        `robust` draws of the task's uncertainty (`Problem.with_robust`; the
        same draws throughout the solve, seeded by its seed and apart from the
        score's), and STAMP minimises the expected cost over them (or its CVaR,
        `robust_cvar`); each iteration costs about K times as much. 0: plan for
        the nominal model. `mjstamp solve --robust` sets 8.
      robust_cvar: with `robust`, the share of the worst draws whose mean cost
        is minimised (CVaR at that level), in (0, 1]; 1: the expected cost.
      cost_scale: β, the inverse temperature of the posterior STAMP samples,
        log ρ = −β·C (and β·log p(Γ(θ)) for discrete SVGD's target; named
        apart from the soft indicators' β of `Task.contact`): a number > 0, or
        "auto": β = max(1, ln M / (median − min)) over the costs of the M
        candidates of the seeding screen, so the best candidate stands at least
        ln M nats above the typical one. Costs written in metres (a distance
        to a goal) make a posterior so flat that SVGD's repulsion outweighs its
        driving term and spreads particles out of the valleys; "auto" sharpens
        such a posterior and leaves one already that steep as declared
        (billiards, pushing). Without a screen (`screen` = 1), "auto" is 1.
        Reported costs are C itself, whatever β.
      devices: shard the particles' rollouts over this many devices
        (`mjstamp.parallel`): host devices on a CPU (`mjstamp.configure(devices=N)`
        first), local GPUs on a GPU machine; None: every device JAX sees. The
        plans do not depend on it beyond rounding (see the README).
    """

    particles: int = 128
    svgd_max_iters: int = 50
    sgd_max_iters: int = 100
    min_iters: int = 20
    window: int = 25
    rtol: float = 1e-3
    motion_tol: float | None = None
    svgd_learning_rate: float | None = None
    sgd_learning_rate: float | None = None
    svgd_step: float = 0.01
    sgd_step: float = 0.003
    jacobian: str = "auto"
    calibrate: bool = True
    fidelity_tolerance: float | None = None
    max_solver_iterations: int | None = None
    allow_unfaithful: bool = False
    repair: bool = True
    repair_rounds: int = 8
    repair_samples: int = 32
    screen: int = 64
    keep_visited: bool = True
    rescue_window: int = 0
    rescue_near: float = 0.5
    nonfinite_redraw: int = 3
    backtrack: bool = True
    robustness_samples: int = 32
    robust: int = 0
    robust_cvar: float = 1.0
    cost_scale: float | str = "auto"
    devices: int | None = None

    def __post_init__(self):
        ints = {"particles": 2, "svgd_max_iters": 0, "sgd_max_iters": 0, "min_iters": 0,
                "window": 1, "max_solver_iterations": 1, "repair_rounds": 0,
                "repair_samples": 1, "screen": 1, "rescue_window": 0,
                "nonfinite_redraw": 0, "robustness_samples": 0, "robust": 0, "devices": 1}
        for name, low in ints.items():
            value = getattr(self, name)
            if value is None and name in ("max_solver_iterations", "devices"):
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
                raise MjstampError(f"solve setting {name}={value!r} must be an integer >= {low}")
        if self.particles > MAX_PARTICLES:
            raise MjstampError(
                f"solve setting particles={self.particles} must be at most {MAX_PARTICLES}: the "
                f"n x n kernel of {self.particles} particles needs "
                f"{self.particles**2 * 8 / 2**30:.3g} GiB in float64"
            )
        positive = ("svgd_step", "sgd_step", "rtol")
        optional = ("motion_tol", "svgd_learning_rate", "sgd_learning_rate", "fidelity_tolerance")
        for name in positive + optional:
            value = getattr(self, name)
            if value is None and name in optional:
                continue
            ok = not isinstance(value, bool) and isinstance(value, numbers.Real)
            if not (ok and math.isfinite(value) and value > 0) and not (
                name in ("rtol", "motion_tol") and ok and value == 0
            ):
                what = "a number > 0" + (" or None" if name in optional else "")
                raise MjstampError(f"solve setting {name}={value!r} must be {what}")
        for name in ("calibrate", "allow_unfaithful", "repair", "keep_visited", "backtrack"):
            if not isinstance(getattr(self, name), bool):
                raise MjstampError(
                    f"solve setting {name}={getattr(self, name)!r} must be True or False"
                )
        cvar = self.robust_cvar
        if (isinstance(cvar, bool) or not isinstance(cvar, numbers.Real)
                or not 0 < cvar <= 1):
            raise MjstampError(f"solve setting robust_cvar={cvar!r} must be a number in (0, 1]: "
                               "the share of the worst draws averaged (1: the expected cost)")
        near = self.rescue_near
        if (isinstance(near, bool) or not isinstance(near, numbers.Real)
                or not 0 <= near <= 1):
            raise MjstampError(f"solve setting rescue_near={near!r} must be a number in [0, 1]")
        scale = self.cost_scale
        if scale != "auto" and (isinstance(scale, (bool, str))
                                or not isinstance(scale, numbers.Real)
                                or not (math.isfinite(scale) and scale > 0)):
            raise MjstampError(
                f"solve setting cost_scale={scale!r} must be a number > 0 or 'auto'")
        if self.jacobian not in ("auto", "fwd", "rev"):
            raise MjstampError(
                f"solve setting jacobian={self.jacobian!r} is not valid; valid: auto, fwd, rev"
            )

    @classmethod
    def fields(cls) -> list[str]:
        """Names of the settings."""
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def from_dict(cls, config: Mapping[str, Any] | None, *, ignore=()) -> SolveConfig:
        """Builds a config from a dict; keys in `ignore` (a task's own settings) are skipped.

        Raises:
          MjstampError: a key that is neither a solve setting nor in `ignore`,
            naming it, the closest valid key and every valid one.
        """
        config = dict(config or {})
        valid = cls.fields()
        for key in config:
            if key in valid or key in ignore:
                continue
            close = difflib.get_close_matches(str(key), valid + list(ignore), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise MjstampError(
                f"unknown solve setting {key!r}{hint}; valid: {valid_list(valid + sorted(ignore))}"
            )
        return cls(**{k: v for k, v in config.items() if k in valid})

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready view."""
        return dataclasses.asdict(self)
