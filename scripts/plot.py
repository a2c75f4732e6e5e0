#!/usr/bin/env python
"""Plot and tabulate training runs: Fig. 5 (return per episode), Fig. 6 (steps per episode), steps to the first goal,
and results.md, from run or Hydra multirun directories.

    python scripts/plot.py multirun/2026-11-22/10-00-00 [more dirs] [--out OUT] [--smooth K] [--bootstrap N] [--seed S]

Runs are grouped by maze and by the method their resolved config ran (ss_drl/methods.py), never by the label stored
in summary.json: a run directory written before the learners were renamed (docs/migration.md) with the count
model's bounds on is ``<method>_bounded``.

All the logic lives in :mod:`ss_drl.analysis`; see ``ss_drl.analysis.plots.main``. An installed package runs
the same as the ``ss-drl-plot`` console script.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without `pip install -e .`

from ss_drl.analysis import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
