"""Throughput benchmarks: `python scripts/benchmark.py [--section SECTION|all] [--repeats R] [--quick]`, SECTION one of
env, train, planner, her, update. The train section times `--experiment NAME` (default easy_dqn_her), side by side
with an older checkout's run of it with `--baseline-checkout PATH` (names mapped by docs/migration.md).

All logic lives in the checkout's top-level :mod:`benchmarks` package (not installed with ss-drl).
"""

import sys
from pathlib import Path

# Run from the checkout: put the repository root (which holds `benchmarks/` and `ss_drl/`) first on the path.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.cli import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(main())
