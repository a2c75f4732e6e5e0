"""The Smart Start controller of guided collection: each episode may begin with a guided phase that travels to S_ss,
then hands over to the agent's epsilon-greedy policy.

Per env copy, at the start of an episode and with probability eta (never in the copy's first episode, and only once
a state has been visited), the smart start state S_ss is chosen by UCB, the planner computes a greedy route to it on
the count model, and the copy follows that route until it is within theta of S_ss, reaches G, or the episode's step
budget ends. The network's epsilon-greedy policy acts for the rest of the same episode. Both phases share the one
step budget of the episode, and every transition of both goes into the replay buffer and the count model.
"""

from __future__ import annotations

import torch

from ss_drl.envs.maze import Maze
from ss_drl.ops import epsilon_greedy, manhattan
from ss_drl.smart_start.counts import CountModel
from ss_drl.smart_start.planner import Planner
from ss_drl.smart_start.selection import select_smart_start


class SmartStart:
    """Per-copy Smart Start state machine.

    Args:
        maze: the maze (for grid distances).
        counts: the shared count model.
        num_envs: env copies.
        eta: probability of a guided phase at an episode start.
        c_ss: exploration weight of the UCB bonus.
        w_q: weight of max_a Q in the UCB (1 in the paper; Keulen's 2017 form weighs it separately).
        theta: the guided phase ends within this Manhattan distance of S_ss.
        planner: the value-iteration planner.
        generator: RNG for the eta draws and the tie-breaks (separate from the training RNG, so that eta = 0
            reproduces a run without Smart Start exactly).
        guided_epsilon: probability of a random action at each guided step (0: the route is followed exactly).
    """

    def __init__(
        self,
        maze: Maze,
        counts: CountModel,
        num_envs: int,
        eta: float,
        c_ss: float,
        w_q: float,
        theta: int,
        planner: Planner,
        generator: torch.Generator,
        guided_epsilon: float = 0.0,
    ):
        self.maze, self.counts, self.planner, self.generator = maze, counts, planner, generator
        self.eta, self.c_ss, self.w_q, self.theta = float(eta), float(c_ss), float(w_q), int(theta)
        self.guided_epsilon = float(guided_epsilon)
        n = int(num_envs)
        self.episodes = torch.zeros(n, dtype=torch.int64)  # finished episodes per copy
        self.active = torch.zeros(n, dtype=torch.bool)  # in the guided phase now
        self.used = torch.zeros(n, dtype=torch.bool)  # this episode began with a guided phase
        self.reached = torch.zeros(n, dtype=torch.bool)  # the guided phase reached S_ss
        self.steps = torch.zeros(n, dtype=torch.int64)  # steps taken in the guided phase
        self.planned_steps = torch.zeros(n, dtype=torch.int64)  # route length predicted by the planner
        self.target = torch.full((n,), -1, dtype=torch.int64)  # S_ss per copy
        self.route = torch.zeros(n, maze.n_cells, dtype=torch.int64)  # greedy planner action per cell
        self.decisions = 0

    def within(self, cells: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Whether each cell is within Manhattan distance theta of its target."""
        return manhattan(cells, targets, self.maze.width) <= self.theta

    def start_episodes(self, copies: torch.Tensor, cells: torch.Tensor, goals: torch.Tensor, q_values) -> None:
        """Begin episodes in the copies of bool mask ``copies``; decide and plan their guided phases.

        ``q_values(states, goals) -> (B, n, A)`` evaluates the online network for all visited states at once.
        """
        self.active[copies] = False
        self.used[copies] = False
        self.reached[copies] = False
        self.steps[copies] = 0
        self.planned_steps[copies] = 0
        self.target[copies] = -1
        if self.eta <= 0 or self.counts.total_visits == 0:
            return
        eligible = copies & (self.episodes > 0)
        draw = torch.rand(eligible.shape, generator=self.generator, dtype=torch.float64)
        chosen = torch.nonzero(eligible & (draw < self.eta)).squeeze(-1)
        if chosen.numel() == 0:
            return
        targets = select_smart_start(
            self.counts,
            lambda states, g: q_values(states, g).amax(dim=-1),
            goals[chosen],
            self.c_ss,
            self.w_q,
            self.generator,
        )
        plan = self.planner.plan(self.counts, targets, self.generator)
        self.decisions += int(chosen.numel())
        self.route[chosen] = plan.policy
        self.target[chosen] = targets
        self.used[chosen] = True
        # V(s0) = gamma^(L - 1) on a deterministic route of L steps: the planner's own estimate of the route length.
        start_values = plan.values[cells[chosen], torch.arange(chosen.numel())].double()
        gamma = torch.tensor(self.planner.gamma, dtype=torch.float64)
        length = torch.where(start_values > 0, torch.log(start_values) / torch.log(gamma) + 1, -1.0)
        self.planned_steps[chosen] = length.round().long()
        there = self.within(cells[chosen], targets)
        self.active[chosen] = ~there
        self.reached[chosen] = there

    def guide(self, cells: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The planner's action for copies in the guided phase, ``action`` for the others.

        With ``guided_epsilon > 0`` a guided step is a uniformly random action with that probability (the route
        is then taken up again from wherever the agent is: the plan covers every visited state).
        """
        if not bool(self.active.any()):
            return action
        planned = self.route.gather(1, cells.unsqueeze(1)).squeeze(1)
        if self.guided_epsilon > 0:
            planned = epsilon_greedy(planned, self.guided_epsilon, self.generator)
        return torch.where(self.active, planned, action)

    def after_step(self, was_active: torch.Tensor, next_cells: torch.Tensor, done: torch.Tensor) -> None:
        """Advance the guided phases after an env step (``was_active``: the mask before the step)."""
        if not bool(was_active.any()):
            return
        self.steps += was_active.long()
        arrived = was_active & self.within(next_cells, self.target)
        self.reached |= arrived
        self.active &= ~arrived & ~done

    def end_episodes(self, copies: torch.Tensor) -> None:
        self.episodes[copies] += 1
        self.active[copies] = False

    def state_dict(self) -> dict:
        names = ("episodes", "active", "used", "reached", "steps", "planned_steps", "target", "route")
        state = {name: getattr(self, name).clone() for name in names}
        state.update(generator=self.generator.get_state(), decisions=self.decisions)
        return state

    def load_state_dict(self, state: dict) -> None:
        for name in ("episodes", "active", "used", "reached", "steps", "planned_steps", "target", "route"):
            setattr(self, name, state[name].clone())
        self.generator.set_state(state["generator"])
        self.decisions = state["decisions"]
