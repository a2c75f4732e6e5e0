"""Find, load and aggregate run directories: learning curves, bootstrap CIs and the results table.

A *run directory* is any directory holding :data:`~ss_drl.training.outputs.SUMMARY_FILE`; it must also hold
:data:`~ss_drl.training.outputs.EPISODES_FILE` and :data:`~ss_drl.training.outputs.EVAL_FILE`. The file names, CSV
columns and summary keys all come from :mod:`ss_drl.training.outputs`, the single source of truth for the format.

Nothing here imports matplotlib; the figures live in :mod:`ss_drl.analysis.plots`.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ss_drl.analysis.tables import format_markdown_table
from ss_drl.methods import method_label
from ss_drl.training.learned import BOUND, LAST_QUARTER, SHARE, EvalRecord, Learned, learned
from ss_drl.training.outputs import (
    CHECKPOINT_FILE,
    EPISODE_COLUMNS,
    EPISODES_FILE,
    EVAL_COLUMNS,
    EVAL_FILE,
    FAILED_FILE,
    SUMMARY_FILE,
    SUMMARY_KEYS,
    TRAIN_COLUMNS,
    TRAIN_FILE,
)

#: Files that mark a directory as a run directory (complete or not).
RUN_MARKERS = (SUMMARY_FILE, EPISODES_FILE, CHECKPOINT_FILE, FAILED_FILE)


def _field(names: tuple[str, ...], name: str) -> str:
    """Return ``name`` after checking that the output contract in :mod:`ss_drl.training.outputs` defines it.

    Each column or key this module reads is named exactly once, below, and checked at import time, so that renaming it
    in ``outputs.py`` fails loudly here instead of silently reading nothing.
    """
    if name not in names:
        raise ImportError(f"ss_drl.training.outputs no longer defines {name!r}; update ss_drl.analysis.aggregate")
    return name


# episodes.csv columns read here
EP_EPISODE = _field(EPISODE_COLUMNS, "episode")
EP_ENV_STEPS = _field(EPISODE_COLUMNS, "env_steps")
EP_LENGTH = _field(EPISODE_COLUMNS, "length")
EP_RETURN = _field(EPISODE_COLUMNS, "return")
EP_SUCCESS = _field(EPISODE_COLUMNS, "success")
# eval.csv columns read here
EV_ENV_STEPS = _field(EVAL_COLUMNS, "env_steps")
EV_EPISODE = _field(EVAL_COLUMNS, "episode")
EV_LENGTH = _field(EVAL_COLUMNS, "eval_length")
EV_SUCCESS = _field(EVAL_COLUMNS, "eval_success")
EV_WALL = _field(EVAL_COLUMNS, "wall_s")  # optional: eval.csv files from before it exist (NaN then)
# summary.json keys read here
SK_METHOD = _field(SUMMARY_KEYS, "method")
SK_MAZE = _field(SUMMARY_KEYS, "maze")
SK_SEED = _field(SUMMARY_KEYS, "seed")
SK_COMPLETED = _field(SUMMARY_KEYS, "completed")
SK_FIRST_GOAL = _field(SUMMARY_KEYS, "first_goal_env_step")
SK_EPISODES = _field(SUMMARY_KEYS, "episodes")
SK_OPTIMAL = _field(SUMMARY_KEYS, "optimal_length")
SK_ENV_STEPS = _field(SUMMARY_KEYS, "env_steps")
SK_WALL = _field(SUMMARY_KEYS, "wall_s")
SK_ACCURACY = _field(SUMMARY_KEYS, "final_greedy_accuracy")
SK_EVAL_RATE = _field(SUMMARY_KEYS, "final_eval_success_rate")
SK_EVAL_LENGTH = _field(SUMMARY_KEYS, "final_eval_length")
SK_SLIP = _field(SUMMARY_KEYS, "slip")

#: Numeric columns parsed from each CSV (the others, e.g. the ``ss_target`` string, are only checked for presence).
EPISODE_NUMERIC = (EP_EPISODE, EP_ENV_STEPS, EP_LENGTH, EP_RETURN, EP_SUCCESS)
#: The episodes.csv columns a run may lack: all but those read here (later versions added columns; older run
#: directories still load).
EPISODE_OPTIONAL = tuple(c for c in EPISODE_COLUMNS if c not in EPISODE_NUMERIC)
EVAL_NUMERIC = (EV_ENV_STEPS, EV_EPISODE, EV_LENGTH, EV_SUCCESS, EV_WALL)
#: Columns a run's eval.csv may lack (older runs): read as NaN.
EVAL_OPTIONAL = (EV_WALL,)

#: Episodes ``1..EARLY_EPISODES`` are the "early" block of the table, the rest the "late" one.
EARLY_EPISODES = 100
#: A greedy evaluation is "near optimal" when it succeeds with ``eval_length <= NEAR_OPTIMAL * optimal_length`` (the
#: bound of the learned rule, :mod:`ss_drl.training.learned`).
NEAR_OPTIMAL = float(BOUND)


class AnalysisError(Exception):
    """A problem that stops the analysis as a whole (no such directory, no complete runs)."""


class IncompleteRun(Exception):
    """A run directory that cannot be used; the message says why (one line)."""


@dataclass
class Run:
    """One loaded run directory.

    ``episodes`` and ``evals`` map the numeric columns (:data:`EPISODE_NUMERIC`, :data:`EVAL_NUMERIC`) to float arrays,
    one entry per CSV row in file order; ``episodes[EP_EPISODE]`` is always ``1..N``. A column of
    :data:`EVAL_OPTIONAL` that the file lacks is all NaN.
    """

    path: Path
    summary: dict
    episodes: dict[str, np.ndarray]
    evals: dict[str, np.ndarray]

    @property
    def maze(self) -> str:
        """The maze's name, with its slip when the moves slip (``easy (slip 0.1)``): a maze with stochastic moves is
        another environment, and its runs are never pooled with the deterministic maze's."""
        slip = self.summary.get(SK_SLIP)
        name = str(self.summary[SK_MAZE])
        return f"{name} (slip {slip:g})" if _is_number(slip) and slip > 0 else name

    @property
    def method(self) -> str:
        """The method its resolved config ran (:func:`~ss_drl.methods.method_label`), never the stored label: a run
        written before the learners were named (docs/migration.md) with the count model's bounds on is
        ``*_bounded``. The stored label serves only a summary without a config that names the agent, HER and Smart
        Start (hand-written ones)."""
        config = self.summary.get("config")
        if isinstance(config, dict):
            try:
                return method_label(config)
            except (KeyError, TypeError, ValueError):  # a config without the agent, her or smart_start it reads
                pass
        return str(self.summary[SK_METHOD])

    @property
    def seed(self):
        return self.summary[SK_SEED]

    @property
    def n_episodes(self) -> int:
        return len(self.episodes[EP_EPISODE])


