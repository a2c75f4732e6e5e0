"""Greedy evaluation: follow argmax_a Q(s||G, a) from S, as the paper measures steps to the goal."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ss_drl.envs.maze import Maze


@dataclasses.dataclass
class GreedyRollout:
    path: list[int]  # visited cells, S first
    length: int  # steps taken (max_steps when G is not reached)
    success: bool
    accuracy: float  # fraction of the states that can reach the goal whose greedy action is on a shortest path


def greedy_accuracy(policy: torch.Tensor, maze: Maze, goal: int | None = None) -> float:
    """Fraction of the free cells that can reach ``goal`` (the goal itself aside) whose greedy action in
    ``policy`` (n_cells,) leads one step closer to it. 1.0: greedy from anywhere is a shortest path.

    Moves are reversible in these mazes, so the BFS distances from the goal are the distances to it.
    """
    goal = maze.goal_cell if goal is None else goal
    dist = maze.distances_from(maze.pos(goal)).reshape(-1)
    cells = np.flatnonzero(dist > 0)
    successor = maze.transition_table()[cells, policy.numpy()[cells]]
    return float(np.mean(dist[successor] == dist[cells] - 1))


def greedy_policy(agent, maze: Maze, goal: int | None = None) -> torch.Tensor:
    """(n_cells,) greedy action of every cell towards ``goal`` (default G), from one batched evaluation of Q."""
    cells = torch.arange(maze.n_cells)
    goal = maze.goal_cell if goal is None else goal
    q = agent.greedy_q_values(cells, torch.tensor([goal]))[0]  # (n_cells, A)
    return q.argmax(dim=-1)


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
    cell = maze.start_cell if start is None else start
    path, seen = [cell], {cell}
    for step in range(1, max_steps + 1):
        cell = int(table[cell, policy[cell]])
        path.append(cell)
        if cell == goal:
            return GreedyRollout(path, step, True, accuracy)
        if cell in seen:
            break
        seen.add(cell)
    return GreedyRollout(path, max_steps, False, accuracy)
