"""Test-session hooks."""

from __future__ import annotations


def pytest_collection_modifyitems(config, items):
    """Run the learning tests (``tests/test_learning.py``, longest first in the file) before the rest.

    pytest-xdist's worksteal scheduler hands each worker a contiguous share of the collected order and lets an idle
    worker steal from a busy one. The learning runs are the suite's longest tests (the medium_small one took a third
    of its CPU time while it ran 30k env steps); at their place in alphabetical order they started last and ran alone
    at the end, on one of CI's two cores. First in the order, they run beside the rest of the suite. The order within
    each file is kept."""
    items.sort(key=lambda item: item.path.name != "test_learning.py")
