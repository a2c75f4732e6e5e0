"""The "learned" rule (ss_drl.training.learned) on hand-built evaluations, and in the trainer's summary."""

from __future__ import annotations

import csv
import json
import random

import pytest
import torch
from helpers import compose_cfg

from ss_drl.training.learned import EvalRecord, Learned, learned, within_bound
from ss_drl.training.outputs import (
    CHECKPOINT_FILE,
    EPISODE_COLUMNS,
    EPISODES_FILE,
    EVAL_COLUMNS,
    EVAL_FILE,
    SUMMARY_FILE,
    SUMMARY_KEYS,
    TRAIN_COLUMNS,
    TRAIN_FILE,
    RunLogger,
)
from ss_drl.training.trainer import Trainer

OPTIMAL = 20  # within bound: success with length <= 21
EVERY = 25  # env steps between evaluations


def evals(pattern: str) -> list[EvalRecord]:
    """One evaluation per character at env steps 25, 50, ...: "x" within bound (length 21), "." a failure (length
    100), "s" a success just outside the bound (length 22); wall seconds = env steps / 10."""
    kinds = {"x": (21, True), ".": (100, False), "s": (22, True)}
    return [EvalRecord(EVERY * k, *kinds[c], EVERY * k / 10) for k, c in enumerate(pattern, start=1)]


def rule(pattern: str) -> Learned:
    return learned(evals(pattern), OPTIMAL, EVERY * len(pattern))


def test_within_bound_is_success_within_five_percent_exactly():
    assert within_bound(21, True, 20) and within_bound(20, 1, 20) and within_bound(105, True, 100)
    assert not within_bound(22, True, 20)
    assert not within_bound(21, False, 20) and not within_bound(19, 0, 20)
    assert within_bound(63, True, 60) and not within_bound(63.0001, True, 60)


# 40 evaluations at 25..1000 env steps, budget 1000: the last quarter is the 10 evaluations at 775..1000.
def test_never_within_bound():
    assert rule("." * 40) == Learned(None, None, 0.0)
    assert rule("s" * 40) == Learned(None, None, 0.0)  # successes 1 step too long are not within bound


def test_learned_early_and_stays():
    assert rule("." * 4 + "x" * 36) == Learned(125, 12.5, 1.0)
    # Two dips after the start keep the streak: from 125 on 34 of 36 (94%) are within bound.
    assert rule("." * 4 + "xxxx..xxxx" + "x" * 26) == Learned(125, 12.5, 1.0)


def test_learned_then_lost():
    assert rule("." * 4 + "x" * 26 + "." * 10) == Learned(None, None, 0.0)
    # Lost for 2 of the last quarter's 10: 80% < 90%.
    assert rule("." * 4 + "x" * 26 + "xxxx..xxxx") == Learned(None, None, 0.8)


def test_flickering_at_85_percent_in_the_last_quarter_is_not_learned():
    # 80 evaluations, budget 2000: the last quarter is the 20 at 1525..2000, 17 of them (85%) within bound.
    pattern = "xxxxxx.xxxxxx.xxxxx." * 4
    assert learned(evals(pattern), OPTIMAL, 2000) == Learned(None, None, 0.85)


def test_learned_only_in_the_last_quarter():
    assert rule("." * 30 + "x" * 10) == Learned(775, 77.5, 1.0)
    assert rule("." * 31 + "x" * 9) == Learned(800, 80.0, 0.9)


def test_exactly_90_percent_is_learned():
    # One failure among the last quarter's 10: 9/10.
    assert rule("x" * 30 + "xxxx.xxxxx") == Learned(25, 2.5, 0.9)
    # 27 of 30: 120 evaluations, budget 3000, the last quarter the 30 at 2275..3000.
    pattern = "x" * 90 + "xxxxxxxxx." * 3
    assert learned(evals(pattern), OPTIMAL, 3000) == Learned(25, 2.5, 0.9)
    below = "x" * 90 + "xxxxxxxxx." * 2 + "xxxxxxxx.."  # 26 of 30
    assert learned(evals(below), OPTIMAL, 3000) == Learned(None, None, 26 / 30)


