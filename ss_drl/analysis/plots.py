"""Figures and the report: the paper's Fig. 5 (return per episode), Fig. 6 (steps per episode), steps to the first
goal per method, and ``results.md``; plus the ``scripts/plot.py`` command line (:func:`main`).

Figures are drawn on :class:`matplotlib.figure.Figure` objects with the Agg canvas, so importing this module never
touches pyplot or the global matplotlib backend.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ss_drl.analysis.aggregate import (
    EP_LENGTH,
    EP_RETURN,
    AnalysisError,
    Run,
    aggregate_curve,
    first_goal_env_step,
    group_runs,
    load_runs,
    load_train_log,
    markdown_table,
    mean_over_seeds,
    results_table,
)

RESULTS_FILE = "results.md"
PLOTS_DIR = "plots"


def _slug(name: str) -> str:
    """A file-name-safe version of a maze name (which may be a path to a maze file)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_.") or "maze"


def _colors(methods: Sequence[str]) -> dict[str, tuple]:
    """One fixed tab10/tab20 colour per method, the same in every figure."""
    from matplotlib import colormaps

    cmap = colormaps["tab10" if len(methods) <= 10 else "tab20"]
    return {m: cmap(i % cmap.N) for i, m in enumerate(methods)}


def _new_figure(figsize=(7.0, 4.5)) -> Figure:
    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def curve_figure(
    maze: str,
    by_method: dict[str, list[Run]],
    column: str,
    ylabel: str,
    title: str,
    colors: dict[str, tuple],
    smooth: int = 1,
    n_resamples: int = 1000,
    seed: int = 0,
) -> Figure:
    """One line per method: the per-episode mean over seeds of ``column`` with its 95% bootstrap band
    (:func:`~ss_drl.analysis.aggregate.aggregate_curve`)."""
    fig = _new_figure()
    ax = fig.add_subplot()
    for method, runs in by_method.items():
        curve = aggregate_curve([r.episodes[column] for r in runs], smooth, n_resamples, 0.95, seed)
        if curve.episode.size == 0:
            continue
        ax.plot(curve.episode, curve.mean, color=colors[method], lw=1.2, label=f"{method} (n={len(runs)})")
        ax.fill_between(curve.episode, curve.low, curve.high, color=colors[method], alpha=0.25, lw=0)
    smoothing = f", moving average over {smooth} episodes" if smooth > 1 else ""
    ax.set_title(f"{title}: {maze}\nmean over seeds, 95% bootstrap CI{smoothing}", fontsize=10)
    ax.set_xlabel("episode")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(fontsize=8)
    return fig


def learning_figure(maze: str, by_method: dict[str, list[Run]], colors: dict[str, tuple]) -> Figure | None:
    """TD loss and mean Q of the sampled batches over env steps (train.csv): each seed thin, the mean over seeds
    (:func:`~ss_drl.analysis.aggregate.mean_over_seeds`) bold. None when no run has a row in train.csv (the frontier
    explorer has no learning update: its train.csv holds the header only)."""
    logs = {
        method: [log for log in map(load_train_log, runs) if log is not None and len(log["env_steps"])]
        for method, runs in by_method.items()
    }
    logs = {method: method_logs for method, method_logs in logs.items() if method_logs}
    if not any(logs.values()):
        return None
    fig = _new_figure(figsize=(7.0, 6.0))
    axes = fig.subplots(2, 1, sharex=True)
    for ax, column, label in ((axes[0], "loss", "TD loss"), (axes[1], "q_mean", "mean Q of the batch")):
        for method, method_logs in logs.items():
            for log in method_logs:
                ax.plot(log["env_steps"], log[column], color=colors[method], lw=0.5, alpha=0.3)
            steps, mean = mean_over_seeds(method_logs, column)
            if steps.size:
                ax.plot(steps, mean, color=colors[method], lw=1.5, label=f"{method} (n={len(method_logs)})")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_yscale("log")
    axes[0].set_title(f"Learning: {maze}\neach seed thin, mean over seeds bold (train.csv)", fontsize=10)
    axes[1].set_xlabel("env steps")
    if axes[0].lines:
        axes[0].legend(fontsize=8)
    return fig


