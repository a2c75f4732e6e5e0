"""Tests of ss_drl.analysis and scripts/plot.py on a hand-written synthetic multirun directory with known numbers."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ss_drl.analysis import aggregate as agg
from ss_drl.analysis import (
    aggregate_curve,
    bootstrap_ci,
    group_runs,
    load_run,
    load_runs,
    main,
    make_report,
    markdown_table,
    moving_average,
    results_table,
)
from ss_drl.analysis.aggregate import AnalysisError, IncompleteRun
from ss_drl.analysis.tables import format_markdown_table
from ss_drl.training.learned import Learned
from ss_drl.training.outputs import (
    EPISODE_COLUMNS,
    EPISODES_FILE,
    EVAL_COLUMNS,
    EVAL_FILE,
    SUMMARY_FILE,
    SUMMARY_KEYS,
)

ROOT = Path(__file__).resolve().parents[1]
MAZE, OTHER_MAZE = "tiny", "other/maze file.txt"
OPTIMAL = 20  # within 5%: eval_length <= 21


def _episodes(lengths, returns):
    rows, env_steps = [], 0
    for i, (length, ret) in enumerate(zip(lengths, returns), start=1):
        env_steps += length
        row = dict.fromkeys(EPISODE_COLUMNS, 0)
        row.update({agg.EP_EPISODE: i, agg.EP_ENV_STEPS: env_steps, agg.EP_LENGTH: length, agg.EP_RETURN: ret})
        row[agg.EP_SUCCESS] = int(ret > 0)
        rows.append(row)
    return rows


def _evals(triples):
    """eval.csv rows from (env_steps, eval_length, eval_success); wall seconds = env steps / 100."""
    rows = []
    for k, (env_steps, length, success) in enumerate(triples, start=1):
        row = dict.fromkeys(EVAL_COLUMNS, 0)
        row.update({agg.EV_ENV_STEPS: env_steps, agg.EV_EPISODE: k, agg.EV_LENGTH: length, agg.EV_SUCCESS: success})
        row[agg.EV_WALL] = env_steps / 100
        rows.append(row)
    return rows


#: eval.csv's columns before it had wall_s (runs written then must still load).
OLD_EVAL_COLUMNS = tuple(c for c in EVAL_COLUMNS if c != agg.EV_WALL)


def _write_run(
    d: Path, maze, method, seed, first_goal, wall, episodes, evals, completed=True, n_episodes=None, accuracy=None,
    eval_columns=EVAL_COLUMNS, config=None, episode_columns=EPISODE_COLUMNS, last_eval=None, slip=None,
):  # fmt: skip
    """A run directory; the summary's env steps (the budget) are those of the last evaluation (0 without any).
    ``config``: the summary's resolved config (None: none, the stored ``method`` labels the run). ``last_eval``:
    the last evaluation's (success rate, length) in the summary (None: none, as in runs from before them)."""
    d.mkdir(parents=True)
    summary = dict.fromkeys(SUMMARY_KEYS)
    summary.update(
        {
            agg.SK_MAZE: maze,
            agg.SK_METHOD: method,
            agg.SK_SEED: seed,
            agg.SK_COMPLETED: completed,
            agg.SK_FIRST_GOAL: first_goal,
            agg.SK_EPISODES: len(episodes) if n_episodes is None else n_episodes,
            agg.SK_OPTIMAL: OPTIMAL,
            agg.SK_WALL: wall,
            agg.SK_ACCURACY: accuracy,
            agg.SK_ENV_STEPS: evals[-1][agg.EV_ENV_STEPS] if evals else 0,
            agg.SK_EVAL_RATE: None if last_eval is None else last_eval[0],
            agg.SK_EVAL_LENGTH: None if last_eval is None else last_eval[1],
            agg.SK_SLIP: slip,
            "config": config,
        }
    )
    (d / SUMMARY_FILE).write_text(json.dumps(summary))
    for name, columns, rows in ((EPISODES_FILE, episode_columns, episodes), (EVAL_FILE, eval_columns, evals)):
        with (d / name).open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)


