"""Collection: step the batched maze env with the agent's policy (Smart Start guiding where it applies).

``MazeCollector.rollout()`` returns the next ``frames_per_batch`` transitions as a (T, N) tensordict, like a TorchRL
collector, and keeps per-episode statistics. It is a plain loop rather than ``torchrl.collectors.Collector`` because
Smart Start decides per copy at each episode start (selection and planning need the count model and the online
network of that moment; the count model is brought up to date before each episode start), and because at one env
copy the loop's per-step cost is what bounds training speed.
"""

from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDict

from ss_drl.envs.batched import BatchedMazeEnv
from ss_drl.smart_start.counts import CountModel
from ss_drl.smart_start.policy import SmartStart


@dataclasses.dataclass
class Episode:
    """One finished training episode (a row of episodes.csv, less the run-level columns)."""

    env_id: int
    env_steps: int
    length: int
    ret: float
    success: bool
    smart_start: bool
    ss_target: int  # -1: none
    ss_reached: bool
    ss_steps: int
    ss_planned_steps: int


class MazeCollector:
    """Collects (T, N) batches of transitions from a :class:`BatchedMazeEnv`.

    Args:
        env: the batched env.
        agent: has ``act(observation, desired_goal)`` (epsilon-greedy actions) and ``q_values(states, goals)``.
        counts: the count model, updated with every transition.
        smart_start: the Smart Start controller, or None.
        frames_per_batch: transitions per batch (a multiple of the number of copies).
    """

    def __init__(
        self,
        env: BatchedMazeEnv,
        agent,
        counts: CountModel,
        smart_start: SmartStart | None,
        frames_per_batch: int,
    ):
        self.env, self.agent, self.counts, self.smart_start = env, agent, counts, smart_start
        self.num_envs = env.num_envs
        self.steps_per_batch = max(1, frames_per_batch // self.num_envs)
        self.env_steps = 0  # transitions collected (all copies)
        self.ep_length = torch.zeros(self.num_envs, dtype=torch.int64)
        self.ep_return = torch.zeros(self.num_envs, dtype=torch.float32)
        self._td: TensorDict | None = None

    @property
    def frames_per_batch(self) -> int:
        return self.steps_per_batch * self.num_envs

    def _begin(self, copies: torch.Tensor) -> None:
        self.ep_length[copies] = 0
        self.ep_return[copies] = 0
        if self.smart_start is not None:
            obs = self._td.get("observation")
            self.smart_start.start_episodes(copies, obs, self._td.get("desired_goal"), self.agent.q_values)

    def rollout(self, max_frames: int | None = None) -> tuple[TensorDict, list[Episode]]:
        """The next (T, N) batch of transitions and the episodes that finished in it.

        ``max_frames`` shortens the batch (to whole env steps of all copies), so a run ends at its budget.
        """
        if self._td is None:
            self._td = self.env.reset()
            self._begin(torch.ones(self.num_envs, dtype=torch.bool))
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
        ss = self.smart_start
        counted = 0  # steps of this batch already in the count model

        def count_until(stop: int) -> None:
            # The count model is updated in blocks of steps; Smart Start only reads it at episode starts, so the
            # steps are counted before every episode start and at the end of the batch.
            nonlocal counted
            if stop > counted:
                block = slice(counted, stop)
                self.counts.update(obs[block], action[block], next_obs[block], reward[block])
                counted = stop

        for t in range(t_max):
            td = self._td
            cells, goals = td.get("observation"), td.get("desired_goal")
            guided = None if ss is None else ss.active.clone()
            if guided is not None and bool(guided.all()):
                act = torch.zeros_like(cells)  # every copy follows its plan: the network's actions would be replaced
            else:
                act = self.agent.act(cells, goals)
            if guided is not None:
                act = ss.guide(cells, act)
            td.set("action", act)
            out, self._td = self.env.step_and_maybe_reset(td)
            nxt = out.get("next")
            new_cells, r, done = nxt.get("observation"), nxt.get("reward"), nxt.get("done").squeeze(-1)
            obs[t], goal[t], action[t], next_obs[t], reward[t] = cells, goals, act, new_cells, r
            terminated[t], truncated[t] = nxt.get("terminated"), nxt.get("truncated")
            self.env_steps += n
            self.ep_length += 1
            self.ep_return += r.squeeze(-1)
            if ss is not None:
                ss.after_step(guided, new_cells, done)
            if bool(done.any()):
                count_until(t + 1)
                finished += self._finish(done, terminated[t].squeeze(-1))
        count_until(t_max)
        batch = TensorDict(
            {
                "observation": obs,
                "desired_goal": goal,
                "action": action,
                "next": {
                    "observation": next_obs,
                    "desired_goal": goal,  # fixed within an episode
                    "reward": reward,
                    "terminated": terminated,
                    "truncated": truncated,
                    "done": terminated | truncated,
                },
            },
            batch_size=(t_max, n),
        )
        return batch, finished

    def _finish(self, done: torch.Tensor, success: torch.Tensor) -> list[Episode]:
        ss = self.smart_start
        episodes = []
        for e in torch.nonzero(done).squeeze(-1).tolist():
            used = ss is not None and bool(ss.used[e])
            episodes.append(
                Episode(
                    env_id=e,
                    env_steps=self.env_steps,
                    length=int(self.ep_length[e]),
                    ret=float(self.ep_return[e]),
                    success=bool(success[e]),
                    smart_start=used,
                    ss_target=int(ss.target[e]) if used else -1,
                    ss_reached=used and bool(ss.reached[e]),
                    ss_steps=int(ss.steps[e]) if used else 0,
                    ss_planned_steps=int(ss.planned_steps[e]) if used else 0,
                )
            )
        if ss is not None:
            ss.end_episodes(done)
        self._begin(done)
        return episodes

    def state_dict(self) -> dict:
        return {
            "env_steps": self.env_steps,
            "ep_length": self.ep_length.clone(),
            "ep_return": self.ep_return.clone(),
            "td": None if self._td is None else self._td.select("observation", "desired_goal").clone(),
            "env_cell": self.env.cell.clone(),
            "env_steps_in_episode": self.env.step_count.clone(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.env_steps = state["env_steps"]
        self.ep_length, self.ep_return = state["ep_length"].clone(), state["ep_return"].clone()
        self._td = state["td"]
        self.env.set_state(state["env_cell"], state["env_steps_in_episode"])
