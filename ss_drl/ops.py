"""Small tensor operations that several modules share, each written once.

* :func:`random_argmax`: argmax with ties broken uniformly at random (Smart Start's UCB, the planner, the table).
* :func:`manhattan`: grid distance between flat cell indices (Smart Start's arrival test, the planner's targets).
* :func:`linear_schedule` and :func:`epsilon_greedy`: the schedules of epsilon and the learning rate, and the
  epsilon-greedy action.
"""

from __future__ import annotations

import torch


def random_argmax(values: torch.Tensor, dim: int = -1, generator: torch.Generator | None = None) -> torch.Tensor:
    """Index of the maximum of ``values`` along ``dim``, ties broken uniformly at random.

    Every entry equal to the maximum gets a uniform random key and the largest key wins, so each tied index is
    equally likely; one draw of ``values.shape`` (in ``values``' dtype when floating, else float64) per call.
    """
    best = values.amax(dim=dim, keepdim=True)
    dtype = values.dtype if values.is_floating_point() else torch.float64
    noise = torch.rand(values.shape, generator=generator, dtype=dtype, device=values.device)
    return torch.where(values >= best, noise, -1.0).argmax(dim=dim)


def manhattan(cells: torch.Tensor, others: torch.Tensor, width: int) -> torch.Tensor:
    """Manhattan distance between flat cell indices (``row * width + col``); the two tensors broadcast."""
    return (cells // width - others // width).abs() + (cells % width - others % width).abs()


def linear_schedule(env_steps: int, start: float, end: float, decay_steps: int) -> float:
    """A value annealed linearly from ``start`` at step 0 to ``end`` at ``decay_steps``, constant after (epsilon;
    the learning rate)."""
    frac = min(1.0, env_steps / max(1, decay_steps))
    return start + frac * (end - start)


def epsilon_greedy(
    greedy: torch.Tensor, epsilon: float, generator: torch.Generator | None = None, n_actions: int = 4
) -> torch.Tensor:
    """With probability ``epsilon`` a uniformly random action of the ``n_actions``, else the greedy action, per
    entry."""
    explore = torch.rand(greedy.shape, generator=generator) < epsilon
    return torch.where(explore, torch.randint(0, n_actions, greedy.shape, generator=generator), greedy)
