"""Greedy evaluation: follow argmax_a Q(s||G, a) from S, as the paper measures steps to the goal.

:func:`evaluate_policy` rolls the greedy policy out in the env's own dynamics, ``trainer.eval_episodes`` episodes
from S, slips included (``env.slip``), with no cut-off but ``env.max_steps``: what the trainer's evaluations and the
learned rule use. :func:`greedy_rollout` is the deterministic walk of one episode that stops at the first revisited
cell (a loop in a deterministic maze), for the analysis tools.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from ss_drl.envs.maze import Maze, goal_reward


@dataclasses.dataclass
class GreedyRollout:
    path: list[int]  # visited cells, S first
    length: int  # steps taken (max_steps when G is not reached)
    success: bool
    accuracy: float  # fraction of the states that can reach the goal whose greedy action is on a shortest path


def greedy_accuracy(policy: torch.Tensor, maze: Maze, goal: int | None = None) -> float:
    """Fraction of the states that can reach ``goal`` (its own states aside) whose greedy action in ``policy``
    (n_states,) leads one step closer to it. 1.0: greedy from anywhere is a shortest path. ``maze`` is any world
    (a maze or a MiniGrid task); another goal than G only on a maze, where moves are reversible.
    """
    if goal is None or goal == maze.goal_cell:
        dist = maze.distances_to_goal()
    else:  # another goal cell of a maze
        dist = maze.distances_from(maze.pos(goal)).reshape(-1)
    cells = np.flatnonzero(dist > 0)
    successor = maze.transition_table()[cells, policy.numpy()[cells]]
    return float(np.mean(dist[successor] == dist[cells] - 1))


def greedy_policy(agent, maze: Maze, goal: int | None = None) -> torch.Tensor:
    """(n_states,) greedy action of every state towards ``goal`` (default G), from one batched evaluation of Q."""
    cells = torch.arange(maze.n_states)
    goal = maze.goal_cell if goal is None else goal
    q = agent.greedy_q_values(cells, torch.tensor([goal]))[0]  # (n_states, A)
    return q.argmax(dim=-1)


@dataclasses.dataclass
class Evaluation:
    """``episodes`` greedy episodes from S in the env's dynamics (one evaluation)."""

    lengths: list[int]  # per episode: steps to G, or max_steps when it did not get there
    successes: list[bool]  # per episode: whether it reached G
    path: list[int]  # the first episode's cells, S first

    @property
    def mean_length(self) -> float:
        return sum(self.lengths) / len(self.lengths)

    @property
    def success(self) -> bool:
        """Every episode reached G."""
        return all(self.successes)

    @property
    def success_rate(self) -> float:
        return sum(self.successes) / len(self.successes)


def evaluate_policy(
    policy: torch.Tensor,
    maze: Maze,
    max_steps: int,
    episodes: int = 1,
    slip: float = 0.0,
    generator: torch.Generator | None = None,
    start: int | None = None,
    goal: int | None = None,
) -> Evaluation:
    """Roll ``policy`` ((n_states,) actions) out from ``start`` (default S) for ``episodes`` episodes at once, in the
    env's dynamics: with probability ``slip`` each step's action is replaced by one of the four drawn uniformly
    (from ``generator``: a rand and a randint for every episode at every step while any runs). An episode ends on
    entering ``goal`` (default G) or after ``max_steps`` steps.

    Without slips the episodes are one deterministic walk: a revisited cell means a loop that never reaches G, so
    the walk stops there with ``max_steps`` (what running on would give, sooner).
    """
    goal = maze.goal_cell if goal is None else goal
    table = torch.from_numpy(maze.transition_table())
    n = int(episodes)
    cells = torch.full((n,), maze.start_state if start is None else start, dtype=torch.int64)
    lengths = torch.full((n,), int(max_steps), dtype=torch.int64)
    done = torch.zeros(n, dtype=torch.bool)
    path, seen = [int(cells[0])], {int(cells[0])}
    for step in range(1, int(max_steps) + 1):
        action = policy[cells]
        if slip > 0:
            slipped = torch.rand(n, generator=generator) < slip
            action = torch.where(slipped, torch.randint(0, maze.n_actions, (n,), generator=generator), action)
        cells = torch.where(done, cells, table[cells, action])
        if not done[0]:
            path.append(int(cells[0]))
        hit = goal_reward(maze.cells(cells), goal) & ~done
        lengths[hit] = step
        done |= hit
        if bool(done.all()):
            break
        if slip == 0:
            if int(cells[0]) in seen:  # a loop: deterministic episodes never reach G from here
                break
            seen.add(int(cells[0]))
    return Evaluation(lengths.tolist(), done.tolist(), path)


def optimum(maze: Maze, slip: float) -> float | int:
    """What an evaluation's length is measured against: the shortest path from S, or under slips the optimal
    policy's expected steps from S (value iteration on the true model), rounded once, as ``summary.json`` holds it,
    so that plot.py's learned rule reads the same optimum."""
    if slip > 0:
        return round(float(maze.expected_steps(slip)[0][maze.start_state]), 3)
    return maze.shortest_path_length


def evaluation_episodes(slip: float, configured: int | None) -> int:
    """The episodes of one evaluation: ``trainer.eval_episodes`` when set (``configured``), else
    :func:`eval_episodes`."""
    return eval_episodes(slip) if configured is None else int(configured)


def eval_episodes(slip: float) -> int:
    """``trainer.eval_episodes`` when it is not set: 1 with deterministic moves, else ``ceil(240 * slip)`` (24 at slip
    0.1, 60 at 0.25). The mean length of n episodes of the optimal policy varies as ``slip / n`` (relative to the
    expected length), so n grows with slip: with it the optimal policy itself passes the learned rule in at least
    95% of runs on Easy and Medium at slip 0.1 and Easy at 0.25 (``tests/test_slip.py`` simulates it; Easy, the
    shortest route, needs the most)."""
    return 1 if slip == 0 else math.ceil(240 * slip)


def greedy_rollout(
    agent, maze: Maze, max_steps: int, start: int | None = None, goal: int | None = None
) -> GreedyRollout:
    """One deterministic greedy episode from ``start`` (default S) to ``goal`` (default G), and the greedy policy's
    accuracy over the whole maze (:func:`greedy_accuracy`).

    A revisited cell means a loop, so the episode would fail: it stops there.
    """
    goal = maze.goal_cell if goal is None else goal
    actions = greedy_policy(agent, maze, goal)
    accuracy = greedy_accuracy(actions, maze, goal)
    policy = actions.tolist()
    table = maze.transition_table()
    cell = maze.start_state if start is None else start
    cell_of = maze.cells(torch.arange(maze.n_states)).tolist()
    path, seen = [cell], {cell}
    for step in range(1, max_steps + 1):
        cell = int(table[cell, policy[cell]])
        path.append(cell)
        if goal_reward(cell_of[cell], goal):
            return GreedyRollout(path, step, True, accuracy)
        if cell in seen:
            break
        seen.add(cell)
    return GreedyRollout(path, max_steps, False, accuracy)
