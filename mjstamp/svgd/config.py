"""`StampConfig`: the settings of the STAMP loop, each validated on construction.

References:
  STAMP Algorithm 1 (what the settings steer); App. C-B (the defaults).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable

import jax

from mjstamp.errors import MjstampError
from mjstamp.svgd._jacobian import JacobianMode, check_mode

__all__ = ["StampConfig"]


Schedule = Callable[[jax.Array], jax.Array]


def _number(value, name: str, *, zero: bool = False, schedule: bool = False,
            none: bool = False) -> None:
    """A finite number > 0 (>= 0 with `zero`), or else an optax schedule or None if allowed."""
    if (schedule and callable(value)) or (none and value is None):
        return
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not math.isfinite(value)
        or not (value >= 0 if zero else value > 0)
    ):
        what = f"a float {'>=' if zero else '>'} 0"
        what += " or an optax schedule" * schedule + " or None" * none
        raise MjstampError(f"{name} must be {what}; got {value!r}")


def _count(value, name: str, minimum: int) -> None:
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Integral)
        or value < minimum
    ):
        raise MjstampError(f"{name} must be an integer >= {minimum}; got {value!r}")


@dataclasses.dataclass(frozen=True)
class StampConfig:
    """Settings of the STAMP loop; every field is validated on construction.

    The one definition of these settings: `run_stamp` reads them, and
    `mjstamp.SolveConfig.stamp` holds them for a solve (with the solve's own
    defaults, see there).

    Attributes:
      svgd_learning_rate: step size ε of the SVGD phase, in units of θ (float
        > 0 or an optax schedule), used by the default optimizer, Adam; None:
        the caller scales the step per coordinate (`svgd_step`) and passes its
        own optimizer (`mjstamp.solve` does, by each coordinate's box width).
      sgd_learning_rate: step size ε of the SGD phase, likewise (`sgd_step`).
      svgd_step: with `svgd_learning_rate` None, the SVGD step as a fraction
        of each coordinate's scale, which the caller's optimizer applies
        (`run_stamp` itself does not read it): 0.01, so 50 iterations can
        cross half a box.
      sgd_step: likewise for SGD: 0.003, finer, to settle into narrow modes.
      svgd_max_iters: cap on SVGD iterations (>= 0; Algorithm 1 line 3-7); the
        fallback if the convergence test never fires.
      sgd_max_iters: cap on SGD iterations (>= 0, line 8-10; 0 skips refinement).
      min_iters: iterations each phase runs before the test may fire.
      window: W, the number of iterations the test looks back over (>= 1;
        `has_converged`).
      rtol: bound on the relative change of the mean log posterior over W
        iterations, |L̄_t − L̄_{t−W}| / max(|L̄_{t−W}|, 1).
      motion_tol: bound on the mean particle displacement per iteration,
        averaged over the last W iterations, in units of θ; None: the caller
        resolves it before `run_stamp` (`mjstamp.solve`: 1e-4 of the mean box
        width).
      seed: seeds the PRNG keys handed to the steps and to a callable
        `initial_particles`; the same seed gives the same run (a solve sets
        it from its own seed).
      jacobian: 'auto', 'fwd' or 'rev': how the SVGD step differentiates a log
        density that also returns kernel features, and how the SGD step
        differentiates its own (see `build_sgd_step`).
      rescue_window: 0 (off) or R >= 1: in the SVGD phase, a particle that has
        stalled for R consecutive iterations is re-drawn by `run_stamp`'s
        `redraw` (and its optimizer moments zeroed). Stalled: its score norm is
        at most the phase's near-zero threshold (`near_zero_threshold`: it
        feels no gradient) and its log density is at most the population's
        median (it is not resting in a good mode), or either is not finite.
      nonfinite_redraw: 0 (never) or M >= 1: a particle whose log density,
        score or features are not finite is frozen for the iteration (both
        phases) and left out of the kernel of the others; after M consecutive
        such iterations it is re-drawn by `redraw` when one is given (and its
        optimizer moments zeroed), else it stays frozen.
      backtrack: True: in SVGD, a step that leaves a particle's log density
        more than max(1, d/2) nats below its peak in the phase is taken back
        (in discrete SVGD the target at the decoded plan, log p(Γ(θ)), is the
        one guarded): at its next iteration the particle returns to its last
        accepted point, its step scale halves (down to 2^-10) and its
        optimizer moments are zeroed; an accepted step multiplies the scale by
        1.25, up to 1, and scales the particle's next optimizer update.
        Adam's per-coordinate normalisation makes its first step the full
        learning rate whatever the gradient, which throws particles out of
        valleys narrower than that step. In SGD
        the optimizer runs free and each particle ends at the best point it
        visited (steps taken back there would shrink until the convergence
        test ended SGD early). False: every update as the optimizer gives it
        and the last iterate returned (Algorithm 1 as written).
    """

    svgd_learning_rate: float | Schedule | None = 1e-2
    sgd_learning_rate: float | Schedule | None = 1e-2
    svgd_step: float = 0.01
    sgd_step: float = 0.003
    svgd_max_iters: int = 1000
    sgd_max_iters: int = 1000
    min_iters: int = 50
    window: int = 25
    rtol: float = 1e-3
    motion_tol: float | None = 1e-3
    seed: int = 0
    jacobian: JacobianMode = "auto"
    rescue_window: int = 0
    nonfinite_redraw: int = 3
    backtrack: bool = True

    def __post_init__(self):
        """Validates every field (MjstampError naming the field and its range)."""
        for name in ("svgd_learning_rate", "sgd_learning_rate"):
            _number(getattr(self, name), name, schedule=True, none=True)
        for name in ("svgd_step", "sgd_step"):
            _number(getattr(self, name), name)
        _count(self.svgd_max_iters, "svgd_max_iters", 0)
        _count(self.sgd_max_iters, "sgd_max_iters", 0)
        _count(self.min_iters, "min_iters", 0)
        _count(self.window, "window", 1)
        _number(self.rtol, "rtol", zero=True)
        _number(self.motion_tol, "motion_tol", zero=True, none=True)
        _count(self.seed, "seed", 0)
        _count(self.rescue_window, "rescue_window", 0)
        _count(self.nonfinite_redraw, "nonfinite_redraw", 0)
        if not isinstance(self.backtrack, bool):
            raise MjstampError(f"backtrack must be True or False; got {self.backtrack!r}")
        try:
            check_mode(self.jacobian, "jacobian")
        except ValueError as e:
            raise MjstampError(str(e)) from None