def _build(root: Path) -> dict[str, Path]:
    """2 methods x 3 seeds on MAZE, 1 run on OTHER_MAZE, and 5 incomplete runs; returns the incomplete dirs.

    Learned (>= 90% of the evaluations after 3/4 of the budget, the last evaluation's env steps, within 21 steps):
    ss_her seeds 0 (at 2000, 20.0 s) and 1 (at 1000; its eval.csv is from before wall_s); not seed 2 (1 of 2).
    """
    a = root / "multirun" / "2026-11-22" / "10-00-00"
    b = root / "multirun" / "2026-11-22" / "11-30-00"
    ep = np.arange(1, 151)
    # ss_her: returns 0 until episode 50 / 75 / never, then 1; lengths 20/30/40 for episodes 1-100, 10/12/14 after.
    _write_run(a / "0", MAZE, "ss_her", 0, 1000, 10.0,
               _episodes(np.where(ep <= 100, 20, 10), (ep > 50).astype(int)),
               _evals([(500, 50, 0), (1000, 20, 0), (1500, 22, 1), (2000, 21, 1), (2500, 20, 1)]),
               accuracy=0.5, last_eval=(1.0, 20.0))  # fmt: skip
    _write_run(a / "1", MAZE, "ss_her", 1, 2000, 20.0,
               _episodes(np.where(ep <= 100, 30, 12), (ep > 75).astype(int)),
               _evals([(500, 100, 0), (1000, 20, 1)]), accuracy=1.0, eval_columns=OLD_EVAL_COLUMNS,
               last_eval=(0.5, 25.0))  # fmt: skip
    _write_run(a / "2", MAZE, "ss_her", 2, 6000, 60.0,
               _episodes(np.where(ep[:120] <= 100, 40, 14), np.ones(120, int)),
               _evals([(1000, 22, 1), (3000, 20, 1), (3500, 100, 0)]))  # fmt: skip
    # dqn: 100 episodes of length 100; only seed 0 reaches G (in episode 100); no greedy eval within 5%.
    _write_run(b / "0", MAZE, "dqn", 0, 9000, 5.0, _episodes([100] * 100, [0] * 99 + [1]),
               _evals([(5000, 100, 0), (10000, 30, 1)]))  # fmt: skip
    for s in (1, 2):
        _write_run(b / str(s), MAZE, "dqn", s, None, 5.0 + s, _episodes([100] * 100, [0] * 100),
                   _evals([(10000, 100, 0)]))  # fmt: skip
    _write_run(b / "3", OTHER_MAZE, "dqn", 0, None, 1.0, _episodes([5] * 10, [0] * 10), _evals([(50, 5, 0)]))
    bad = {
        "not_completed": a / "3",
        "missing_episodes": b / "4",
        "truncated_line": b / "5",
        "fewer_rows": b / "nested" / "deeper" / "6",
        "eval_goes_back": b / "7",
    }
    _write_run(bad["not_completed"], MAZE, "ss_her", 3, 1, 1.0, _episodes([1], [1]), _evals([]), completed=False)
    _write_run(bad["missing_episodes"], MAZE, "dqn", 4, None, 1.0, _episodes([1], [0]), _evals([]))
    (bad["missing_episodes"] / EPISODES_FILE).unlink()
    _write_run(bad["truncated_line"], MAZE, "dqn", 5, None, 1.0, _episodes([1, 2], [0, 0]), _evals([]))
    with (bad["truncated_line"] / EPISODES_FILE).open("a") as f:
        f.write("3,0,")  # a row cut short by a killed writer
    _write_run(bad["fewer_rows"], MAZE, "dqn", 6, None, 1.0, _episodes([1, 2], [0, 0]), _evals([]), n_episodes=5)
    _write_run(bad["eval_goes_back"], MAZE, "dqn", 7, None, 1.0, _episodes([1], [0]),
               _evals([(100, 5, 0), (300, 5, 0), (200, 5, 0)]))  # fmt: skip
    return bad


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    bad = _build(root)
    return root / "multirun", bad


@pytest.fixture(scope="module")
def loaded(synth):
    root, _ = synth
    warnings = []
    runs = load_runs([root], warn=warnings.append)
    return runs, warnings


# ---------------------------------------------------------------------------------------------------------------------
# bootstrap_ci and curves
# ---------------------------------------------------------------------------------------------------------------------


def test_bootstrap_identical_and_single_values_collapse():
    assert bootstrap_ci([5.0, 5.0, 5.0, 5.0], 200, rng=0) == (5.0, 5.0, 5.0)
    assert bootstrap_ci([7.0], 200, rng=np.random.default_rng(1)) == (7.0, 7.0, 7.0)


