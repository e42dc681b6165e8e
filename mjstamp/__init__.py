"""mjstamp: differentiable task and motion planning (STAMP) on MuJoCo MJX.

References:
  Lee et al., "Differentiable Task and Motion Planning via Stein Variational
  Gradient Descent" (STAMP).

N.B. importing mjstamp has no side effects: no XLA flags, no x64, no cache
directory. The CLI (or your script) sets those.
"""

__version__ = "0.1.0"
