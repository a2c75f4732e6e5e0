"""Evaluate a run's final checkpoint: `python scripts/evaluate.py <run dir> [--episodes N] [--out PNG]`."""

import sys

from ss_drl.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
