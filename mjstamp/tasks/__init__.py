"""Tasks: TAMP problems declared on scenes and compiled into Problems.

A `Task` is a declaration (variables, symbols, costs, success); `task.build()`
compiles it into the frozen `Problem` that solvers consume. The registry of
tasks by name is `mjstamp.registry`; the shipped tasks (`billiards`,
`pushing`, `jaco`) register themselves there.

May import: scenes/, relax/, svgd/ (kernels), skills/ (pushing), config.
"""

from __future__ import annotations

from mjstamp import _moved
from mjstamp.tasks.declaration import Contact, Kind, Term, Variable
from mjstamp.tasks.problem import Decoded, Poses, Problem, Rollout, as_problem
from mjstamp.tasks.task import Task

_MOVED = {
    **dict.fromkeys(("Command", "Entry", "Option", "default_config", "entries", "load", "names",
                     "register", "solve_config", "summaries"), "mjstamp.registry"),
    "parse_overrides": "mjstamp.cli.settings",
}

# N.B. the registry moved out of this package; its old names work for one release.
__getattr__ = _moved.moved_names(__name__, _MOVED)


__all__ = ["Contact", "Decoded", "Kind", "Poses", "Problem", "Rollout", "Task", "Term", "Variable",
           "as_problem"]
