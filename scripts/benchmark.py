"""Throughput benchmarks: `python scripts/benchmark.py [--section env|train|planner|her|all] [--repeats R] [--quick]`.

All logic lives in :mod:`ss_drl.benchmark`.
"""

from ss_drl.benchmark import main

if __name__ == "__main__":
    raise SystemExit(main())
