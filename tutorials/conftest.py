"""Marks the notebooks (executed by nbmake) `slow`, and runs them at their small settings.

MJSTAMP_TUTORIAL_SMALL=1 (set here, inherited by nbmake's kernels) makes each notebook's
first cell choose fewer particles and iterations: the test run checks that every cell
runs end to end; a reader opening the notebook gets the full settings.
"""

import os

import pytest

os.environ.setdefault("MJSTAMP_TUTORIAL_SMALL", "1")


def pytest_collection_modifyitems(items):
    """Adds the `slow` marker to every notebook item, so `-m "not slow"` skips them."""
    for item in items:
        if item.path.suffix == ".ipynb":
            item.add_marker(pytest.mark.slow)
