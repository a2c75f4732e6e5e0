"""Hindsight Experience Replay on a TorchRL replay buffer, relabeling at sample time.

The buffer stores transitions from N env copies collected in lock-step batches of shape (T, N). Flattened row-major
into a TorchRL ``LazyTensorStorage`` of ``rows * N`` slots, the transition of copy ``e`` at absolute row ``t``
(t-th env step of the run) lives in slot ``(t % rows) * N + e``: each copy owns one column, so its episodes stay
contiguous in time even after the buffer wraps around, and another copy's data is never mixed in.

Per slot the buffer keeps its episode's first and last absolute rows (the last is filled in when the episode ends;
until then it is the newest row). Sampling is then O(batch), whatever the number of stored transitions:

* ``future``: the new goal is the achieved goal (the next state) of a step t' >= t of the same episode and copy;
* ``final``: of the episode's last stored step;
* ``episode``: of any stored step of the same episode;
* ``random``: of any stored transition.

A fraction k / (k + 1) of each batch is relabeled (the first items; the sample's ``relabeled`` key marks them).
For a relabeled transition reward **and** terminated/done are recomputed for the new goal: one that reaches its goal
is terminal, so the target never bootstraps past it.

``torchrl.data.HERReplayBuffer`` (torchrl 0.13/0.14) is not used: it takes the goal from the pre-action achieved
goal and keeps stale terminated/done flags on a relabeled sample (both shown in ``tests/test_her.py``); in 0.14 it
also rebuilds its episode index from the whole storage after every write, so each write costs O(stored).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from ss_drl.envs.maze import goal_reward

STRATEGIES = ("future", "final", "episode", "random")


def storage_rows(capacity: int, num_envs: int) -> int:
    """The steps of ``num_envs`` env copies that a buffer of ``capacity`` transitions holds: each copy owns one column
    of ``ceil(capacity / num_envs)`` rows."""
    return -(-int(capacity) // int(num_envs))


class HindsightReplayBuffer(TensorDictReplayBuffer):
    """A TorchRL replay buffer of goal-conditioned maze transitions with HER relabeling at sample time.

    Args:
        capacity: transitions to keep (rounded up to a multiple of ``num_envs``).
        num_envs: env copies whose (T, N) batches are stored.
        batch_size: default sample size.
        strategy: ``future``, ``final``, ``episode`` or ``random``.
        k: relabeled goals per real one (relabel ratio k / (k + 1)); ``k = 0`` turns HER off.
        generator: RNG for goal selection (defaults to torch's global RNG).
        n_step: steps per sampled transition (see :meth:`_n_step`); ``gamma`` discounts the rewards inside it.
        goal_steps: give each sample ``goal_steps``, the steps k after which the stored episode reached the sample's
            goal (0: not known to be reached), for the agent's hindsight bound. Off, the real-goal items skip the
            read it costs.
        window_states: give each sample ``window_observation`` (B, n_step): the state after each step of its n-step
            window (entries past the window's m steps repeat later stored states; ``n_steps`` says how many count),
            for the agent's ``n_step_max`` targets.

    Stored keys: ``observation``, ``desired_goal``, ``action`` and ``next``: ``observation`` (the achieved goal),
    ``desired_goal``, ``reward``, ``terminated``, ``truncated``, ``done``.
    """

    def __init__(
        self,
        capacity: int,
        num_envs: int,
        batch_size: int,
        strategy: str = "future",
        k: int = 4,
        generator: torch.Generator | None = None,
        n_step: int = 1,
        gamma: float = 1.0,
        goal_steps: bool = False,
        window_states: bool = False,
        cells: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ):
        if n_step < 1:
            raise ValueError(f"n_step must be >= 1 (got {n_step})")
        if strategy not in STRATEGIES:
            raise ValueError(f"unknown HER strategy {strategy!r} (allowed: {', '.join(STRATEGIES)})")
        if k < 0:
            raise ValueError(f"HER k must be >= 0 (got {k})")
        self.num_envs = int(num_envs)
        self.rows = storage_rows(capacity, self.num_envs)
        super().__init__(
            storage=LazyTensorStorage(self.rows * self.num_envs),
            sampler=RandomSampler(),
            batch_size=batch_size,
        )
        self.strategy = strategy
        self.k = int(k)
        self.generator = generator
        self.n_step, self.gamma = int(n_step), float(gamma)
        self.goal_steps = bool(goal_steps)
        self.window_states = bool(window_states)
        self.cells = cells  # a state's cell, its achieved goal (None: states are cells, as in a maze)
        shape = (self.rows, self.num_envs)
        self.ep_start = torch.zeros(shape, dtype=torch.int64)  # absolute row of the slot's episode start
        self.ep_end = torch.full(shape, -1, dtype=torch.int64)  # absolute row of its last step; -1 while running
        self.rows_written = 0  # absolute rows written so far
        self.open_start = torch.zeros(self.num_envs, dtype=torch.int64)  # start row of each copy's running episode

    @property
    def relabel_ratio(self) -> float:
        return self.k / (self.k + 1)

    # --- writing -----------------------------------------------------------------------------------------------
    def extend(self, batch: TensorDictBase, **kwargs) -> torch.Tensor:
        """Store a (T, N) batch of consecutive steps of the N copies and update the episode bookkeeping."""
        if batch.ndim != 2 or batch.shape[1] != self.num_envs:
            raise ValueError(f"expected a (T, {self.num_envs}) batch, got shape {tuple(batch.shape)}")
        n_rows = batch.shape[0]
        if n_rows > self.rows:
            raise ValueError(f"batch of {n_rows} rows is larger than the buffer ({self.rows} rows)")
        done = batch.get(("next", "done")).reshape(n_rows, self.num_envs)
        first = self.rows_written
        abs_row = torch.arange(first, first + n_rows).unsqueeze(1).expand(n_rows, self.num_envs)
        # Episode start: the carried-over start, or the row after each done.
        starts = torch.full_like(abs_row, -1)
        starts[0] = self.open_start
        starts[1:] = torch.where(done[:-1], abs_row[1:], -1)
        ep_start = torch.cummax(starts, dim=0).values
        # Episode end: the next done at or after the row (reverse cumulative min), -1 if still running.
        never = torch.iinfo(torch.int64).max
        ends = torch.where(done, abs_row, never).flip(0)
        ep_end = torch.cummin(ends, dim=0).values.flip(0)
        ep_end = torch.where(ep_end == never, -1, ep_end)
        # Close episodes that started in earlier batches and end in this one.
        closing = done.any(dim=0) & (self.open_start < first)
        if bool(closing.any()):
            first_done = torch.where(closing, ep_end[0], -1)
            span = min(int((first - self.open_start[closing]).max()), self.rows)
            back = torch.arange(first - span, first)  # absolute rows, oldest first
            mask = (back.unsqueeze(1) >= self.open_start.unsqueeze(0)) & closing.unsqueeze(0)
            rows = back % self.rows
            block = self.ep_end[rows]
            self.ep_end[rows] = torch.where(mask, first_done.unsqueeze(0), block)
        slot_rows = abs_row[:, 0] % self.rows
        self.ep_start[slot_rows] = ep_start
        self.ep_end[slot_rows] = ep_end
        self.open_start = torch.where(done[-1], first + n_rows, ep_start[-1])
        self.rows_written = first + n_rows
        return super().extend(batch.reshape(-1), **kwargs)

    def _absolute_row(self, row: torch.Tensor) -> torch.Tensor:
        """Absolute row index of the data now stored at storage row ``row``."""
        last = self.rows_written - 1
        return last - torch.remainder(last - row, self.rows)

    # --- sampling ----------------------------------------------------------------------------------------------
    def _sample(self, batch_size: int):
        data, info = super()._sample(batch_size)
        index = torch.as_tensor(info["index"])
        n_her = round(batch_size * self.relabel_ratio)
        relabeled = torch.zeros(batch_size, dtype=torch.bool)
        relabeled[:n_her] = True
        data.set("relabeled", relabeled)  # which items carry a relabeled goal (the first n_her)
        goal_steps = torch.zeros(batch_size, dtype=torch.int64)
        if n_her > 0:
            goal_steps[:n_her] = self._relabel(data, index, n_her)
        if self.goal_steps:
            goal_steps[n_her:] = self._real_goal_steps(data.get("desired_goal")[n_her:], index[n_her:])
            data.set("goal_steps", goal_steps.unsqueeze(1))  # k: the goal is reached k steps on (0: not known to be)
        if self.n_step > 1:
            self._n_step(data, index)
        else:
            data.set("n_steps", torch.ones(batch_size, 1, dtype=torch.int64))
            if self.window_states:
                data.set("window_observation", data.get(("next", "observation")).unsqueeze(1))
        return data, info

    def _real_goal_steps(self, goal: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Per item, the steps k from its step t to the stored step that reached its (real) ``goal``: k = end - t + 1
        when the episode has ended by entering the goal, 0 when it has not (it failed, or is still running)."""
        row, env = index // self.num_envs, index % self.num_envs
        t, end = self._absolute_row(row), self.ep_end[row, env]
        end_slot = (end.clamp(min=0) % self.rows) * self.num_envs + env
        reached = (end >= 0) & goal_reward(self.achieved_goals(end_slot), goal)
        return torch.where(reached, end - t + 1, 0)

    def _relabel(self, data: TensorDictBase, index: torch.Tensor, n_her: int) -> torch.Tensor:
        """Relabel the first ``n_her`` items; returns their steps k to the new goal (0 where it was not taken from
        step t or later of the same episode)."""
        new_goal, goal_steps = self.sample_goals(index[:n_her])
        # ``data`` is a gathered copy, so its leaves are relabeled in place (cheaper than tensordict writes).
        nxt = data.get("next")
        reached = goal_reward(self._cells(nxt.get("observation")[:n_her]), new_goal).unsqueeze(-1)  # (n_her, 1)
        truncated = nxt.get("truncated")[:n_her] & ~reached
        data.get("desired_goal")[:n_her] = new_goal
        nxt.get("desired_goal")[:n_her] = new_goal
        nxt.get("reward")[:n_her] = reached
        nxt.get("terminated")[:n_her] = reached
        nxt.get("truncated")[:n_her] = truncated
        nxt.get("done")[:n_her] = reached | truncated
        return goal_steps

    def _n_step(self, data: TensorDictBase, index: torch.Tensor) -> None:
        """Turn each sampled transition into an n-step one, for its (possibly relabeled) goal.

        From step t, the window runs over the steps t, ..., t + m - 1 of the same episode and copy, where m <= n stops
        at the first step that reaches the goal (terminal), at the episode's last step and at the newest stored step:
        never past the end of an episode. Each step's reward is recomputed for the sample's goal (1 on reaching it,
        which the env's reward is for G too). The sample then holds ``next.reward`` = sum_j gamma^j r_j,
        ``next.observation`` = the state after the window's last step, ``next.terminated``/``done`` = the goal was
        reached in the window, ``next.truncated`` = the window ended at the episode's time limit, and ``n_steps`` = m
        (the target bootstraps with gamma^m); with ``window_states``, ``window_observation`` = the state after each of
        the n steps (past m: later stored states of the same episode, or its last one).
        """
        n = self.n_step
        row, env = index // self.num_envs, index % self.num_envs
        t = self._absolute_row(row)
        end = self.ep_end[row, env]
        end = torch.where(end < 0, self.rows_written - 1, end)  # running episode: up to the newest stored step
        offsets = torch.arange(n)
        rows = t.unsqueeze(1) + offsets  # (B, n) absolute rows of the window
        in_episode = rows <= end.unsqueeze(1)
        slots = (torch.minimum(rows, end.unsqueeze(1)) % self.rows) * self.num_envs + env.unsqueeze(1)
        states = self.next_states(slots)  # (B, n)
        reached = goal_reward(self._cells(states), data.get("desired_goal").unsqueeze(1)) & in_episode
        before = torch.cumsum(reached.long(), dim=1) - reached.long()  # goals reached before each step
        alive = in_episode & (before == 0)  # the window's steps
        m = alive.sum(dim=1)  # >= 1: step t itself is always in it
        hit = reached & alive
        discounts = self.gamma ** offsets.to(torch.float32)
        reward = (hit.to(torch.float32) * discounts).sum(dim=1, keepdim=True)
        terminated = hit.any(dim=1, keepdim=True)
        last = m - 1
        last_slot = slots.gather(1, last.unsqueeze(1)).squeeze(1)
        storage = self._storage._storage
        truncated = storage.get(("next", "truncated"))[last_slot].reshape(-1, 1) & ~terminated
        nxt = data.get("next")
        nxt.set("observation", states.gather(1, last.unsqueeze(1)).squeeze(1))
        nxt.set("reward", reward)
        nxt.set("terminated", terminated)
        nxt.set("truncated", truncated)
        nxt.set("done", terminated | truncated)
        data.set("n_steps", m.unsqueeze(1))
        if self.window_states:
            data.set("window_observation", states)

    def sample_goals(self, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """New goals for the transitions in storage slots ``index`` by the buffer's strategy, and per item the steps
        k from its step t to the step whose next state is the new goal (``source - t + 1``), or 0 where that step is
        not t or later in the same episode (``episode`` goals before t, ``random`` goals)."""
        row, env = index // self.num_envs, index % self.num_envs
        t = self._absolute_row(row)
        start = self.ep_start[row, env].clamp(min=self.rows_written - self.rows)  # oldest step still stored
        end = self.ep_end[row, env]
        end = torch.where(end < 0, self.rows_written - 1, end)
        u = torch.rand(index.shape, generator=self.generator, dtype=torch.float64)
        if self.strategy == "future":
            source = t + (u * (end - t + 1)).long().clamp(max=end - t)
        elif self.strategy == "final":
            source = end
        elif self.strategy == "episode":
            source = start + (u * (end - start + 1)).long().clamp(max=end - start)
        else:  # random: any stored transition, any copy
            filled = min(self.rows_written, self.rows)
            source = self.rows_written - 1 - (u * filled).long().clamp(max=filled - 1)
            env = torch.randint(self.num_envs, index.shape, generator=self.generator)
        goals = self.achieved_goals((source % self.rows) * self.num_envs + env)
        later = source >= t if self.strategy != "random" else torch.zeros_like(source, dtype=torch.bool)
        return goals, torch.where(later, source - t + 1, 0)

    def next_states(self, slots: torch.Tensor) -> torch.Tensor:
        """The next states stored in ``slots``.

        Gathers the one stored tensor (``LazyTensorStorage`` keeps its data in ``_storage``): ``storage[slots]``
        would gather every key.
        """
        return self._storage._storage.get(("next", "observation"))[slots]

    def achieved_goals(self, slots: torch.Tensor) -> torch.Tensor:
        """The achieved goals stored in ``slots``: the cells of the next states (the next states themselves in a
        maze, where states are cells)."""
        return self._cells(self.next_states(slots))

    def _cells(self, states: torch.Tensor) -> torch.Tensor:
        return states if self.cells is None else self.cells(states)

    # --- persistence -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        state = super().state_dict()
        state["her"] = {
            "ep_start": self.ep_start.clone(),
            "ep_end": self.ep_end.clone(),
            "rows_written": self.rows_written,
            "open_start": self.open_start.clone(),
        }
        return state

    def load_state_dict(self, state: dict) -> None:
        her = state["her"]
        super().load_state_dict({k: v for k, v in state.items() if k != "her"})
        self.ep_start, self.ep_end = her["ep_start"].clone(), her["ep_end"].clone()
        self.rows_written, self.open_start = her["rows_written"], her["open_start"].clone()