# ----------------------------------------------------------------------------------------------------------------------
# Finding and loading runs
# ----------------------------------------------------------------------------------------------------------------------


def find_run_dirs(roots: Iterable[str | os.PathLike]) -> list[Path]:
    """Every run directory at or below ``roots`` (holding any of ``RUN_MARKERS``: finished, running, interrupted or
    failed), sorted and without duplicates.

    Raises :class:`AnalysisError` when a root is not an existing directory.
    """
    found: set[Path] = set()
    for root in roots:
        root = Path(root)
        if not root.is_dir():
            raise AnalysisError(f"not a directory: {root}")
        for dirpath, dirnames, filenames in os.walk(root):
            dirnames.sort()
            if any(marker in filenames for marker in RUN_MARKERS):
                found.add(Path(dirpath).resolve())
    return sorted(found)


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def read_run_csv(
    path: Path, columns: tuple[str, ...], numeric: tuple[str, ...], optional: tuple[str, ...] = ()
) -> dict[str, np.ndarray]:
    """Read a run CSV strictly: the header must hold ``columns`` (except those in ``optional``), every row must have
    the header's field count and every ``numeric`` cell must parse as a finite number. Raises :class:`IncompleteRun`
    otherwise. A ``numeric`` column of ``optional`` that the header lacks is returned all NaN."""
    name = path.name
    if not path.is_file():
        raise IncompleteRun(f"missing {name}")
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise IncompleteRun(f"cannot read {name}: {_one_line(e)}") from None
    if not rows:
        raise IncompleteRun(f"{name} is empty (no header)")
    header = rows[0]
    missing = [c for c in columns if c not in header and c not in optional]
    if missing:
        raise IncompleteRun(f"{name} lacks columns {', '.join(missing)}")
    where = [header.index(c) if c in header else None for c in numeric]
    values = np.full((len(rows) - 1, len(numeric)), math.nan)
    for i, row in enumerate(rows[1:]):
        line = i + 2
        if len(row) != len(header):
            raise IncompleteRun(f"{name} line {line} has {len(row)} fields, expected {len(header)} (partial file?)")
        for j, k in enumerate(where):
            if k is None:
                continue
            try:
                v = float(row[k])
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise IncompleteRun(f"{name} line {line}: bad {numeric[j]} value {row[k]!r}")
            values[i, j] = v
    return {c: values[:, j].copy() for j, c in enumerate(numeric)}


