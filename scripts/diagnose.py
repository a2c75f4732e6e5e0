#!/usr/bin/env python
"""Diagnose trained runs: greedy accuracy and value error by distance to G, Q along the greedy path from S, and the
training data's goal share and successes (issue 12, point 5).

    python scripts/diagnose.py <run dir> [<run dir> ...] [--bucket-width 10] [--out DIR]

All the logic lives in :mod:`ss_drl.analysis.diagnose`. An installed package runs the same as the
``ss-drl-diagnose`` console script.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without `pip install -e .`

from ss_drl.analysis.diagnose import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