# Resample means of [0, 3, 6] (n = 3): each of the 27 equally likely index triples gives mean k1 + 2 * k2, where k1 and
# k2 count the draws of 3 and of 6, i.e. the sum of three uniform draws from {0, 1, 2}. So the mean takes the values
# 0..6 with counts 1, 3, 6, 7, 6, 3, 1 out of 27: cumulative 1/27 = .037, 4/27 = .148, 10/27 = .370, 17/27 = .630,
# 23/27 = .852, 26/27 = .963, 1. A percentile that falls strictly inside a step of this CDF is that step's value, and
# with 20,000 resamples every such percentile below sits at least 9 standard errors from a step's edge.
THREE_VALUES = [0.0, 3.0, 6.0]
THREE_VALUES_CI = {
    0.95: (0.0, 6.0),  # 2.5%: .025 < .037 -> 0;  97.5%: .963 < .975 -> 6
    0.90: (1.0, 5.0),  # 5%: .037 < .05 < .148 -> 1;  95%: .852 < .95 < .963 -> 5
    0.50: (2.0, 4.0),  # 25%: .148 < .25 < .370 -> 2;  75%: .630 < .75 < .852 -> 4
}


@pytest.mark.parametrize("confidence", sorted(THREE_VALUES_CI))
def test_bootstrap_three_values_known_quantiles(confidence):
    mean, low, high = bootstrap_ci(THREE_VALUES, 20_000, confidence, rng=5)
    assert (mean, low, high) == (3.0, *THREE_VALUES_CI[confidence])
    # The order of the values does not matter.
    assert bootstrap_ci(THREE_VALUES[::-1], 20_000, confidence, rng=6) == (3.0, *THREE_VALUES_CI[confidence])


def test_bootstrap_seed_is_reproducible():
    values = np.array([1.0, 4.0, 2.0, 8.0, 5.0])
    ci = bootstrap_ci(values, 500, 0.9, np.random.default_rng(123))
    assert bootstrap_ci(values, 500, 0.9, 123) == ci  # an int seed is default_rng(seed)
    assert bootstrap_ci(values, 500, 0.9, 123) == ci  # and the same seed gives the same interval
    assert ci[0] == 4.0 and 1.0 <= ci[1] < 4.0 < ci[2] <= 8.0
    _, low50, high50 = bootstrap_ci(values, 500, 0.5, 123)
    assert ci[1] <= low50 < high50 <= ci[2]


def test_bootstrap_ci_of_normal_samples_covers_and_narrows_like_one_over_sqrt_n():
    # The 95% percentile-bootstrap interval of the mean of N draws from N(0, 1) is about mean +- 1.96 * sd / sqrt(N),
    # where sd is the sample's plug-in spread, sqrt((N - 1) / N) on average, and it holds the true mean 0 in ~95% of
    # repetitions (~93% at N = 20, for that plug-in spread). 400 repetitions: the coverage's standard error is ~0.012.
    rng = np.random.default_rng(2024)
    reps = 400
    widths, covered = {}, {}
    for n in (20, 80):
        cis = [bootstrap_ci(rng.normal(0.0, 1.0, n), 1000, 0.95, rng) for _ in range(reps)]
        low, high = np.array([c[1] for c in cis]), np.array([c[2] for c in cis])
        widths[n] = float(np.mean(high - low))
        covered[n] = float(np.mean((low <= 0.0) & (0.0 <= high)))
    for n in (20, 80):
        assert 0.89 <= covered[n] <= 0.98, (n, covered[n])
        assert widths[n] == pytest.approx(2 * 1.96 * np.sqrt((n - 1) / n) / np.sqrt(n), rel=0.05)
    assert widths[20] / widths[80] == pytest.approx(2.0, rel=0.1)  # 4x the samples, half the width


def test_moving_average_trailing_window():
    np.testing.assert_array_equal(moving_average([1, 2, 3, 4], 2), [1.0, 1.5, 2.5, 3.5])
    np.testing.assert_array_equal(moving_average([3, 0, 6, 3], 3), [3.0, 1.5, 3.0, 3.0])
    np.testing.assert_array_equal(moving_average([1, 5], 1), [1.0, 5.0])