def test_an_early_lucky_evaluation_is_not_the_learned_step():
    assert rule("x" + "." * 29 + "x" * 10) == Learned(775, 77.5, 1.0)
    # Three early hits, then 5 failures: from 25, 50 or 75 on only 35/40, 34/39, 33/38 (< 90%) are within bound.
    assert rule("xxx" + "....." + "x" * 32) == Learned(225, 22.5, 1.0)


def test_last_quarter_starts_strictly_after_three_quarters_of_the_budget():
    at_750 = [EvalRecord(750, 100, False, 1.0), EvalRecord(1000, 21, True, 2.0)]
    assert learned(at_750, OPTIMAL, 1000) == Learned(1000, 2.0, 1.0)  # 750 is not in it; from 750 on only 1/2
    assert learned([EvalRecord(700, 21, True)], OPTIMAL, 1000) == Learned(None, None, None)  # no last-quarter eval
    assert learned([], OPTIMAL, 1000) == Learned(None, None, None)


def test_wall_seconds_not_recorded():
    rows = [EvalRecord(s, 21, True) for s in (500, 1000)]  # old eval.csv: no wall_s
    assert learned(rows, OPTIMAL, 1000) == Learned(500, None, 1.0)
    rows = [EvalRecord(s, 21, True, float("nan")) for s in (500, 1000)]
    assert learned(rows, OPTIMAL, 1000) == Learned(500, None, 1.0)


def _reference(pattern: str, total: int) -> Learned:
    """The rule, written out directly from its definition (quadratic), to check :func:`learned` against."""
    ok = [c == "x" for c in pattern]
    steps = [EVERY * k for k in range(1, len(pattern) + 1)]
    quarter = [w for s, w in zip(steps, ok) if 4 * s > 3 * total]
    if not quarter:
        return Learned(None, None, None)
    share = sum(quarter) / len(quarter)
    if 10 * sum(quarter) < 9 * len(quarter):
        return Learned(None, None, share)
    for i in range(len(ok)):
        if ok[i] and 10 * sum(ok[i:]) >= 9 * len(ok[i:]):
            return Learned(steps[i], steps[i] / 10, share)
    raise AssertionError("a learned run has a learned step")


def test_matches_the_definition_on_random_runs():
    rng = random.Random(7)
    outcomes = set()
    for _ in range(400):
        n = rng.randint(1, 60)
        p = rng.choice([0.5, 0.85, 0.95, 1.0])
        onset = rng.randint(0, n)  # failures before, within bound with probability p after
        pattern = "".join("." if k < onset or rng.random() > p else "x" for k in range(n))
        total = EVERY * n + rng.choice([0, 0, 40])  # budget at the last evaluation, or a little after it
        got = learned(evals(pattern), OPTIMAL, total)
        assert got == _reference(pattern, total), pattern
        if got.env_step is not None:  # the first within-bound evaluation of the last quarter qualifies, or earlier
            first = next(EVERY * k for k, c in enumerate(pattern, 1) if c == "x" and 4 * EVERY * k > 3 * total)
            assert got.env_step <= first
        outcomes.add(got.env_step is None)
    assert outcomes == {True, False}


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="optimal_length must be > 0, got 0"):
        learned(evals("x"), 0, 25)
    with pytest.raises(ValueError, match="total_env_steps must be > 0, got 0"):
        learned(evals("x"), OPTIMAL, 0)
    with pytest.raises(ValueError, match="out of order \\(env_steps 50 then 25\\)"):
        learned(evals("xx")[::-1], OPTIMAL, 50)


# ---------------------------------------------------------------------------------------------------------------------
# The trainer: eval.csv's wall_s, summary.json, and the evaluation list across a resume
# ---------------------------------------------------------------------------------------------------------------------

# Tabular Q-learning with Smart Start learns easy_small (shortest path 19) within ~2000 steps at seed 0, in seconds.
RUN = ["+experiment=easy_small_tabular_ss", "trainer.eval_interval=100", "trainer.checkpoint_interval=100000"]


def _eval_rows(run_dir) -> list[EvalRecord]:
    with (run_dir / EVAL_FILE).open(newline="") as f:
        rows = list(csv.DictReader(f))
    return [
        EvalRecord(int(r["env_steps"]), int(r["eval_length"]), r["eval_success"] == "1", float(r["wall_s"]))
        for r in rows
    ]


