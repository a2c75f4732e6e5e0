"""Analysis of run directories: aggregation and bootstrap CIs (:mod:`.aggregate`), figures and the
``results.md`` report (:mod:`.plots`). ``scripts/plot.py`` is a thin wrapper around :func:`main`."""

from ss_drl.analysis.aggregate import (
    AnalysisError,
    Curve,
    IncompleteRun,
    Run,
    TableRow,
    aggregate_curve,
    bootstrap_ci,
    find_run_dirs,
    first_goal_env_step,
    group_runs,
    load_run,
    load_runs,
    markdown_table,
    moving_average,
    near_optimal_env_step,
    results_table,
    table_row,
)
from ss_drl.analysis.plots import build_parser, main, make_report, write_plots

__all__ = [
    "AnalysisError",
    "Curve",
    "IncompleteRun",
    "Run",
    "TableRow",
    "aggregate_curve",
    "bootstrap_ci",
    "build_parser",
    "find_run_dirs",
    "first_goal_env_step",
    "group_runs",
    "load_run",
    "load_runs",
    "main",
    "make_report",
    "markdown_table",
    "moving_average",
    "near_optimal_env_step",
    "results_table",
    "table_row",
    "write_plots",
]