def test_aggregate_curve_aligns_by_episode_over_seeds_that_have_it():
    c = aggregate_curve([[1, 2, 3], [3, 4], [5]], n_resamples=300, seed=4)
    np.testing.assert_array_equal(c.episode, [1, 2, 3])
    np.testing.assert_array_equal(c.n_seeds, [3, 2, 1])
    np.testing.assert_array_equal(c.mean, [3.0, 3.0, 3.0])
    for i, values in enumerate([[1, 3, 5], [2, 4], [3]]):
        _, low, high = bootstrap_ci(values, 300, 0.95, np.random.default_rng(4))
        assert (c.low[i], c.high[i]) == pytest.approx((low, high), rel=1e-12)
    assert (c.low[2], c.high[2]) == (3.0, 3.0)
    # Independently of bootstrap_ci: seeds at 0, 3, 6 in every episode have the 90% band [1, 5] (see THREE_VALUES_CI).
    band = aggregate_curve([[0, 0], [3, 3], [6, 6]], n_resamples=20_000, confidence=0.9, seed=1)
    np.testing.assert_array_equal(band.mean, [3.0, 3.0])
    np.testing.assert_array_equal(np.stack([band.low, band.high]), [[1.0, 1.0], [5.0, 5.0]])
    # Smoothing per seed before aggregating: [0, 2, 4] -> [0, 1, 3] and [2, 2] -> [2, 2].
    s = aggregate_curve([[0, 2, 4], [2, 2]], smooth=2, n_resamples=50)
    np.testing.assert_array_equal(s.mean, [1.0, 1.5, 3.0])


# ---------------------------------------------------------------------------------------------------------------------
# Loading and the table
# ---------------------------------------------------------------------------------------------------------------------


def test_incomplete_runs_are_skipped_with_one_warning_each(synth, loaded):
    _, bad = synth
    runs, warnings = loaded
    assert len(runs) == 7
    assert len(warnings) == len(bad)
    reasons = {
        "not_completed": "completed=false",
        "missing_episodes": f"missing {EPISODES_FILE}",
        "truncated_line": "line 4 has 3 fields",
        "fewer_rows": "has 2 episodes but summary.json says episodes=5",
        "eval_goes_back": f"{EVAL_FILE} line 4: env_steps 200 is below the one before",
    }
    for key, d in bad.items():
        (line,) = [w for w in warnings if str(d.resolve()) + ":" in w]
        assert line.startswith("warning: skipping ") and reasons[key] in line and "\n" not in line
        with pytest.raises(IncompleteRun):
            load_run(d)


def test_a_run_with_a_damaged_train_csv_is_skipped_before_any_figure(tmp_path):
    """train.csv is read for the learning figure only, which came after the table and the other figures: a bad cell
    there was a traceback (IncompleteRun) with figures half written. It is checked with the run's other files."""
    from ss_drl.training.outputs import TRAIN_COLUMNS, TRAIN_FILE

    d = tmp_path / "run"
    _write_run(d, MAZE, "ss_her", 0, 100, 1.0, _episodes([1], [1]), _evals([(100, 20, 1)]))
    row = dict.fromkeys(TRAIN_COLUMNS, "1")
    with (d / TRAIN_FILE).open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=TRAIN_COLUMNS)
        w.writeheader()
        w.writerow({**row, "loss": "zz4353"})
    _write_run(tmp_path / "good", MAZE, "ss_her", 1, 100, 1.0, _episodes([1], [1]), _evals([(100, 20, 1)]))
    warnings: list[str] = []
    assert [run.seed for run in load_runs([tmp_path], warn=warnings.append)] == [1]
    (line,) = warnings
    assert f"{TRAIN_FILE} line 2: bad loss value 'zz4353'" in line and "\n" not in line
    with pytest.raises(IncompleteRun, match=f"{TRAIN_FILE} line 2: bad loss value"):
        load_run(d)


def test_a_summary_whose_names_are_not_names_is_skipped(tmp_path):
    """summary.json's maze, method and seed label the run's row: a maze that is an object (it became the row
    label {'a': 1}), or a seed that is text, skips the run with one warning naming the key."""
    for name, key, value in (("maze", "maze", {"a": 1}), ("method", "method", 3), ("seed", "seed", "0")):
        d = tmp_path / name
        _write_run(d, MAZE, "ss_her", 0, 100, 1.0, _episodes([1], [1]), _evals([(100, 20, 1)]))
        summary = json.loads((d / "summary.json").read_text())
        (d / "summary.json").write_text(json.dumps({**summary, key: value}))
        with pytest.raises(IncompleteRun) as info:
            load_run(d)
        kind = "int" if key == "seed" else "str"
        assert str(info.value) == f"summary.json: {key} is {json.dumps(value)}, not a {kind}"


def test_groups_by_maze_and_method(loaded):
    groups = group_runs(loaded[0])
    assert list(groups) == [(OTHER_MAZE, "dqn"), (MAZE, "dqn"), (MAZE, "ss_her")]
    assert [r.seed for r in groups[(MAZE, "ss_her")]] == [0, 1, 2]
    assert [r.n_episodes for r in groups[(MAZE, "ss_her")]] == [150, 150, 120]