def first_goal_figure(maze: str, by_method: dict[str, list[Run]], colors: dict[str, tuple], seed: int = 0) -> Figure:
    """Env steps to the first goal per method: a box over the seeds that reached G with every such seed as a point;
    seeds that never reached G are drawn as crosses in a separate "never" row above the boxes and counted in the
    tick labels."""
    fig = _new_figure((max(4.0, 1.6 * len(by_method) + 2), 4.5))
    ax = fig.add_subplot()
    rng = np.random.default_rng(seed)  # horizontal jitter of the points only
    reached = {m: [s for s in (first_goal_env_step(r) for r in runs) if s is not None] for m, runs in by_method.items()}
    top = max((max(v) for v in reached.values() if v), default=1.0)
    never_y = 1.12 * top if top > 0 else 1.0
    labels = []
    any_never = False
    for i, (method, runs) in enumerate(by_method.items()):
        values = reached[method]
        n_never = len(runs) - len(values)
        if values:
            ax.boxplot([values], positions=[i], widths=0.5, showfliers=False, medianprops={"color": "black"})
            ax.scatter(i + rng.uniform(-0.12, 0.12, len(values)), values, color=colors[method], zorder=3, s=18)
        if n_never:
            any_never = True
            ax.scatter(i + rng.uniform(-0.12, 0.12, n_never), [never_y] * n_never, color=colors[method], marker="x",
                       zorder=3, s=30)  # fmt: skip
        labels.append(f"{method}\nreached {len(values)}/{len(runs)}")
    if any_never:
        ax.axhline(0.5 * (top + never_y), color="gray", ls=":", lw=1)
        ax.text(len(by_method) - 0.5, never_y, "never reached", ha="right", va="bottom", fontsize=8, color="gray")
    ax.set_xticks(range(len(by_method)), labels)
    ax.set_xlim(-0.6, len(by_method) - 0.4)
    ax.set_ylabel("env steps to first goal")
    ax.set_title(f"Steps to the first goal: {maze}\nbox over seeds that reached G, one point per seed", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    return fig


def write_plots(
    groups: dict[tuple[str, str], list[Run]],
    out_dir: str | os.PathLike,
    smooth: int = 1,
    n_resamples: int = 1000,
    seed: int = 0,
) -> list[Path]:
    """Write the PNGs of each maze into ``out_dir`` and return their paths: ``<maze>_fig5_return.png``,
    ``<maze>_fig6_length.png``, ``<maze>_first_goal.png`` and, for runs with a train.csv, ``<maze>_learning.png``
    (TD loss and mean Q over env steps)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    colors = _colors(sorted({method for _, method in groups}))
    mazes: dict[str, dict[str, list[Run]]] = {}
    for (maze, method), runs in groups.items():
        mazes.setdefault(maze, {})[method] = runs
    written, used = [], set()
    for maze, by_method in mazes.items():
        stem = _slug(maze)
        while stem in used:  # two maze names that differ only in unsafe characters
            stem += "_"
        used.add(stem)
        figures = {
            f"{stem}_fig5_return.png": curve_figure(
                maze, by_method, EP_RETURN, "average reward per episode", "Fig. 5, return per episode", colors,
                smooth, n_resamples, seed,
            ),
            f"{stem}_fig6_length.png": curve_figure(
                maze, by_method, EP_LENGTH, "steps per episode", "Fig. 6, steps per episode", colors,
                smooth, n_resamples, seed,
            ),
            f"{stem}_first_goal.png": first_goal_figure(maze, by_method, colors, seed),
            f"{stem}_learning.png": learning_figure(maze, by_method, colors),
        }  # fmt: skip
        for name, fig in figures.items():
            if fig is None:
                continue
            fig.savefig(out / name, dpi=120)
            written.append(out / name)
    return written


def make_report(
    dirs: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike | None = None,
    smooth: int = 1,
    n_resamples: int = 1000,
    seed: int = 0,
    warn: Callable[[str], None] | None = None,
) -> tuple[str, list[Path]]:
    """Load the runs under ``dirs``, write the PNGs and ``results.md`` into ``out_dir`` (default
    ``<dirs[0]>/plots``) and return ``(markdown table, written paths)``.

    Skipped runs are reported through ``warn`` (default: one line each on stderr). Raises
    :class:`~ss_drl.analysis.aggregate.AnalysisError` when a dir does not exist or there is no complete run.
    """
    if not dirs:
        raise AnalysisError("no directories given")
    if smooth < 1:
        raise AnalysisError(f"--smooth must be >= 1, got {smooth}")
    if n_resamples < 1:
        raise AnalysisError(f"--bootstrap must be >= 1, got {n_resamples}")
    runs = load_runs(dirs) if warn is None else load_runs(dirs, warn)
    groups = group_runs(runs)
    out = Path(out_dir) if out_dir is not None else Path(dirs[0]) / PLOTS_DIR
    written = write_plots(groups, out, smooth, n_resamples, seed)
    table = markdown_table(results_table(groups, n_resamples, seed))
    results = out / RESULTS_FILE
    results.write_text(
        "# Results\n\n"
        f"{len(runs)} complete runs from {', '.join(str(d) for d in dirs)}. "
        f"CIs: 95% percentile bootstrap over seeds, {n_resamples} resamples, seed {seed}.\n\n"
        + table
        + "\nFirst goal: env steps until G was first reached, over the seeds that reached it. "
        "Return/length: per-seed mean over the episode range, then the mean over seeds. "
        "≤1.05× optimal: env steps until the greedy evaluation reached G within 5% of the shortest path "
        "(median over the seeds that got there). Learned: at least 90% of the greedy evaluations after 75% of the "
        "budget reached G within 5% of the shortest path; its env steps and wall s are those of the first evaluation "
        "of the streak that stays learned (from it on, at least 90% within 5%), median over the seeds that learned. "
        "Method: what each run's resolved config ran (ss_drl/methods.py), never its stored label: `_bounded` is the "
        "model-bounded DQN (count-model bounds on), no suffix the replay-only one.\n"
    )
    written.append(results)
    return table, written


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="plot.py",
        description="Plot and tabulate run directories (Hydra run or multirun dirs, searched recursively), grouped "
        "by maze and by the method each run's resolved config ran (runs from before the learners were renamed "
        "included: one with the count model's bounds on is *_bounded).",
    )
    p.add_argument("dirs", nargs="+", help="directories holding run directories (any depth)")
    p.add_argument("--out", default=None, help=f"output directory (default: <first dir>/{PLOTS_DIR})")
    p.add_argument("--smooth", type=int, default=1, help="moving-average window per seed, in episodes (default: 1)")
    p.add_argument("--bootstrap", type=int, default=1000, help="bootstrap resamples (default: 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap generator (default: 0)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """``scripts/plot.py``: print the results table to stdout, return the exit code (errors: one line on stderr)."""
    args = build_parser().parse_args(argv)
    try:
        table, written = make_report(args.dirs, args.out, args.smooth, args.bootstrap, args.seed)
    except (AnalysisError, OSError) as e:
        print(f"plot.py: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    print(table, end="")
    print(f"wrote {len(written)} files to {written[-1].parent}", file=sys.stderr)
    return 0
