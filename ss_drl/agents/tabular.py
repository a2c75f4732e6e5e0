"""Keulen's original baseline: tabular Q-learning with epsilon-greedy exploration (random tie-breaks).

Q(s, a) is a table for the maze's goal G (the original is not goal-conditioned): the update after each transition is
``Q(s,a) += alpha * (r + gamma * (1 - terminated) * max_a' Q(s',a') - Q(s,a))``. With Smart Start it shares the
count model and planner of the deep agent, so both are compared on the same mazes, budgets and outputs.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

from ss_drl.envs.maze import Maze


class TabularQAgent:
    """Tabular Q-learning over maze cells for the fixed goal G.

    Args:
        cfg: ``gamma``, ``alpha``, ``eps_start``/``eps_end``/``eps_decay_steps``.
        maze: the maze.
        seed: seeds the agent's own RNG (exploration and tie-breaks).
    """

    def __init__(self, cfg, maze: Maze, seed: int = 0):
        self.cfg = cfg
        self.maze = maze
        self.gamma = float(cfg.gamma)
        self.alpha = float(cfg.alpha)
        self.q = np.zeros((maze.n_cells, 4), dtype=np.float64)
        self.rng = np.random.default_rng(seed)
        self.epsilon = float(cfg.eps_start)
        self.updates = 0

    def set_epsilon(self, value: float) -> None:
        self.epsilon = float(value)

    def _greedy(self, cells: np.ndarray) -> np.ndarray:
        q = self.q[cells]
        ties = q >= q.max(axis=1, keepdims=True)
        noise = self.rng.random(q.shape)
        return np.where(ties, noise, -1.0).argmax(axis=1)

    def act(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        """Epsilon-greedy actions (the goal is always G for the table)."""
        cells = observation.numpy()
        action = self._greedy(cells)
        explore = self.rng.random(cells.shape) < self.epsilon
        return torch.from_numpy(np.where(explore, self.rng.integers(0, 4, cells.shape), action))

    def q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, 4): the table's Q(s, .) for the maze's goal (the only goal a tabular agent knows)."""
        if bool((goals != self.maze.goal_cell).any()):
            raise ValueError("the tabular agent only knows the maze's goal G")
        q = torch.from_numpy(self.q[states.numpy()]).to(torch.float32)
        return q.unsqueeze(0).expand(goals.numel(), -1, -1)

    def observe(self, batch: TensorDict, env_steps: int) -> None:
        """One Q-learning update per transition, in the order they happened."""
        n_rows, n_envs = batch.shape
        s = batch.get("observation").reshape(-1).tolist()
        a = batch.get("action").reshape(-1).tolist()
        s2 = batch.get(("next", "observation")).reshape(-1).tolist()
        r = batch.get(("next", "reward")).reshape(-1).tolist()
        term = batch.get(("next", "terminated")).reshape(-1).tolist()
        q, alpha, gamma = self.q, self.alpha, self.gamma
        for i in range(n_rows * n_envs):
            target = r[i] if term[i] else r[i] + gamma * q[s2[i]].max()
            q[s[i], a[i]] += alpha * (target - q[s[i], a[i]])
        self.updates += n_rows * n_envs

    def state_dict(self) -> dict:
        return {"q": self.q.copy(), "rng": self.rng.bit_generator.state, "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.q = state["q"].copy()
        self.rng.bit_generator.state = state["rng"]
        self.updates = state["updates"]
