"""The solve: STAMP on a task's log posterior, then decode, verify, repair and select plans.

`solve(task, config)` (`pipeline`) builds the task's `Problem` once and runs,
in order: the screen in MuJoCo C (`mjstamp.seeding`), calibration of the
gradient model (`calibrate`), STAMP (`mjstamp.svgd`), the precision polish and
landing, the evaluation of the final particles in MJX and their C replay,
repair, robustness, and the choice of the particles returned (`selection`).
What it produces is a `SolveResult` (`outcome`).

May import: everything below it in `docs/architecture.md` (tasks, svgd,
verify, seeding, checkpoint, results, figures); never baselines, viz or cli.
"""

from mjstamp.config import SolveConfig
from mjstamp.solver.outcome import (
    FOUND_FILE,
    MAX_SEED,
    Found,
    Outcome,
    SolveResult,
    loss_report,
    problem_jit,
)
from mjstamp.solver.pipeline import (
    box_optimizer,
    calibrate,
    mjx_divergence,
    polish_iterations,
    solve,
)
from mjstamp.tasks import as_problem

__all__ = ["FOUND_FILE", "MAX_SEED", "Found", "Outcome", "SolveConfig", "SolveResult",
           "as_problem", "box_optimizer", "calibrate", "loss_report", "mjx_divergence",
           "polish_iterations", "problem_jit", "solve"]