@pytest.mark.slow  # a training run, resumed
def test_summary_applies_the_rule_to_eval_csv_also_after_a_resume(tmp_path):
    first = Trainer(compose_cfg(*RUN, "trainer.total_env_steps=2000"), tmp_path).train()
    rows_first = _eval_rows(tmp_path)
    with (tmp_path / EVAL_FILE).open() as f:
        assert next(csv.reader(f)) == list(EVAL_COLUMNS)
    assert first == json.loads((tmp_path / SUMMARY_FILE).read_text())
    assert [k for k in SUMMARY_KEYS if k not in first] == []
    expected = learned(rows_first, first["optimal_length"], 2000)
    got = (first["learned_env_step"], first["learned_wall_s"], first["last_quarter_within"])
    assert got == (expected.env_step, expected.wall_s, expected.last_quarter_within)
    walls = [r.wall_s for r in rows_first]
    assert walls == sorted(walls) and 0 <= walls[0] and walls[-1] <= first["wall_s"]

    # Resume the completed run with twice the budget: the rule sees the evaluations of both sessions.
    trainer = Trainer(compose_cfg(*RUN, "trainer.total_env_steps=4000", "trainer.resume=true"), tmp_path)
    assert trainer.evals == rows_first
    second = trainer.train()
    rows = _eval_rows(tmp_path)
    assert rows[: len(rows_first)] == rows_first and len(rows) > len(rows_first)
    assert trainer.evals == rows
    assert [r.wall_s for r in rows] == sorted(r.wall_s for r in rows)  # the wall clock goes on across the resume
    expected = learned(rows, second["optimal_length"], 4000)
    assert expected.env_step is not None and expected.env_step < 2000  # learned in the first session, and stayed
    got = (second["learned_env_step"], second["learned_wall_s"], second["last_quarter_within"])
    assert got == (expected.env_step, expected.wall_s, expected.last_quarter_within)


@pytest.mark.slow  # a training run
def test_resume_refuses_outputs_from_before_the_evaluation_list(tmp_path):
    Trainer(compose_cfg(*RUN, "trainer.total_env_steps=200"), tmp_path).train()
    state = torch.load(tmp_path / CHECKPOINT_FILE, weights_only=False)
    del state["evals"]
    torch.save(state, tmp_path / CHECKPOINT_FILE)
    with pytest.raises(ValueError, match=r"checkpoint.pt predates the list of evaluations"):
        Trainer(compose_cfg(*RUN, "trainer.total_env_steps=400", "trainer.resume=true"), tmp_path)
    # An eval.csv without wall_s: rows of 5 fields under its 4-field header would make a file no one can parse.
    old = tmp_path / "old"
    old.mkdir()
    (old / EVAL_FILE).write_text("env_steps,episode,eval_length,eval_success\r\n100,0,1000,0\r\n")
    with pytest.raises(ValueError, match="eval.csv has columns env_steps,episode,eval_length,eval_success but"):
        RunLogger(old, compose_cfg(*RUN), {}, resume_rows=(0, 1, 0))


def test_an_evaluation_brings_every_csv_on_disk_up_to_date(tmp_path):
    logger = RunLogger(tmp_path, compose_cfg(*RUN), {})
    for k in range(3):  # fewer episodes than the 50 between episodes.csv's own flushes
        logger.log_episode(dict.fromkeys(EPISODE_COLUMNS, k))
    logger.log_train(dict.fromkeys(TRAIN_COLUMNS, 0))
    logger.log_eval(dict.fromkeys(EVAL_COLUMNS, 0))
    on_disk = {
        name: list(csv.reader((tmp_path / name).read_text().splitlines()))
        for name in (EPISODES_FILE, TRAIN_FILE, EVAL_FILE)
    }
    assert [row[0] for row in on_disk[EPISODES_FILE][1:]] == ["0", "1", "2"]
    assert len(on_disk[TRAIN_FILE]) == 2
    assert on_disk[EVAL_FILE] == [list(EVAL_COLUMNS), ["0"] * len(EVAL_COLUMNS)]  # its own row too
    logger.close()
