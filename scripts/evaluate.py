"""Evaluate a run's final checkpoint: `python scripts/evaluate.py <run dir> [--episodes N] [--out PNG]`.

The same as the `ss-drl-evaluate` console script of an installed package.
"""

import sys

from ss_drl.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