def test_runs_of_a_maze_with_slips_are_grouped_apart_from_the_deterministic_maze(tmp_path):
    """A maze whose moves slip is another environment: its runs get their own rows, named with the slip."""
    for d, slip in (("a", None), ("b", 0.0), ("c", 0.1), ("d", 0.25)):
        _write_run(tmp_path / d, MAZE, "ss_her", 0, 100, 1.0, _episodes([1], [1]), _evals([(100, 20, 1)]), slip=slip)
    runs = load_runs([tmp_path], warn=lambda _: None)
    assert sorted(run.maze for run in runs) == [MAZE, MAZE, f"{MAZE} (slip 0.1)", f"{MAZE} (slip 0.25)"]
    groups = group_runs(runs)
    assert list(groups) == [(MAZE, "ss_her"), (f"{MAZE} (slip 0.1)", "ss_her"), (f"{MAZE} (slip 0.25)", "ss_her")]
    assert [len(group) for group in groups.values()] == [2, 1, 1]


def test_results_table_values(loaded):
    rows = {(r.maze, r.method): r for r in results_table(group_runs(loaded[0]), n_resamples=20_000, seed=9)}
    ss = rows[(MAZE, "ss_her")]
    assert (ss.seeds, ss.first_goal_reached, ss.first_goal_mean, ss.first_goal_median) == (3, 3, 3000.0, 2000.0)
    # Over 3 seeds (1000, 2000, 6000), a resample of the smallest alone (or the largest alone) has probability
    # 1/27 = 3.7% > 2.5%, so the 95% percentile interval runs from the smallest to the largest value: asymmetric
    # about the mean 3000 (at 20,000 resamples the 3.7% is 9 standard errors above 2.5%).
    assert (ss.first_goal_low, ss.first_goal_high) == (1000.0, 6000.0)
    assert ss.return_early == 1.75 / 3 and ss.return_late == 1.0
    assert ss.length_early == 30.0 and ss.length_late == 12.0
    assert (ss.near_optimal_median, ss.near_optimal_reached) == (2000.0, 3)  # first hits: 2000, 1000, 3000
    assert ss.wall_median == 20.0
    assert ss.greedy_accuracy == 0.75  # seeds 0 and 1 (0.5, 1.0); seed 2's summary has none
    # Learned: seeds 0 (at 2000) and 1 (at 1000, no wall seconds in its old eval.csv); seed 2 has 1 of 2 within bound.
    assert (ss.learned_reached, ss.learned_known, ss.learned_median) == (2, 3, 1500.0)
    assert ss.learned_wall_median == 20.0
    assert ss.last_quarter_mean == pytest.approx(2.5 / 3)
    assert ss.cells() == [
        MAZE, "ss_her", "3", "3,000.0", "[1,000.0, 6,000.0]", "2,000.0", "3/3 seeds",
        "0.583", "1.000", "30.0", "12.0", "2,000.0", "3/3 seeds",
        "2/3 seeds", "1,500.0", "20.0", "0.833", "0.750", "20.0", "0.750", "22.5", "20.0",
    ]  # fmt: skip
    # The last evaluation: seeds 0 (1.0, 20 steps) and 1 (0.5, 25); seed 2's summary has neither.
    assert (ss.optimal_length, ss.eval_success_rate, ss.eval_length) == (20.0, 0.75, 22.5)

    dqn = rows[(MAZE, "dqn")]
    # One seed reached G: a mean, and no interval.
    assert (dqn.first_goal_mean, dqn.first_goal_low, dqn.first_goal_high) == (9000.0, None, None)
    assert dqn.return_early == 0.01 / 3 and dqn.return_late is None and dqn.length_late is None
    assert (dqn.near_optimal_median, dqn.near_optimal_reached) == (None, 0)
    assert dqn.cells() == [
        MAZE, "dqn", "3", "9,000.0", "–", "9,000.0", "1/3 seeds",
        "0.003", "–", "100.0", "–", "never", "0/3 seeds",
        "0/3 seeds", "never", "–", "0.000", "–", "20.0", "–", "–", "6.0",
    ]  # fmt: skip

    other = rows[(OTHER_MAZE, "dqn")]
    assert other.cells()[3:7] == ["never", "–", "never", "0/1 seeds"]
    assert other.cells()[11:17] == ["never", "0/1 seeds", "0/1 seeds", "never", "–", "0.000"]
    assert (other.first_goal_mean, other.first_goal_low, other.first_goal_high) == (None, None, None)