def load_run(path: str | os.PathLike) -> Run:
    """Load one run directory; raises :class:`IncompleteRun` (with a one-line reason) when it cannot be used.

    A run is incomplete when a file is missing or unreadable, a CSV row is cut short, ``summary.json`` lacks the
    keys used here or says ``completed: false``, the episode column is not ``1..N``, ``episodes.csv`` has fewer or
    more rows than the summary's episode count (a partially written file), or eval.csv's env steps go back.
    """
    path = Path(path)
    failed = path / FAILED_FILE
    if failed.is_file():
        lines = failed.read_text(errors="replace").strip().splitlines()
        raise IncompleteRun(f"the job failed: {_one_line(lines[-1]) if lines else '(no message)'}")
    summary_path = path / SUMMARY_FILE
    try:
        summary = json.loads(summary_path.read_text())
    except FileNotFoundError:
        raise IncompleteRun(f"missing {SUMMARY_FILE}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise IncompleteRun(f"unreadable {SUMMARY_FILE}: {_one_line(e)}") from None
    if not isinstance(summary, dict):
        raise IncompleteRun(f"{SUMMARY_FILE} is not a JSON object")
    missing = [k for k in (SK_METHOD, SK_MAZE, SK_SEED, SK_COMPLETED) if k not in summary]
    if missing:
        raise IncompleteRun(f"{SUMMARY_FILE} lacks {', '.join(missing)}")
    if summary[SK_COMPLETED] is not True:
        raise IncompleteRun(f"{SUMMARY_FILE} says {SK_COMPLETED}={json.dumps(summary[SK_COMPLETED])}")
    for key, kind in ((SK_MAZE, str), (SK_METHOD, str), (SK_SEED, int)):  # they name the run's row and group
        if not isinstance(summary[key], kind) or isinstance(summary[key], bool):
            raise IncompleteRun(f"{SUMMARY_FILE}: {key} is {json.dumps(summary[key])}, not a {kind.__name__}")
    episodes = read_run_csv(path / EPISODES_FILE, EPISODE_COLUMNS, EPISODE_NUMERIC, EPISODE_OPTIONAL)
    evals = read_run_csv(path / EVAL_FILE, EVAL_COLUMNS, EVAL_NUMERIC, EVAL_OPTIONAL)
    if (path / TRAIN_FILE).is_file():  # read again for the learning figure; a damaged one skips the run here, before
        read_run_csv(path / TRAIN_FILE, TRAIN_COLUMNS, TRAIN_COLUMNS)  # any figure is drawn
    steps = evals[EV_ENV_STEPS]
    back = np.flatnonzero(np.diff(steps) < 0)
    if back.size:
        i = int(back[0]) + 1  # the data row whose env steps are below the previous row's
        raise IncompleteRun(f"{EVAL_FILE} line {i + 2}: {EV_ENV_STEPS} {steps[i]:g} is below the one before")
    n = len(episodes[EP_EPISODE])
    if not np.array_equal(episodes[EP_EPISODE], np.arange(1, n + 1)):
        raise IncompleteRun(f"{EPISODES_FILE} column {EP_EPISODE} is not 1..{n}")
    expected = summary.get(SK_EPISODES)
    if isinstance(expected, int) and not isinstance(expected, bool) and expected != n:
        raise IncompleteRun(
            f"{EPISODES_FILE} has {n} episodes but {SUMMARY_FILE} says {SK_EPISODES}={expected} (partial file?)"
        )
    return Run(path=path, summary=summary, episodes=episodes, evals=evals)


def _warn_stderr(message: str) -> None:
    print(message, file=sys.stderr)


def load_runs(roots: Iterable[str | os.PathLike], warn: Callable[[str], None] = _warn_stderr) -> list[Run]:
    """Load every complete run under ``roots``; each skipped run gets one ``warn("warning: skipping DIR: why")``.

    Raises :class:`AnalysisError` when a root is not a directory or no complete run is found.
    """
    roots = list(roots)
    runs = []
    for d in find_run_dirs(roots):
        try:
            runs.append(load_run(d))
        except IncompleteRun as e:
            warn(f"warning: skipping {d}: {e}")
    if not runs:
        raise AnalysisError(f"no complete runs under {', '.join(str(r) for r in roots)}")
    return runs


def _seed_key(seed) -> tuple:
    return (0, seed, "") if isinstance(seed, (int, float)) and not isinstance(seed, bool) else (1, 0, str(seed))


def group_runs(runs: Iterable[Run]) -> dict[tuple[str, str], list[Run]]:
    """Group runs by ``(maze, method)`` (the maze with its slip, :attr:`Run.maze`): keys sorted, runs in each group
    sorted by seed (then path)."""
    groups: dict[tuple[str, str], list[Run]] = {}
    for run in runs:
        groups.setdefault((run.maze, run.method), []).append(run)
    return {k: sorted(groups[k], key=lambda r: (_seed_key(r.seed), str(r.path))) for k in sorted(groups)}


# ----------------------------------------------------------------------------------------------------------------------
# Statistics
# ----------------------------------------------------------------------------------------------------------------------


def bootstrap_ci(
    values: Sequence[float] | np.ndarray,
    n_resamples: int = 1000,
    confidence: float = 0.95,
    rng: np.random.Generator | int | None = None,
) -> tuple[float, float, float]:
    """Percentile-bootstrap confidence interval of the mean: returns ``(mean, low, high)``.

    With ``n = len(values)``, draw ``n_resamples`` resamples of ``n`` values with replacement, in one call
    ``idx = rng.integers(0, n, size=(n_resamples, n))``; take the mean of each resample, and return the
    ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` percentiles of those means (``np.percentile``, linear
    interpolation) as ``low`` and ``high``. ``mean`` is the plain mean of ``values``.

    With a single value (or identical values) every resample mean equals it, so the CI collapses to that value.
    ``rng`` is a ``numpy.random.Generator`` or a seed for ``numpy.random.default_rng``; pass a fixed seed for
    reproducible intervals.
    """
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.size == 0:
        raise ValueError("bootstrap_ci needs at least one value")
    mean, low, high = _bootstrap_columns(v[:, None], n_resamples, confidence, rng)
    return float(mean[0]), float(low[0]), float(high[0])


def _bootstrap_columns(
    samples: np.ndarray, n_resamples: int, confidence: float, rng: np.random.Generator | int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`bootstrap_ci` for each column of ``samples`` (shape ``(n, k)``), all columns sharing one draw of
    resample indices (so each column gets exactly what ``bootstrap_ci`` gives for it with the same ``rng``)."""
    if n_resamples < 1:
        raise ValueError(f"n_resamples must be >= 1, got {n_resamples}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    n, k = samples.shape
    idx = rng.integers(0, n, size=(n_resamples, n))
    q = [100 * (1 - confidence) / 2, 100 * (1 + confidence) / 2]
    low, high = np.empty(k), np.empty(k)
    chunk = max(1, 4_000_000 // (n_resamples * n))  # bound the (n_resamples, n, chunk) temporary
    for s in range(0, k, chunk):
        means = samples[:, s : s + chunk][idx].mean(axis=1)  # (n_resamples, chunk)
        low[s : s + chunk], high[s : s + chunk] = np.percentile(means, q, axis=0)
    return samples.mean(axis=0), low, high


def moving_average(x: Sequence[float] | np.ndarray, k: int) -> np.ndarray:
    """Trailing moving average with window ``k``: ``y[i] = mean(x[max(0, i - k + 1) : i + 1])``.

    The output has the input's length; the first ``k - 1`` entries average the values seen so far. ``k = 1`` returns
    a copy of ``x``.
    """
    if k < 1:
        raise ValueError(f"smoothing window must be >= 1, got {k}")
    x = np.asarray(x, dtype=float)
    c = np.concatenate([[0.0], np.cumsum(x)])
    i = np.arange(1, len(x) + 1)
    lo = np.maximum(i - k, 0)
    return (c[i] - c[lo]) / (i - lo)


@dataclass
class Curve:
    """Per-episode aggregate of one metric over seeds: ``episode`` is ``1..max episodes``; ``n_seeds[i]`` is how many
    seeds have episode ``episode[i]``; ``mean``/``low``/``high`` are the bootstrap mean and CI over those seeds."""

    episode: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n_seeds: np.ndarray


def aggregate_curve(
    series: Sequence[Sequence[float] | np.ndarray],
    smooth: int = 1,
    n_resamples: int = 1000,
    confidence: float = 0.95,
    seed: int = 0,
) -> Curve:
    """Aggregate one per-episode metric over seeds, aligned by episode index.

    Each seed's series is smoothed first (:func:`moving_average` with window ``smooth``). Episode ``i`` is aggregated
    over the seeds that have it (seeds may have different numbers of episodes). The band is :func:`bootstrap_ci`
    over those seeds with ``rng = numpy.random.default_rng(seed)`` -- the same generator state for every episode, so
    the band at episode ``i`` equals ``bootstrap_ci(values_at_i, n_resamples, confidence, default_rng(seed))`` with
    the values in the order of ``series``.
    """
    smoothed = [moving_average(s, smooth) for s in series]
    lengths = np.array([len(s) for s in smoothed], dtype=int)
    n_max = int(lengths.max(initial=0))
    mean, low, high = np.full(n_max, np.nan), np.full(n_max, np.nan), np.full(n_max, np.nan)
    n_seeds = (lengths[:, None] > np.arange(n_max)[None, :]).sum(axis=0)
    # Episodes with the same seed count have the same set of seeds: bootstrap each such block at once.
    for m in sorted(set(n_seeds.tolist()) - {0}):
        cols = np.flatnonzero(n_seeds == m)
        have = [s for s, n in zip(smoothed, lengths) if n > cols[0]]
        block = np.stack([s[cols] for s in have])
        mean[cols], low[cols], high[cols] = _bootstrap_columns(
            block, n_resamples, confidence, np.random.default_rng(seed)
        )
    return Curve(episode=np.arange(1, n_max + 1), mean=mean, low=low, high=high, n_seeds=n_seeds)


# ----------------------------------------------------------------------------------------------------------------------
# The results table
# ----------------------------------------------------------------------------------------------------------------------


def first_goal_env_step(run: Run) -> float | None:
    """Env steps until G was first reached (the summary's ``first_goal_env_step``), or None if never."""
    value = run.summary.get(SK_FIRST_GOAL)
    return float(value) if _is_number(value) else None


def near_optimal_env_step(run: Run, tolerance: float = NEAR_OPTIMAL) -> float | None:
    """Env steps at the first greedy evaluation that succeeds within ``tolerance`` x the shortest path, or None.

    "Within" means ``eval_success == 1`` and ``eval_length <= tolerance * optimal_length``; None also when the
    summary has no ``optimal_length``.
    """
    optimal = run.summary.get(SK_OPTIMAL)
    if not isinstance(optimal, (int, float)) or isinstance(optimal, bool):
        return None
    ok = (run.evals[EV_SUCCESS] == 1) & (run.evals[EV_LENGTH] <= tolerance * optimal)
    hits = np.flatnonzero(ok)
    return float(run.evals[EV_ENV_STEPS][hits[0]]) if hits.size else None


def run_learned(run: Run) -> Learned | None:
    """The learned rule (:func:`ss_drl.training.learned.learned`) on the run's eval.csv rows, with the summary's
    ``optimal_length`` and ``env_steps`` (a completed run's env steps are its budget, ``trainer.total_env_steps``).

    None when the summary lacks either number. ``wall_s`` is None for an eval.csv without the ``wall_s`` column.
    """
    optimal, total = run.summary.get(SK_OPTIMAL), run.summary.get(SK_ENV_STEPS)
    if not (_is_number(optimal) and optimal > 0 and _is_number(total) and total > 0):
        return None
    ev = run.evals
    records = [
        EvalRecord(float(s), float(n), bool(ok), float(w))
        for s, n, ok, w in zip(ev[EV_ENV_STEPS], ev[EV_LENGTH], ev[EV_SUCCESS] == 1, ev[EV_WALL])
    ]
    return learned(records, optimal, total)


def _episode_block_mean(runs: Sequence[Run], column: str, first: int, last: float) -> float | None:
    """Mean over seeds of each seed's mean of ``column`` over episodes ``first..last``; seeds without such episodes
    are left out; None when no seed has any."""
    per_seed = []
    for run in runs:
        ep = run.episodes[EP_EPISODE]
        sel = (ep >= first) & (ep <= last)
        if sel.any():
            per_seed.append(float(run.episodes[column][sel].mean()))
    return float(np.mean(per_seed)) if per_seed else None


@dataclass
class TableRow:
    """One ``(maze, method)`` row of the results table (numbers; :meth:`cells` formats them).

    * ``first_goal_*``: env steps until G was first reached, over the seeds that reached it (``first_goal_reached``
      of ``seeds``): mean with its 95% percentile-bootstrap CI ``[first_goal_low, first_goal_high]``, and median;
      all None when no seed reached G, and the CI None when only one did (one value has no interval).
    * ``return_early`` / ``length_early``: mean over seeds of each seed's mean over episodes ``1..EARLY_EPISODES``;
      ``*_late``: the same over episodes ``EARLY_EPISODES + 1`` onwards (None when no seed has them).
    * ``near_optimal_median``: median over the seeds that got there (``near_optimal_reached`` of ``seeds``) of the env
      steps until the greedy evaluation succeeded within 5% of the shortest path; None ("never") when none did.
    * ``greedy_accuracy``: mean over the seeds whose summary has it of the final greedy accuracy (the fraction of
      states whose greedy action is on a shortest path to G); None when none has it (runs from before it existed).
    * ``optimal_length``: median over seeds of the optimum the rule measures against (the shortest path; under slips
      the optimal policy's expected steps from S). ``eval_success_rate`` / ``eval_length``: mean over the seeds whose
      summary has it of the last evaluation's share of episodes that reached G and its (mean) length; None when none
      has it.
    * ``learned_*``: the learned rule (:func:`run_learned`): ``learned_reached`` of ``learned_known`` seeds learned
      (``learned_known``: the seeds whose summary has ``optimal_length`` and ``env_steps``, normally all);
      ``learned_median`` / ``learned_wall_median``: median over the seeds that learned of the env steps / wall seconds
      at the learned step (the wall median over those whose eval.csv has ``wall_s``); None when there are none.
    * ``last_quarter_mean``: mean over seeds of the fraction of last-quarter evaluations within 1.05x (None when no
      seed has last-quarter evaluations).
    * ``wall_median``: median wall time per run in seconds (None when no summary has it).
    """

    maze: str
    method: str
    seeds: int
    first_goal_mean: float | None
    first_goal_low: float | None
    first_goal_high: float | None
    first_goal_median: float | None
    first_goal_reached: int
    return_early: float | None
    return_late: float | None
    length_early: float | None
    length_late: float | None
    near_optimal_median: float | None
    near_optimal_reached: int
    learned_reached: int
    learned_known: int
    learned_median: float | None
    learned_wall_median: float | None
    last_quarter_mean: float | None
    greedy_accuracy: float | None
    optimal_length: float | None
    eval_success_rate: float | None
    eval_length: float | None
    wall_median: float | None

    def cells(self) -> list[str]:
        """The row's markdown cells, in :data:`TABLE_HEADER` order."""
        if self.first_goal_mean is None:
            first_goal, first_median = "never", "never"
        else:
            first_goal, first_median = f"{self.first_goal_mean:,.1f}", f"{self.first_goal_median:,.1f}"
        if self.first_goal_low is None or self.first_goal_high is None:
            interval = "–"
        else:
            # The percentile interval is asymmetric about the mean: print both ends, not a half width.
            interval = f"[{self.first_goal_low:,.1f}, {self.first_goal_high:,.1f}]"
        return [
            self.maze,
            self.method,
            str(self.seeds),
            first_goal,
            interval,
            first_median,
            f"{self.first_goal_reached}/{self.seeds} seeds",
            _fmt(self.return_early, ".3f"),
            _fmt(self.return_late, ".3f"),
            _fmt(self.length_early, ",.1f"),
            _fmt(self.length_late, ",.1f"),
            "never" if self.near_optimal_median is None else f"{self.near_optimal_median:,.1f}",
            f"{self.near_optimal_reached}/{self.seeds} seeds",
            f"{self.learned_reached}/{self.learned_known} seeds",
            ("never" if self.learned_known else "–") if self.learned_median is None else f"{self.learned_median:,.1f}",
            _fmt(self.learned_wall_median, ",.1f"),
            _fmt(self.last_quarter_mean, ".3f"),
            _fmt(self.greedy_accuracy, ".3f"),
            _fmt(self.optimal_length, ",.1f"),
            _fmt(self.eval_success_rate, ".3f"),
            _fmt(self.eval_length, ",.1f"),
            _fmt(self.wall_median, ",.1f"),
        ]


def _fmt(x: float | None, spec: str) -> str:
    return "–" if x is None else format(x, spec)


TABLE_HEADER = (
    "maze",
    "method",
    "seeds",
    "first goal: env steps (mean)",
    "first goal: 95% CI [low, high]",
    "first goal: median",
    "reached goal",
    f"return (ep 1-{EARLY_EPISODES})",
    f"return (ep {EARLY_EPISODES + 1}+)",
    f"length (ep 1-{EARLY_EPISODES})",
    f"length (ep {EARLY_EPISODES + 1}+)",
    f"env steps to ≤{NEAR_OPTIMAL:g}× optimal (median)",
    f"≤{NEAR_OPTIMAL:g}× optimal",
    f"learned (≥{float(SHARE):.0%} of evals after {float(LAST_QUARTER):.0%} of budget ≤{NEAR_OPTIMAL:g}×)",
    "learned: env steps (median)",
    "learned: wall s (median)",
    f"evals after {float(LAST_QUARTER):.0%} of budget ≤{NEAR_OPTIMAL:g}× (mean fraction)",
    "final greedy accuracy (mean)",
    "optimum: steps (median)",
    "last eval: success rate (mean)",
    "last eval: length (mean)",
    "wall s/run (median)",
)


def table_row(maze: str, method: str, runs: Sequence[Run], n_resamples: int = 1000, seed: int = 0) -> TableRow:
    """Compute one table row from the runs of one ``(maze, method)`` group (see :class:`TableRow`).

    The first-goal CI is ``bootstrap_ci(values, n_resamples, 0.95, numpy.random.default_rng(seed))`` over the seeds
    that reached G, when at least two did.
    """
    first = [s for s in (first_goal_env_step(r) for r in runs) if s is not None]
    fg_mean = fg_low = fg_high = fg_median = None
    if len(first) > 1:
        fg_mean, fg_low, fg_high = bootstrap_ci(first, n_resamples, 0.95, np.random.default_rng(seed))
    elif first:
        fg_mean = first[0]
    if first:
        fg_median = float(np.median(first))
    near = [s for s in (near_optimal_env_step(r) for r in runs) if s is not None]
    walls, accuracy, optimal, rates, lengths = (
        _summary_numbers(runs, key) for key in (SK_WALL, SK_ACCURACY, SK_OPTIMAL, SK_EVAL_RATE, SK_EVAL_LENGTH)
    )
    rules = [rule for rule in (run_learned(r) for r in runs) if rule is not None]
    learned_steps = [rule.env_step for rule in rules if rule.env_step is not None]
    learned_walls = [rule.wall_s for rule in rules if rule.env_step is not None and rule.wall_s is not None]
    quarters = [rule.last_quarter_within for rule in rules if rule.last_quarter_within is not None]
    return TableRow(
        maze=maze,
        method=method,
        seeds=len(runs),
        first_goal_mean=fg_mean,
        first_goal_low=fg_low,
        first_goal_high=fg_high,
        first_goal_median=fg_median,
        first_goal_reached=len(first),
        return_early=_episode_block_mean(runs, EP_RETURN, 1, EARLY_EPISODES),
        return_late=_episode_block_mean(runs, EP_RETURN, EARLY_EPISODES + 1, math.inf),
        length_early=_episode_block_mean(runs, EP_LENGTH, 1, EARLY_EPISODES),
        length_late=_episode_block_mean(runs, EP_LENGTH, EARLY_EPISODES + 1, math.inf),
        near_optimal_median=float(np.median(near)) if near else None,
        near_optimal_reached=len(near),
        learned_reached=len(learned_steps),
        learned_known=len(rules),
        learned_median=float(np.median(learned_steps)) if learned_steps else None,
        learned_wall_median=float(np.median(learned_walls)) if learned_walls else None,
        last_quarter_mean=float(np.mean(quarters)) if quarters else None,
        greedy_accuracy=float(np.mean(accuracy)) if accuracy else None,
        optimal_length=float(np.median(optimal)) if optimal else None,
        eval_success_rate=float(np.mean(rates)) if rates else None,
        eval_length=float(np.mean(lengths)) if lengths else None,
        wall_median=float(np.median(walls)) if walls else None,
    )


def _summary_numbers(runs: Sequence[Run], key: str) -> list[float]:
    """The summary's ``key`` of each run that has it as a finite number (older runs may lack it)."""
    return [float(r.summary[key]) for r in runs if _is_number(r.summary.get(key))]


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def results_table(groups: dict[tuple[str, str], list[Run]], n_resamples: int = 1000, seed: int = 0) -> list[TableRow]:
    """One :class:`TableRow` per ``(maze, method)`` group, in the groups' order."""
    return [table_row(maze, method, runs, n_resamples, seed) for (maze, method), runs in groups.items()]


def markdown_table(rows: Sequence[TableRow]) -> str:
    """The results table in markdown (:data:`TABLE_HEADER`, one line per row; trailing newline)."""
    return format_markdown_table(TABLE_HEADER, [r.cells() for r in rows]) + "\n"


def load_train_log(run: Run) -> dict[str, np.ndarray] | None:
    """The run's train.csv as float arrays (:data:`~ss_drl.training.outputs.TRAIN_COLUMNS`), or None for a run
    written before train.csv existed."""
    path = run.path / TRAIN_FILE
    if not path.is_file():
        return None
    return read_run_csv(path, TRAIN_COLUMNS, TRAIN_COLUMNS)


def mean_over_seeds(logs: Sequence[dict[str, np.ndarray]], column: str, points: int = 200) -> tuple[np.ndarray, ...]:
    """(env steps, mean of ``column``): each seed's log interpolated linearly in env steps onto ``points`` steps
    over the range that every seed covers, then averaged. Empty arrays when the seeds' ranges do not overlap."""
    logs = [log for log in logs if len(log["env_steps"])]
    if not logs:
        return np.empty(0), np.empty(0)
    low = max(float(log["env_steps"].min()) for log in logs)
    high = min(float(log["env_steps"].max()) for log in logs)
    if high < low:
        return np.empty(0), np.empty(0)
    grid = np.linspace(low, high, points)
    return grid, np.mean([np.interp(grid, log["env_steps"], log[column]) for log in logs], axis=0)
