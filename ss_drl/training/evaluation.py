"""Greedy evaluation: follow argmax_a Q(s||G, a) from S, as the paper measures steps to the goal."""

from __future__ import annotations

import dataclasses

import torch

from ss_drl.envs.maze import Maze


@dataclasses.dataclass
class GreedyRollout:
    path: list[int]  # visited cells, S first
    length: int  # steps taken (max_steps when G is not reached)
    success: bool


def greedy_policy(agent, maze: Maze) -> torch.Tensor:
    """(n_cells,) greedy action of every cell towards G, from one batched evaluation of Q."""
    cells = torch.arange(maze.n_cells)
    q = agent.q_values(cells, torch.tensor([maze.goal_cell]))[0]  # (n_cells, A)
    return q.argmax(dim=-1)


def greedy_rollout(agent, maze: Maze, max_steps: int) -> GreedyRollout:
    """One deterministic greedy episode from S. A revisited cell means a loop: the episode would fail."""
    policy = greedy_policy(agent, maze).tolist()
    table = maze.transition_table()
    cell, goal = maze.start_cell, maze.goal_cell
    path, seen = [cell], {cell}
    for step in range(1, max_steps + 1):
        cell = int(table[cell, policy[cell]])
        path.append(cell)
        if cell == goal:
            return GreedyRollout(path, step, True)
        if cell in seen:
            break
        seen.add(cell)
    return GreedyRollout(path, max_steps, False)
