"""Input checks shared by the kernels, the steps and the STAMP loop."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp


def check_particles(
    particles: Any, *, min_particles: int = 2, name: str = "particles"
) -> None:
    """Raises ValueError unless `particles` is a float (n, d) array, n >= min_particles.

    Shapes are static under jit, so inside a traced step this raises while
    tracing, before anything is compiled.
    """
    shape = getattr(particles, "shape", None)
    if shape is None or len(shape) != 2:
        raise ValueError(
            f"{name} must be a 2-D array of shape (n, d); got shape {shape}"
        )
    n, d = shape
    if n < min_particles:
        raise ValueError(
            f"{name}: SVGD needs at least {min_particles} particles "
            f"(n >= {min_particles}); got n={n}"
        )
    if d < 1:
        raise ValueError(f"{name} must have d >= 1 coordinates; got shape {shape}")
    if not jnp.issubdtype(particles.dtype, jnp.floating):
        raise ValueError(
            f"{name} must be a floating array; got dtype {particles.dtype}"
        )
