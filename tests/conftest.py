"""Test-session settings: the CLI's precision policy and the compilation cache.

N.B. `import mjstamp` sets nothing (STYLE.md); like the CLI, the test session
turns on float64 (see mjstamp.scenes.gradsafe) and JAX's persistent compilation
cache, so MJX functions compiled once (20-45 s each on 2 cores) are reused by
later runs and by CLI subprocesses.
"""

import pytest

from mjstamp.cli import configure_jax

configure_jax(precision="float64")


@pytest.fixture(scope="session")
def billiards():
    """The shipped billiards scene, shared so its compiled rollouts are reused."""
    from mjstamp.scenes import Scene

    return Scene.shipped("billiards")


@pytest.fixture(scope="session")
def pushing():
    """The shipped pushing scene, shared so its compiled rollouts are reused."""
    from mjstamp.scenes import Scene

    return Scene.shipped("pushing")
