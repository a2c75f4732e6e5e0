"""Collection: step the batched maze env, each episode beginning with Smart Start's guided phase where it applies.

``MazeCollector.rollout()`` returns the next batch of transitions as a (T, N) tensordict, like a TorchRL collector,
and the episodes that finished in it. An episode has two phases:

1. the **guided phase** (Smart Start): at the episode start the controller may choose S_ss and plan a route to it on
   the count model; the copy follows the route until it arrives;
2. the **epsilon-greedy phase**: the agent's epsilon-greedy policy acts for the rest of the episode.

A batch ends after the step where any episode ends, so the count model, which the training loop updates after each
batch, is current at every episode start, where Smart Start reads it.

It is a plain loop rather than ``torchrl.collectors.Collector`` because Smart Start decides per copy at each episode
start (selection and planning need the count model and the online network of that moment), and because at one env
copy the loop's per-step cost is what bounds training speed.
"""

from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDict

from ss_drl.envs.batched import BatchedMazeEnv
from ss_drl.smart_start.controller import SmartStart
from ss_drl.smart_start.frontier import Frontier


@dataclasses.dataclass
class Episode:
    """One finished training episode (a row of episodes.csv, less the run-level columns)."""

    env_id: int
    env_steps: int
    length: int
    episode_return: float  # undiscounted: 1 if the episode entered G, else 0
    success: bool
    smart_start: bool
    ss_target: int  # -1: none
    ss_reached: bool
    ss_steps: int
    ss_planned_steps: int
    end_state: int  # the cell the episode ended in (G on success)
    new_moves: int = 0  # moves (s, a) tried for the first time in the run during this episode
    new_moves_after_ss: int = 0  # of them, after the guided phase (the exploration phase and the policy's)
    explore_steps: int = 0  # steps of Smart Start's exploration phase (smart_start.explore)
    ss_frontier_steps: int = -1  # planner's steps from S_ss to the nearest frontier state at the episode start


