"""Keulen's original baseline: tabular Q-learning with epsilon-greedy exploration (random tie-breaks).

Q(s, a) is a table for the maze's goal G (the original is not goal-conditioned): the update after each transition is
``Q(s,a) += alpha * (r + gamma * (1 - terminated) * max_a' Q(s',a') - Q(s,a))``. With Smart Start it shares the
count model and planner of the deep agent, so both are compared on the same mazes, budgets and outputs.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase

from ss_drl.envs.maze import Maze
from ss_drl.ops import epsilon_greedy, random_argmax


class TabularQAgent:
    """Tabular Q-learning over maze cells for the fixed goal G (an :class:`~ss_drl.agents.Agent`).

    Online Q-learning learns from each transition once, in the order they happened: :meth:`store` queues a
    collected batch and the one :meth:`update` it is due runs its updates.

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
        self.q = np.zeros((maze.n_states, maze.n_actions), dtype=np.float64)
        self.generator = torch.Generator().manual_seed(seed)
        self.epsilon = float(cfg.eps_start)
        self.updates = 0  # Q-learning updates (one per transition)
        self.pending: list[TensorDictBase] = []  # stored batches not learned from yet

    def act(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        """Epsilon-greedy actions (the goal is always G for the table), greedy ties broken at random."""
        greedy = random_argmax(torch.from_numpy(self.q[observation.numpy()]), dim=-1, generator=self.generator)
        return epsilon_greedy(greedy, self.epsilon, self.generator, self.maze.n_actions)

    def q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, 4): the table's Q(s, .) for the maze's goal (the only goal a tabular agent knows)."""
        if bool((goals != self.maze.goal_cell).any()):
            raise ValueError("the tabular agent only knows the maze's goal G")
        q = torch.from_numpy(self.q[states.numpy()]).to(torch.float32)
        return q.unsqueeze(0).expand(goals.numel(), -1, -1)

    #: The table is the only estimate: its greedy answer is the one collection reads.
    greedy_q_values = q_values

    def store(self, batch: TensorDictBase) -> None:
        self.pending.append(batch)

    def updates_due(self, env_steps: int, new_steps: int) -> int:
        """One :meth:`update` call per stored batch."""
        return len(self.pending)

    def update(self) -> torch.Tensor:
        """One Q-learning update per transition of the oldest stored batch, in the order they happened; returns
        :data:`~ss_drl.agents.UPDATE_METRICS` over those updates (the table learns only for G: no relabeling)."""
        batch = self.pending.pop(0)
        s = batch.get("observation").reshape(-1).tolist()
        a = batch.get("action").reshape(-1).tolist()
        s2 = batch.get(("next", "observation")).reshape(-1).tolist()
        r = batch.get(("next", "reward")).reshape(-1).tolist()
        term = batch.get(("next", "terminated")).reshape(-1).tolist()
        q, alpha, gamma = self.q, self.alpha, self.gamma
        td = np.empty(len(s))
        q_taken = np.empty(len(s))
        for i in range(len(s)):
            target = r[i] if term[i] else r[i] + gamma * q[s2[i]].max()
            q_taken[i] = q[s[i], a[i]]
            td[i] = target - q_taken[i]
            q[s[i], a[i]] += alpha * td[i]
        self.updates += len(s)
        return torch.tensor([np.mean(td**2), q_taken.mean(), np.abs(td).mean(), 0.0, 1.0], dtype=torch.float32)

    def state_dict(self) -> dict:
        return {"q": self.q.copy(), "generator": self.generator.get_state(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.q = state["q"].copy()
        if "generator" in state:  # checkpoints up to 92d551c kept a numpy RNG: the resumed stream differs
            self.generator.set_state(state["generator"])
        self.updates = state["updates"]
