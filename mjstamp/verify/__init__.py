"""Verify: plans replayed in MuJoCo C, decoded, costed, repaired and scored.

What it is for: everything a solve does to plans after STAMP, in the scene's
own physics: the `Replay` of particles (MuJoCo C, or MJX for comparison) with
the poses decode and the task's costs read, computed once (`replay`); the
local search that repairs plans failing in C (`repairs`); Gauss–Newton in C
on a task's residual goals (`landing`); the robustness score
under the task's uncertain physics and the perturbed replays of a saved plan
(`perturbed`).

What it may import: scenes/, tasks/ and the modules below them; never solve,
the results table or figures.
"""

from mjstamp.tasks.problem import Decoded
from mjstamp.verify.landing import Landing, land
from mjstamp.verify.perturbed import Robustness, perturbed_replays, robustness
from mjstamp.verify.repairs import Repair, repair
from mjstamp.verify.replay import (
    Replay,
    cost_c,
    decode,
    residuals_c,
    simulate_c,
    simulate_mjx,
)

__all__ = ["Decoded", "Landing", "Repair", "Replay", "Robustness", "cost_c", "decode", "land",
           "perturbed_replays", "repair", "residuals_c", "robustness", "simulate_c",
           "simulate_mjx"]