def test_learned_rule_on_loaded_runs(loaded, tmp_path):
    runs = {(r.method, r.seed): r for r in loaded[0] if r.maze == MAZE}
    assert agg.run_learned(runs[("ss_her", 0)]) == Learned(2000.0, 20.0, 1.0)
    # An eval.csv from before the wall_s column loads, with no wall seconds.
    old = runs[("ss_her", 1)]
    assert np.isnan(old.evals[agg.EV_WALL]).all() and len(old.evals[agg.EV_WALL]) == 2
    assert agg.run_learned(old) == Learned(1000.0, None, 1.0)
    assert agg.run_learned(runs[("ss_her", 2)]) == Learned(None, None, 0.5)
    # Without the budget (summary env_steps) the rule cannot be applied, and the table counts the seed as unknown.
    _write_run(tmp_path / "r", MAZE, "ss_her", 0, 1000, 1.0, _episodes([1], [1]), _evals([(100, 20, 1)]))
    summary = json.loads((tmp_path / "r" / SUMMARY_FILE).read_text())
    summary[agg.SK_ENV_STEPS] = None
    (tmp_path / "r" / SUMMARY_FILE).write_text(json.dumps(summary))
    unknown = load_run(tmp_path / "r")
    assert agg.run_learned(unknown) is None
    row = agg.table_row(MAZE, "ss_her", [unknown, runs[("ss_her", 0)]], n_resamples=10)
    assert row.cells()[13:17] == ["1/1 seeds", "2,000.0", "20.0", "1.000"]
    assert agg.table_row(MAZE, "ss_her", [unknown], n_resamples=10).cells()[13:17] == ["0/0 seeds", "–", "–", "–"]


def test_markdown_table_shape(loaded):
    rows = results_table(group_runs(loaded[0]), n_resamples=50)
    lines = markdown_table(rows).splitlines()
    assert len(lines) == 2 + 3
    assert lines[0] == "| " + " | ".join(agg.TABLE_HEADER) + " |"
    assert all(line.count(" | ") == len(agg.TABLE_HEADER) - 1 for line in lines[2:])
    assert lines[-1].startswith(f"| {MAZE} | ss_her | 3 | 3,000.0 | [")
    assert lines[3].startswith(f"| {MAZE} | dqn | 3 | 9,000.0 | – | 9,000.0 | 1/3 seeds |")


def test_format_markdown_table_escapes_and_checks_row_length():
    text = format_markdown_table(["a", "b|c"], [[1, "x|y"], ["two\nlines", 2.5]])
    assert text.splitlines() == [
        "| a | b\\|c |",
        "|---|---|",
        "| 1 | x\\|y |",
        "| two lines | 2.5 |",
    ]
    assert not text.endswith("\n")
    with pytest.raises(ValueError, match="table row 1 has 1 cells, expected 2"):
        format_markdown_table(["a", "b"], [[1, 2], [3]])
    with pytest.raises(ValueError, match="at least one header"):
        format_markdown_table([], [])


# ---------------------------------------------------------------------------------------------------------------------
# Report and command line
# ---------------------------------------------------------------------------------------------------------------------

PNGS = [
    f"{stem}_{kind}.png"
    for stem in ("tiny", "other_maze_file.txt")
    for kind in ("fig5_return", "fig6_length", "first_goal")
]


def test_make_report_writes_pngs_and_results_md_to_default_dir(synth):
    root, bad = synth
    warnings = []
    table, written = make_report([root], smooth=5, n_resamples=100, seed=2, warn=warnings.append)
    out = root / "plots"
    assert sorted(p.name for p in written) == sorted([*PNGS, "results.md"])
    for name in PNGS:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert table in (out / "results.md").read_text()
    assert table == markdown_table(results_table(group_runs(load_runs([root], warn=lambda _: None)), 100, 2))
    assert len(warnings) == len(bad)


def test_cli_subprocess(synth, tmp_path):
    root, bad = synth
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "plot.py"), str(root), "--out", str(out), "--bootstrap", "200",
         "--seed", "3", "--smooth", "3"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    expected = markdown_table(results_table(group_runs(load_runs([root], warn=lambda _: None)), 200, 3))
    assert proc.stdout == expected
    assert sum(line.startswith("warning: skipping ") for line in proc.stderr.splitlines()) == len(bad)
    assert sorted(p.name for p in out.iterdir()) == sorted([*PNGS, "results.md"])
    assert "Traceback" not in proc.stderr


def test_cli_nonexistent_dir_subprocess(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "plot.py"), str(tmp_path / "nope")],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode != 0
    assert proc.stderr.splitlines() == [f"plot.py: error: not a directory: {tmp_path / 'nope'}"]
    assert proc.stdout == ""


