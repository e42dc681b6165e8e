"""Marks the notebooks (executed by nbmake) `slow`, like the suite's end-to-end solves."""

import pytest


def pytest_collection_modifyitems(items):
    """Adds the `slow` marker to every notebook item, so `-m "not slow"` skips them."""
    for item in items:
        if item.path.suffix == ".ipynb":
            item.add_marker(pytest.mark.slow)
