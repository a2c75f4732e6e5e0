"""Choosing the smart start state S_ss by an upper confidence bound over the visited states."""

from __future__ import annotations

import torch

from ss_drl.ops import random_argmax
from ss_drl.smart_start.counts import CountModel


def ucb_scores(max_q: torch.Tensor, visits: torch.Tensor, c_ss: float, w_q: float = 1.0) -> torch.Tensor:
    """UCB of each visited state: ``w_q * max_a Q(s||g, a) + sqrt(c_ss * ln(sum_s N(s)) / N(s))``.

    ``w_q = 1`` is the form of the issue/paper; Keulen's 2017 form weighs the two terms separately (``w_q``, ``c_ss``).
    """
    visits = visits.to(torch.float64)
    bonus = torch.sqrt(c_ss * torch.log(visits.sum()) / visits)
    return w_q * max_q.to(torch.float64) + bonus


def select_smart_start(
    counts: CountModel,
    max_q_fn,
    goals: torch.Tensor,
    c_ss: float,
    w_q: float = 1.0,
    generator: torch.Generator | None = None,
    allowed: torch.Tensor | None = None,
) -> torch.Tensor:
    """S_ss for each goal in ``goals`` (B,): argmax over visited states (N(s) > 0) of the UCB, random tie-break.

    Args:
        counts: the count model.
        max_q_fn: ``f(states (n,), goals (B,)) -> (B, n)`` max_a Q(s||g, a), one batched evaluation; not called
            when ``w_q == 0`` (S_ss by counts alone, the paper's experiment), which then needs no network pass.
        goals: (B,) desired goal per env copy that starts an episode.
        allowed: optional (B, S) bool over all states: S_ss is chosen among the visited states it allows (the
            frontier, for ``smart_start.select=frontier``); a row that allows none of them chooses among all.
    Returns:
        (B,) smart start states.
    """
    states = counts.structure().states  # the visited states, cached until a new transition is seen
    if states.numel() == 0:
        raise ValueError("Smart Start needs at least one visited state")
    if w_q == 0:
        max_q = torch.zeros(goals.numel(), states.numel(), dtype=torch.float64)
    else:
        max_q = max_q_fn(states, goals)  # (B, n)
    scores = ucb_scores(max_q, counts.state_counts[states].unsqueeze(0), c_ss, w_q)
    if allowed is not None:
        allowed = allowed[:, states]
        allowed |= ~allowed.any(dim=1, keepdim=True)
        scores = scores.masked_fill(~allowed, -torch.inf)
    return states[random_argmax(scores, dim=1, generator=generator)]