def test_cli_no_complete_runs(synth, tmp_path, capsys):
    _, bad = synth
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([str(empty)]) == 1
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"plot.py: error: no complete runs under {empty}"]
    assert captured.out == ""
    assert not (empty / "plots").exists()

    assert main([str(bad["not_completed"])]) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and err[0].startswith("warning: skipping ")
    assert err[1].startswith("plot.py: error: no complete runs")
    with pytest.raises(AnalysisError):
        load_runs([bad["missing_episodes"]], warn=lambda _: None)


# ---------------------------------------------------------------------------------------------------------------------
# Run directories written before the learners were renamed: labelled by their resolved config
# ---------------------------------------------------------------------------------------------------------------------


def _old_config(method="ss_her", her_k=4, eta=1.0, **bounds) -> dict:
    """A resolved config as summary.json held it at 7ac5009: a declared ``method`` label, the count model's switches
    (all off unless given) and options deleted since (advantage_learning, eval_tau, lr_end)."""
    switches = ("distance_floor", "distance_ceiling", "bound_all_actions", "model_targets", "optimistic_floor")
    agent = {"name": "dqn", "gamma": 1.0, "n_step": 5, "hindsight_bound": True, "n_step_max": False}
    agent |= {"advantage_learning": False, "eval_network": "target", "eval_tau": 0.01, "lr_end": None}
    agent |= {key: bool(bounds.get(key, False)) for key in switches}
    return {
        "experiment": f"easy_{method}",
        "method": method,
        "seed": 0,
        "agent": agent,
        "her": {"strategy": "future", "k": her_k},
        "smart_start": {"eta": eta, "c_ss": 0.1},
    }


def _write_old_run(d: Path, method: str, seed: int, config: dict) -> None:
    _write_run(d, MAZE, method, seed, 1000, 10.0, _episodes([20] * 10, [1] * 10), _evals([(200, 20, 1)]),
               config=config)  # fmt: skip


@pytest.mark.parametrize(
    ("bounds", "label"),
    [
        ({}, "ss_her"),
        ({"distance_floor": True}, "ss_her_bounded"),
        ({"distance_ceiling": True}, "ss_her_bounded"),
        ({"model_targets": True}, "ss_her_bounded"),
        ({"distance_floor": True, "distance_ceiling": True, "bound_all_actions": True}, "ss_her_bounded"),
    ],
)
def test_an_old_run_is_labelled_by_its_resolved_config(tmp_path, bounds, label):
    """summary.json says ``"method": "ss_her"`` (the label at 7ac5009, when every deep method used the count model's
    bounds); the run is grouped and tabulated as what its config ran: ``ss_her_bounded`` with any of the distance
    floor, the distance ceiling or the model targets on, ``ss_her`` with all of them off."""
    _write_old_run(tmp_path / "run", "ss_her", 0, _old_config(**bounds))
    (run,) = load_runs([tmp_path], warn=pytest.fail)
    assert run.summary[agg.SK_METHOD] == "ss_her"
    assert run.method == label
    assert list(group_runs([run])) == [(MAZE, label)]
    (row,) = results_table(group_runs([run]), n_resamples=10)
    assert row.method == label


def test_plot_py_groups_old_runs_by_learner(tmp_path, capsys):
    """Old runs stored under one label, ``ss_her``, two of them with the count model's bounds on and one without,
    and one stored as ``dqn_her`` whose config ran Smart Start: scripts/plot.py's table and results.md have one row
    per learner and method, never the stored labels."""
    root = tmp_path / "old"
    _write_old_run(root / "a", "ss_her", 0, _old_config(distance_floor=True, distance_ceiling=True))
    _write_old_run(root / "b", "ss_her", 1, _old_config(model_targets=True))
    _write_old_run(root / "c", "ss_her", 0, _old_config())
    _write_old_run(root / "d", "dqn_her", 1, _old_config("dqn_her"))  # a stored label that its config contradicts
    # A hand-written summary whose config names no learner: its stored label.
    _write_run(root / "e", MAZE, "dqn", 0, None, 1.0, _episodes([5] * 3, [0] * 3), _evals([(15, 5, 0)]),
               config={"seed": 0})  # fmt: skip
    assert main([str(root), "--bootstrap", "10"]) == 0
    out = capsys.readouterr().out
    methods = [line.split("|")[2].strip() for line in out.splitlines()[2:] if line.startswith("|")]
    assert methods == ["dqn", "ss_her", "ss_her_bounded"], out
    groups = group_runs(load_runs([root]))
    assert {r.method: r.seeds for r in results_table(groups, n_resamples=10)} == {
        "dqn": 1,
        "ss_her": 2,
        "ss_her_bounded": 2,
    }
    assert [r.path.name for r in groups[(MAZE, "ss_her_bounded")]] == ["a", "b"]
    assert sorted(r.path.name for r in groups[(MAZE, "ss_her")]) == ["c", "d"]
    assert out in (root / "plots" / "results.md").read_text()


