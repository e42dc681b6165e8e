"""What more than one family of figures reads of a task: the names of θ's coordinates."""

from __future__ import annotations


def _axis_names(task) -> list[str]:
    """Names of θ's coordinates: 'name[k]' for multi-coordinate variables."""
    names = []
    for v in task.variables:
        names += [v.name] if v.size == 1 else [f"{v.name}[{k}]" for k in range(v.size)]
    return names


__all__: list[str] = []
