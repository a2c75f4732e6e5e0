"""Learners: the goal-conditioned DQN (:mod:`.dqn`), Keulen's tabular Q-learning baseline (:mod:`.tabular`) and the
frontier explorer (:mod:`.frontier`), a perfect-memory baseline for exploration.

All follow :class:`Agent`, the interface the training loop uses: act, store, update.
"""

from __future__ import annotations

from typing import Protocol

import torch
from tensordict import TensorDictBase

#: What :meth:`Agent.update` returns, in this order (one float tensor of this length, read at the logging cadence):
UPDATE_METRICS = (
    "loss",  # TD loss of the update's batch
    "q_mean",  # mean Q(s||g, a) of the batch's (state, goal, action) on the learner's reward scale
    "td_abs",  # mean |TD error| of the batch
    "her_share",  # fraction of the batch whose goal HER relabeled (to a goal achieved later in the episode)
    "goal_share",  # fraction of the batch whose goal is the maze's goal G
)


class Agent(Protocol):
    """A learner as the training loop sees it.

    The loop collects with :meth:`act` (and Smart Start, which reads :meth:`q_values`), then :meth:`store` s the
    batch, then runs :meth:`updates_due` calls of :meth:`update`.
    """

    epsilon: float  # exploration rate of :meth:`act`, set by the loop's schedule (``agent.eps_*``) where it has one
    updates: int  # learning updates so far

    def act(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        """Epsilon-greedy actions for a batch of (state, goal) cells."""

    def q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, 4): Q(s||g, .) on the env's 0/1 reward scale for each goal (B,) and state (n,)."""

    def greedy_q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """Like :meth:`q_values`, for the greedy policy the agent answers with (evaluation, ``scripts/evaluate.py``,
        ``scripts/diagnose.py``); it may come from a different estimate than the one collection reads."""

    def store(self, batch: TensorDictBase) -> None:
        """Keep a collected (T, N) batch of transitions to learn from."""

    def updates_due(self, env_steps: int, new_steps: int) -> int:
        """How many :meth:`update` calls the last ``new_steps`` env steps (ending at ``env_steps``) are due."""

    def update(self) -> torch.Tensor:
        """One learning update; returns the :data:`UPDATE_METRICS` as a tensor, without a host sync."""

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...
