"""When a run has "learned" the maze (issue 12): one rule, used by the trainer's summary and by the results table.

The numbers are exact fractions, so that "exactly 90%" and "exactly 1.05x" are decided without float rounding.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import NamedTuple

#: An evaluation is within bound when it succeeds with ``eval_length <= BOUND * optimal_length``.
BOUND = Fraction(105, 100)
#: The share of evaluations that must be within bound (in the last quarter, and from the learned step on).
SHARE = Fraction(9, 10)
#: The last quarter of the budget: evaluations with ``env_steps > LAST_QUARTER * total_env_steps``.
LAST_QUARTER = Fraction(3, 4)


class EvalRecord(NamedTuple):
    """One greedy evaluation from S (one row of eval.csv)."""

    env_steps: int | float  # env steps of training when it ran
    length: int | float  # the greedy episode's length (max_steps when it failed)
    success: bool | int | float  # whether it reached G (truthy)
    wall_s: float | None = None  # seconds since the run started (None: not recorded, e.g. an old eval.csv)


@dataclass(frozen=True)
class Learned:
    """The rule's verdict on one run (see :func:`learned`)."""

    env_step: int | float | None  # env steps of the first evaluation of the streak that stays learned; None if not
    wall_s: float | None  # the run's wall seconds at that evaluation; None if not learned or not recorded
    last_quarter_within: float | None  # fraction of last-quarter evaluations within bound; None if there are none


def within_bound(length: float, success, optimal_length: float) -> bool:
    """Whether one evaluation succeeded with ``length <= 1.05 * optimal_length`` (exactly, no float rounding). Under
    slips ``length`` is the mean length of the evaluation's episodes, ``success`` whether all of them reached G, and
    ``optimal_length`` the optimal policy's expected steps (:meth:`~ss_drl.envs.maze.Maze.expected_steps`)."""
    return bool(success) and Fraction(length) <= BOUND * Fraction(optimal_length)


def learned(evals: Sequence[EvalRecord], optimal_length: int, total_env_steps: int) -> Learned:
    """Whether, and from when, the run's greedy path from S stayed within 1.05x the shortest path.

    ``evals`` are the run's evaluations in order (the rows of eval.csv, ``env_steps`` non-decreasing);
    ``total_env_steps`` is the run's budget (``trainer.total_env_steps``: the run's env steps once completed).

    * An evaluation is *within bound* when ``success`` and ``length <= 1.05 * optimal_length``.
    * The *last quarter* is the evaluations with ``env_steps > 0.75 * total_env_steps``; ``last_quarter_within`` is
      the fraction of them within bound (None when there are none).
    * The run is *learned* iff ``last_quarter_within >= 0.9``.
    * ``env_step`` (None unless learned) is the ``env_steps`` of the earliest within-bound evaluation ``e`` such that,
      among all evaluations from ``e`` to the end of the run (``e`` included), at least 90% are within bound. When
      the run is learned such an ``e`` exists: the first within-bound evaluation of the last quarter qualifies, since
      from it on the last quarter's within-bound evaluations are all there and only failures were left out. So one
      lucky early evaluation followed by many failures is not the learned step; a streak that stays learned is.
    * ``wall_s`` is the ``wall_s`` of that evaluation (None unless learned, or when it was not recorded).

    Raises ``ValueError`` on a non-positive ``optimal_length`` or ``total_env_steps``, or evaluations out of order.
    """
    if not optimal_length > 0:
        raise ValueError(f"learned: optimal_length must be > 0, got {optimal_length}")
    if not total_env_steps > 0:
        raise ValueError(f"learned: total_env_steps must be > 0, got {total_env_steps}")
    steps = [e.env_steps for e in evals]
    for i in range(1, len(steps)):
        if steps[i] < steps[i - 1]:
            raise ValueError(f"learned: evaluations out of order (env_steps {steps[i - 1]} then {steps[i]})")
    ok = [within_bound(e.length, e.success, optimal_length) for e in evals]
    quarter = [w for e, w in zip(evals, ok) if Fraction(e.env_steps) > LAST_QUARTER * total_env_steps]
    if not quarter:
        return Learned(None, None, None)
    share = Fraction(sum(quarter), len(quarter))
    if share < SHARE:
        return Learned(None, None, float(share))
    # From the end backwards: within-bound count and total of evaluations i..end; keep the earliest qualifying i.
    first, within = None, 0
    for i in range(len(evals) - 1, -1, -1):
        within += ok[i]
        if ok[i] and Fraction(within, len(evals) - i) >= SHARE:
            first = i
    e = evals[first]
    wall = None if e.wall_s is None or not math.isfinite(e.wall_s) else float(e.wall_s)
    return Learned(e.env_steps, wall, float(share))
