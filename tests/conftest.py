"""Test-session hooks."""

from __future__ import annotations


def pytest_collection_modifyitems(config, items):
    """Run the learning tests (``tests/test_learning.py``, longest first in the file) before the rest.

    pytest-xdist's worksteal scheduler hands each worker a contiguous share of the collected order and lets an idle
    worker steal from a busy one. The medium_small learning run takes about a third of the suite's CPU time; at its
    place in alphabetical order it started last and ran alone at the end, on one of CI's two cores. First in the
    order, it runs beside the rest of the suite. The order within each file is kept."""
    items.sort(key=lambda item: item.path.name != "test_learning.py")
