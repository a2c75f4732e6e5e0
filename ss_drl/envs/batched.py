"""A native, batched TorchRL environment: N independent copies of one world stepped with tensor ops.

A world is a maze (:class:`~ss_drl.envs.maze.Maze`) or a MiniGrid task with a fixed layout
(:class:`~ss_drl.envs.minigrid.MiniGridTask`). The dynamics are its precomputed transition table
``next_cell[state, action]`` (``world.transition_table()``), so one step of all N copies is a single gather. Each copy
resets on its own: TorchRL's ``step_and_maybe_reset`` resets exactly the copies whose episode ended (``terminated``
on G or ``truncated`` at ``max_steps``).

Observation keys (int64, shape (N,)), the form the Q-network, the count model and the replay buffer use:
    ``observation``   the agent's state: in a maze its cell ``row * width + col`` (``env.maze.pos(cell)`` gives
                      (row, col)); in a MiniGrid task a state id. ``world.cells(state)`` is its achieved goal.
    ``desired_goal``  the goal's cell
Each copy's step counter (for truncation at ``max_steps``) is env state, readable as ``env.step_count``.

With ``slip > 0`` moves are stochastic (``env.slip``): at each step and in each copy, with probability ``slip`` the
action taken is replaced by one of the four actions drawn uniformly (so the chosen move happens with probability
``1 - slip + slip / 4``). The draws come from the env's own generator (seeded by ``seed`` or ``set_seed``; its state is
``rng_state()``, saved in checkpoints); with ``slip == 0`` nothing is drawn.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from ss_drl.envs.maze import Maze, goal_reward, load_maze


class BatchedMazeEnv(EnvBase):
    """N copies of a world, stepped at once. On a maze, the semantics of :class:`ss_drl.envs.gridworld.MazeEnv`."""

    def __init__(
        self,
        layout: str | Path | Maze = "easy",
        num_envs: int = 1,
        max_steps: int = 1000,
        device="cpu",
        slip: float = 0.0,
        seed: int = 0,
    ):
        if not 0.0 <= float(slip) <= 1.0:
            raise ValueError(f"slip must be in [0, 1] (got {slip})")
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1 (got {num_envs})")
        if int(max_steps) < 1:
            raise ValueError(f"max_steps must be >= 1 (got {max_steps})")
        super().__init__(batch_size=torch.Size([int(num_envs)]), device=device)
        self.maze = load_maze(layout) if isinstance(layout, (str, Path)) else layout  # a maze or a MiniGrid task
        self.num_envs = int(num_envs)
        self.max_steps = int(max_steps)
        self.slip = float(slip)
        self.generator = torch.Generator(device=device).manual_seed(int(seed))  # the slips' draws
        self.width = self.maze.width
        n = self.num_envs
        self.next_cell = torch.as_tensor(self.maze.transition_table(), device=self.device)
        self.start_cell = self.maze.start_state
        self.n_actions = self.maze.n_actions
        self._goal_cell = torch.full((n,), self.maze.goal_cell, dtype=torch.int64, device=self.device)
        # Mutable env state lives in a plain dict: rebinding an attribute of an nn.Module costs more than a step.
        self._state = {
            "cell": torch.full((n,), self.start_cell, dtype=torch.int64, device=self.device),
            "steps": torch.zeros(n, dtype=torch.int64, device=self.device),
        }

        state_spec = Bounded(low=0, high=self.maze.n_states - 1, shape=(n,), dtype=torch.int64, device=self.device)
        cell_spec = Bounded(low=0, high=self.maze.n_cells - 1, shape=(n,), dtype=torch.int64, device=self.device)
        self.observation_spec = Composite(observation=state_spec, desired_goal=cell_spec, shape=(n,))
        self.action_spec = Categorical(self.n_actions, shape=(n,), dtype=torch.int64, device=self.device)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            terminated=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            truncated=Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device),
            shape=(n,),
        )

    @property
    def step_count(self) -> torch.Tensor:
        """Steps taken in each copy's current episode."""
        return self._state["steps"]

    @property
    def cell(self) -> torch.Tensor:
        """Each copy's current cell."""
        return self._state["cell"]

    def _tensordict(self, source: dict[str, torch.Tensor]) -> TensorDictBase:
        # Every entry is built here with the right shape, dtype and device: skip TensorDict's per-key validation,
        # which costs more than the step itself.
        return TensorDict._new_unsafe(source, batch_size=self.batch_size, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        state = self._state
        if mask is None:
            state["cell"] = torch.full_like(state["cell"], self.start_cell)
            state["steps"].zero_()
        else:
            mask = mask.reshape(self.num_envs)
            state["cell"] = state["cell"].masked_fill(mask, self.start_cell)
            state["steps"].masked_fill_(mask, 0)
        return self._tensordict({"observation": state["cell"], "desired_goal": self._goal_cell})

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = self._state
        action = tensordict.get("action").reshape(self.num_envs)
        if self.slip > 0:
            slipped = torch.rand(self.num_envs, generator=self.generator, device=self.device) < self.slip
            drawn = torch.randint(0, self.n_actions, (self.num_envs,), generator=self.generator, device=self.device)
            action = torch.where(slipped, drawn, action)
        # A new tensor each step (never updated in place), so earlier observations stay valid.
        cell = state["cell"] = self.next_cell[state["cell"], action]
        steps = state["steps"]
        steps += 1
        terminated = goal_reward(self.maze.cells(cell), self._goal_cell).unsqueeze(-1)
        truncated = (steps >= self.max_steps).unsqueeze(-1) & ~terminated
        out = {
            "observation": cell,
            "desired_goal": self._goal_cell,
            "reward": terminated.to(torch.float32),
            "terminated": terminated,
            "truncated": truncated,
            "done": terminated | truncated,
        }
        return self._tensordict(out)

    def set_state(self, cell: torch.Tensor, steps: torch.Tensor) -> None:
        """Restore each copy's cell and step counter (used when a run resumes from a checkpoint)."""
        self._state["cell"] = cell.clone().to(self.device)
        self._state["steps"] = steps.clone().to(self.device)

    def rng_state(self) -> torch.Tensor:
        """The slips' generator state (for checkpoints)."""
        return self.generator.get_state()

    def set_rng_state(self, state: torch.Tensor) -> None:
        self.generator.set_state(state)

    def _set_seed(self, seed: int | None) -> None:
        # Only the slips are random (the start state is fixed).
        self.generator.manual_seed(0 if seed is None else int(seed))