class MazeCollector:
    """Collects (T, N) batches of transitions from a :class:`BatchedMazeEnv`.

    Args:
        env: the batched env.
        agent: an :class:`~ss_drl.agents.Agent` (its ``act`` and, for Smart Start's UCB, ``q_values``).
        smart_start: the Smart Start controller, or None.
        frames_per_batch: the most transitions per batch (a multiple of the number of copies).
        frontier: the tried moves, observed at every step (each episode's ``new_moves``); Smart Start's own when
            it is on.
    """

    def __init__(
        self,
        env: BatchedMazeEnv,
        agent,
        smart_start: SmartStart | None,
        frames_per_batch: int,
        frontier: Frontier | None = None,
    ):
        self.env, self.agent, self.smart_start = env, agent, smart_start
        self.frontier = smart_start.frontier if smart_start is not None else frontier
        self.num_envs = env.num_envs
        self.steps_per_batch = max(1, frames_per_batch // self.num_envs)
        self.env_steps = 0  # transitions collected (all copies)
        self.ep_length = torch.zeros(self.num_envs, dtype=torch.int64)
        self.ep_return = torch.zeros(self.num_envs, dtype=torch.float32)
        self.ep_new_moves = torch.zeros(self.num_envs, dtype=torch.int64)
        self.ep_new_moves_after_ss = torch.zeros(self.num_envs, dtype=torch.int64)
        self.ss_frontier_steps = torch.full((self.num_envs,), -1, dtype=torch.int64)
        self.starting = torch.zeros(self.num_envs, dtype=torch.bool)  # copies whose episode starts at the next step
        self._td: TensorDict | None = None

    @property
    def frames_per_batch(self) -> int:
        return self.steps_per_batch * self.num_envs

    def rollout(self, max_frames: int | None = None) -> tuple[TensorDict, list[Episode]]:
        """The next (T, N) batch of transitions and the episodes that finished in it.

        The batch holds ``frames_per_batch`` transitions, or fewer when an episode ends first; ``max_frames`` caps
        it (to whole env steps of all copies), so a run ends at its budget.
        """
        if self._td is None:
            self._td = self.env.reset()
            self.starting[:] = True
        self._start_episodes()
        t_max, n = self.steps_per_batch, self.num_envs
        if max_frames is not None:
            t_max = max(1, min(t_max, -(-max_frames // n)))
        obs = torch.empty(t_max, n, dtype=torch.int64)
        goal = torch.empty(t_max, n, dtype=torch.int64)
        action = torch.empty(t_max, n, dtype=torch.int64)
        next_obs = torch.empty(t_max, n, dtype=torch.int64)
        reward = torch.empty(t_max, n, 1, dtype=torch.float32)
        terminated = torch.empty(t_max, n, 1, dtype=torch.bool)
        truncated = torch.empty(t_max, n, 1, dtype=torch.bool)
        finished: list[Episode] = []
        steps = 0
        while steps < t_max and not finished:
            td = self._td
            cells, goals = td.get("observation"), td.get("desired_goal")
            act, guided = self._act(cells, goals)
            td.set("action", act)
            out, self._td = self.env.step_and_maybe_reset(td)
            nxt = out.get("next")
            new_cells, r, done = nxt.get("observation"), nxt.get("reward"), nxt.get("done").squeeze(-1)
            if self.frontier is not None:
                new = self.frontier.observe(cells, act, new_cells).long()
                self.ep_new_moves += new
                if guided is not None:
                    self.ep_new_moves_after_ss += new * (~guided).long()
            t = steps
            obs[t], goal[t], action[t], next_obs[t], reward[t] = cells, goals, act, new_cells, r
            terminated[t], truncated[t] = nxt.get("terminated"), nxt.get("truncated")
            steps += 1
            self.env_steps += n
            self.ep_length += 1
            self.ep_return += r.squeeze(-1)
            if guided is not None:
                self.smart_start.after_step(guided, new_cells, done)
            if bool(done.any()):
                finished = self._finish(done, terminated[t].squeeze(-1), new_cells)
        batch = TensorDict(
            {
                "observation": obs[:steps],
                "desired_goal": goal[:steps],
                "action": action[:steps],
                "next": {
                    "observation": next_obs[:steps],
                    "desired_goal": goal[:steps],  # fixed within an episode
                    "reward": reward[:steps],
                    "terminated": terminated[:steps],
                    "truncated": truncated[:steps],
                    "done": terminated[:steps] | truncated[:steps],
                },
            },
            batch_size=(steps, n),
        )
        return batch, finished

    def _act(self, cells: torch.Tensor, goals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Each copy's action: the planned one in the guided phase, the agent's epsilon-greedy one after it.

        Also returns the guided-phase mask before the step (None without Smart Start).
        """
        ss = self.smart_start
        if ss is None:
            return self.agent.act(cells, goals), None
        guided = ss.active.clone()
        if bool(guided.all()):
            # Guided phase in every copy: the network's actions would all be replaced, so it is not evaluated.
            return ss.guide(cells, torch.zeros_like(cells)), guided
        return ss.guide(cells, self.agent.act(cells, goals)), guided

    def _start_episodes(self) -> None:
        """Begin the episodes of the copies that just reset: Smart Start decides and plans their guided phases."""
        if not bool(self.starting.any()):
            return
        copies = self.starting.clone()
        self.starting[:] = False
        self.ep_length[copies] = 0
        self.ep_return[copies] = 0
        self.ep_new_moves[copies] = 0
        self.ep_new_moves_after_ss[copies] = 0
        if self.smart_start is not None:
            obs, goals = self._td.get("observation"), self._td.get("desired_goal")
            self.smart_start.start_episodes(copies, obs, goals, self.agent.q_values, self.agent.greedy_q_values)
            steps = self.smart_start.frontier_steps(copies, goals)
            self.ss_frontier_steps = torch.where(copies, steps, self.ss_frontier_steps)

    def _finish(self, done: torch.Tensor, success: torch.Tensor, end_cells: torch.Tensor) -> list[Episode]:
        ss = self.smart_start
        episodes = []
        for e in torch.nonzero(done).squeeze(-1).tolist():
            used = ss is not None and bool(ss.used[e])
            episodes.append(
                Episode(
                    env_id=e,
                    env_steps=self.env_steps,
                    length=int(self.ep_length[e]),
                    episode_return=float(self.ep_return[e]),
                    success=bool(success[e]),
                    smart_start=used,
                    ss_target=int(ss.target[e]) if used else -1,
                    ss_reached=used and bool(ss.reached[e]),
                    ss_steps=int(ss.steps[e]) if used else 0,
                    ss_planned_steps=int(ss.planned_steps[e]) if used else 0,
                    end_state=int(end_cells[e]),
                    new_moves=int(self.ep_new_moves[e]),
                    new_moves_after_ss=int(self.ep_new_moves_after_ss[e]) if used else 0,
                    explore_steps=0 if ss is None else int(ss.explore_steps[e]),
                    ss_frontier_steps=int(self.ss_frontier_steps[e]) if used else -1,
                )
            )
        if ss is not None:
            ss.end_episodes(done)
        self.starting |= done
        return episodes

    def state_dict(self) -> dict:
        return {
            "env_steps": self.env_steps,
            "ep_length": self.ep_length.clone(),
            "ep_return": self.ep_return.clone(),
            "ep_new_moves": self.ep_new_moves.clone(),
            "ep_new_moves_after_ss": self.ep_new_moves_after_ss.clone(),
            "ss_frontier_steps": self.ss_frontier_steps.clone(),
            "starting": self.starting.clone(),
            "td": None if self._td is None else self._td.select("observation", "desired_goal").clone(),
            "env_cell": self.env.cell.clone(),
            "env_steps_in_episode": self.env.step_count.clone(),
            "env_rng": self.env.rng_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.env_steps = state["env_steps"]
        self.ep_length, self.ep_return = state["ep_length"].clone(), state["ep_return"].clone()
        for name in ("ep_new_moves", "ep_new_moves_after_ss", "ss_frontier_steps"):  # absent in older checkpoints
            if name in state:
                setattr(self, name, state[name].clone())
        if self.frontier is not None:
            self.frontier.sync()
        self.starting = state["starting"].clone()
        self._td = state["td"]
        self.env.set_state(state["env_cell"], state["env_steps_in_episode"])
        if "env_rng" in state:  # absent in checkpoints written before env.slip (their moves never slipped)
            self.env.set_rng_state(state["env_rng"])