def test_learning_figure_draws_td_loss_and_mean_q_averaged_over_seeds(tmp_path):
    from ss_drl.analysis.plots import learning_figure, write_plots
    from ss_drl.training.outputs import TRAIN_COLUMNS, TRAIN_FILE

    # Seed 0 logs loss 1 and Q 0.2 at env steps 100..1000; seed 1 loss 3 and Q 0.6 from 300 on. Over the steps both
    # cover (300..1000) the mean is loss 2 and Q 0.4.
    runs = []
    for seed, (first, loss, q) in enumerate([(100, 1.0, 0.2), (300, 3.0, 0.6)]):
        d = tmp_path / f"seed{seed}"
        _write_run(d, "tiny", "ss_her", seed, 100, 1.0, _episodes([10], [1]), _evals([(0, 10, 1)]))
        with (d / TRAIN_FILE).open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=TRAIN_COLUMNS)
            w.writeheader()
            for i, steps in enumerate(range(first, 1001, 100), start=1):
                row = dict.fromkeys(TRAIN_COLUMNS, 0)
                row.update(env_steps=steps, updates=100 * i, loss=loss, q_mean=q)
                w.writerow(row)
        runs.append(agg.load_run(d))
    logs = [agg.load_train_log(r) for r in runs]
    assert logs[1]["env_steps"].tolist() == list(range(300, 1001, 100))
    steps, mean_loss = agg.mean_over_seeds(logs, "loss", points=8)
    assert steps.tolist() == list(range(300, 1001, 100))
    np.testing.assert_allclose(mean_loss, 2.0)
    fig = learning_figure("tiny", {"ss_her": runs}, {"ss_her": (0.0, 0.0, 1.0, 1.0)})
    (loss_mean,) = [line for line in fig.axes[0].lines if line.get_label() == "ss_her (n=2)"]
    (q_mean,) = [line for line in fig.axes[1].lines if line.get_label() == "ss_her (n=2)"]
    np.testing.assert_allclose(loss_mean.get_ydata(), 2.0)
    np.testing.assert_allclose(q_mean.get_ydata(), 0.4)
    assert (loss_mean.get_xdata().min(), loss_mean.get_xdata().max()) == (300, 1000)
    written = write_plots({("tiny", "ss_her"): runs}, tmp_path / "plots", n_resamples=10)
    assert (tmp_path / "plots" / "tiny_learning.png") in written
    # A run without train.csv (written before it existed) draws no learning figure.
    (runs[0].path / TRAIN_FILE).unlink()
    (runs[1].path / TRAIN_FILE).unlink()
    assert learning_figure("tiny", {"ss_her": runs}, {"ss_her": (0.0, 0.0, 1.0, 1.0)}) is None


#: episodes.csv's columns as 7ac5009 wrote them, before the exploration measures (session 37) and MiniGrid's return.
OLD_EPISODE_COLUMNS = tuple(
    c for c in EPISODE_COLUMNS
    if c not in ("new_moves", "new_moves_after_ss", "explore_steps", "ss_frontier_steps", "minigrid_return")
)  # fmt: skip


def test_runs_written_before_the_newer_episode_columns_still_load(tmp_path):
    """A run directory whose episodes.csv lacks the columns added since (an issue 48 replay-only run at 7ac5009)
    loads, with the same figures as one that has them: only the columns read are required."""
    evals = _evals([(500, 1000, 0), (1000, 31, 1)])
    episodes = _episodes([400, 600], [0.0, 1.0])
    _write_run(tmp_path / "old", "easy", "ss_her", 0, 1000, 10.0, episodes, evals, episode_columns=OLD_EPISODE_COLUMNS)
    _write_run(tmp_path / "new", "easy", "ss_her", 0, 1000, 10.0, episodes, evals)
    header = (tmp_path / "old" / EPISODES_FILE).read_text().splitlines()[0].split(",")
    assert "new_moves" not in header and "minigrid_return" not in header
    old, new = agg.load_run(tmp_path / "old"), agg.load_run(tmp_path / "new")
    for key in agg.EPISODE_NUMERIC:
        assert np.array_equal(old.episodes[key], new.episodes[key])
