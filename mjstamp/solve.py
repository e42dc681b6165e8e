"""Moved to `mjstamp.solver`; `mjstamp.solve` is the function (`from mjstamp import solve`).

This path works for one release: `from mjstamp.solve import solve` still
imports, with one deprecation line, and `mjstamp.solve(task, config)` still
calls the solve after it.
"""

import sys
import types

from mjstamp import _moved

_solver = _moved.alias(__name__, "mjstamp.solver")


class _CallableModule(types.ModuleType):
    """`mjstamp.solve`, once this stub is imported, is this module: it still solves."""

    def __call__(self, *args, **kwargs):
        return _solver.solve(*args, **kwargs)


_solver.__class__ = _CallableModule
sys.modules[__name__] = _solver
