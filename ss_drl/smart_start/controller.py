"""The Smart Start controller of guided collection: each episode may begin with a guided phase that travels to S_ss,
then hands over to the agent's epsilon-greedy policy.

Per env copy, at the start of an episode and with probability eta (never in the copy's first episode, and only once
a state has been visited), the smart start state S_ss is chosen by UCB, the planner computes a greedy route to it on
the count model, and the copy follows that route until it is within theta of S_ss, reaches G, or the episode's step
budget ends. The network's epsilon-greedy policy acts for the rest of the same episode. Both phases share the one
step budget of the episode, and every transition of both goes into the replay buffer and the count model.

Two options, off in the paper's Smart Start, aim the episode at the frontier of exploration (the known states with a
move not tried yet, :mod:`ss_drl.smart_start.frontier`), as a perfect-memory explorer would (issue 49):

* ``select="frontier"``: S_ss is the UCB choice among the visited states on the frontier (among all visited states
  when none is);
* ``explore``: what happens on arrival at S_ss. ``"epsilon_greedy"`` (the paper): the agent's policy takes over.
  ``"untried"``: one untried move of S_ss is tried first (uniformly at random among them), then the policy.
  ``"frontier"`` (Go-Explore's "return, then explore"): an exploration phase follows that tries an untried move
  wherever there is one and otherwise walks the planner's route to the nearest frontier state, until the episode
  ends or no frontier state is left; then the policy.

``explore_after_goal=False`` turns both options off once the goal has been reached in any episode, so that the rest
of the run is the paper's Smart Start.

``greedy_path`` (off in the paper's Smart Start) acts once the goal has been reached. Before each guided phase it walks
the greedy policy that evaluation follows (the network the agent evaluates) from the episode's start on the count
model's observed transitions. If that walk meets a move never tried, before it reaches G or repeats a state, S_ss is
the state where it does and, on arrival, that move is taken first; otherwise S_ss is chosen as above. So an optimistic
value of an untried move on the greedy path (the model-bounded learner's optimistic floor) is tried in training, not
left for every evaluation to walk into. Deterministic moves only.
"""

from __future__ import annotations

import torch

from ss_drl.envs.maze import Maze
from ss_drl.ops import epsilon_greedy, manhattan, random_argmax
from ss_drl.smart_start.counts import CountModel
from ss_drl.smart_start.frontier import Frontier
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
        frontier: the tried moves, current at every step (needed by ``select="frontier"`` and ``explore``).
        select: ``"visited"`` (the paper: S_ss among all visited states) or ``"frontier"``.
        explore: ``"epsilon_greedy"`` (the paper), ``"untried"`` or ``"frontier"``: what follows arrival at S_ss.
        explore_after_goal: keep ``select`` and ``explore`` after the goal has been reached (False: the paper's
            Smart Start from then on).
        explore_from_start: with ``explore="frontier"``, a copy's first episode (which has no guided phase: nothing
            is visited yet) is an exploration phase from its first step.
        guided_limit: the guided phase also ends after this many times the planner's route length (at least one
            step); None: no limit. Under slips the route is walked from wherever the agent lands, and a run of bad
            luck must not keep the policy from acting for the rest of the episode.
        greedy_path: once the goal has been reached, S_ss is the state of the first untried move on the evaluated
            greedy path from the episode's start, where there is one (:meth:`untried_on_greedy_path`), and that
            move is taken on arrival.
        max_steps: the longest greedy walk :meth:`untried_on_greedy_path` takes (the episode's step budget).
    """

    SELECT = ("visited", "frontier")
    EXPLORE = ("epsilon_greedy", "untried", "frontier")

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
        frontier: Frontier | None = None,
        select: str = "visited",
        explore: str = "epsilon_greedy",
        explore_after_goal: bool = True,
        guided_limit: float | None = None,
        explore_from_start: bool = False,
        greedy_path: bool = False,
        max_steps: int = 1000,
    ):
        if select not in self.SELECT or explore not in self.EXPLORE:
            raise ValueError(f"unknown Smart Start option: select={select!r}, explore={explore!r}")
        self.maze, self.counts, self.planner, self.generator = maze, counts, planner, generator
        self.eta, self.c_ss, self.w_q, self.theta = float(eta), float(c_ss), float(w_q), int(theta)
        self.guided_epsilon = float(guided_epsilon)
        self.select, self.explore, self.explore_after_goal = select, explore, bool(explore_after_goal)
        self.guided_limit = None if guided_limit is None else float(guided_limit)
        self.explore_from_start = bool(explore_from_start)
        self.greedy_path, self.max_steps = bool(greedy_path), int(max_steps)
        self.frontier = frontier if frontier is not None else Frontier(counts)
        n = int(num_envs)
        self.episodes = torch.zeros(n, dtype=torch.int64)  # finished episodes per copy
        self.active = torch.zeros(n, dtype=torch.bool)  # in the guided phase now
        self.used = torch.zeros(n, dtype=torch.bool)  # this episode began with a guided phase
        self.reached = torch.zeros(n, dtype=torch.bool)  # the guided phase reached S_ss
        self.steps = torch.zeros(n, dtype=torch.int64)  # steps taken in the guided phase
        self.planned_steps = torch.zeros(n, dtype=torch.int64)  # route length predicted by the planner
        self.target = torch.full((n,), -1, dtype=torch.int64)  # S_ss per copy
        self.route = torch.zeros(n, maze.n_states, dtype=torch.int64)  # greedy planner action per cell
        self.decisions = 0
        self.greedy_path_decisions = 0  # guided phases sent to an untried move on the greedy path (greedy_path)
        # The exploration phase after arrival (explore != "epsilon_greedy").
        self.exploring = torch.zeros(n, dtype=torch.bool)  # in the exploration phase now
        self.explore_steps = torch.zeros(n, dtype=torch.int64)  # steps taken in it this episode
        self.reach = torch.zeros(n, maze.n_states, dtype=torch.bool)  # cells from which the route leads on
        self.plan_version = torch.full((n,), -1, dtype=torch.int64)  # the model's size when the route was planned
        self.goal = torch.full((n,), -1, dtype=torch.int64)  # the episode's goal (never a frontier state)
        self.first_move = torch.full((n,), -1, dtype=torch.int64)  # greedy_path: the move to take on arrival
        self.exact = torch.zeros(n, dtype=torch.bool)  # greedy_path: the guided phase ends in S_ss itself

    # --- the options in force --------------------------------------------------------------------------------------
    def goal_found(self) -> bool:
        """Whether some transition has been rewarded (the goal has been reached in an episode)."""
        return bool((self.counts.reward_sums > 0).any())

    def _options_on(self) -> bool:
        return self.explore_after_goal or not self.goal_found()

    def within(self, cells: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Whether each cell is within Manhattan distance theta of its target."""
        return manhattan(self.maze.cells(cells), self.maze.cells(targets), self.maze.width) <= self.theta

    def arrived(self, cells: torch.Tensor, targets: torch.Tensor, exact: torch.Tensor) -> torch.Tensor:
        """Whether each state ends its guided phase: the target itself where ``exact``, else :meth:`within`."""
        return torch.where(exact, cells == targets, self.within(cells, targets))

    def start_episodes(
        self, copies: torch.Tensor, cells: torch.Tensor, goals: torch.Tensor, q_values, greedy_q_values=None
    ) -> None:
        """Begin episodes in the copies of bool mask ``copies``; decide and plan their guided phases.

        ``q_values(states, goals) -> (B, n, A)`` evaluates the online network for all visited states at once;
        ``greedy_q_values``, of the same form, the network whose greedy policy is evaluated (``greedy_path``).
        """
        self.active[copies] = False
        self.used[copies] = False
        self.reached[copies] = False
        self.steps[copies] = 0
        self.planned_steps[copies] = 0
        self.target[copies] = -1
        self.exploring[copies] = False
        self.explore_steps[copies] = 0
        self.goal[copies] = goals[copies]
        self.first_move[copies] = -1
        self.exact[copies] = False
        if self.explore_from_start and self.explore == "frontier" and self._options_on():
            # A copy's first episode has no S_ss to travel to: with explore_from_start it explores from S at once.
            self.exploring |= copies & (self.episodes == 0)
        if self.eta <= 0 or self.counts.total_visits == 0:
            return
        eligible = copies & (self.episodes > 0)
        draw = torch.rand(eligible.shape, generator=self.generator, dtype=torch.float64)
        chosen = torch.nonzero(eligible & (draw < self.eta)).squeeze(-1)
        if chosen.numel() == 0:
            return
        options = self._options_on()
        targets = select_smart_start(
            self.counts,
            lambda states, g: q_values(states, g).amax(dim=-1),
            goals[chosen],
            self.c_ss,
            self.w_q,
            self.generator,
            allowed=self.frontier.states(goals[chosen]) if options and self.select == "frontier" else None,
        )
        exact = torch.zeros(chosen.numel(), dtype=torch.bool)  # the guided phase ends in S_ss itself
        if self.greedy_path and self.goal_found():
            if greedy_q_values is None:
                raise ValueError("smart_start.greedy_path needs the evaluated network (greedy_q_values)")
            on_path, moves = self.untried_on_greedy_path(cells[chosen], goals[chosen], greedy_q_values)
            exact = moves >= 0
            targets = torch.where(exact, on_path, targets)
            self.first_move[chosen] = moves
            self.greedy_path_decisions += int(exact.sum())
        if bool(exact.any()):  # to the very state whose move is untried, not any state of its cell (MiniGrid)
            terminal = self.planner.terminal_mask(self.counts.n_states, targets).T
            terminal[exact] = torch.arange(self.counts.n_states).unsqueeze(0) == targets[exact].unsqueeze(1)
            plan = self.planner.plan_to(self.counts, terminal, self.generator, targets)
        else:
            plan = self.planner.plan(self.counts, targets, self.generator)
        self.exact[chosen] = exact
        self.decisions += int(chosen.numel())
        self.route[chosen] = plan.policy
        self.target[chosen] = targets
        self.used[chosen] = True
        # V(s0) = gamma^(L - 1) on a deterministic route of L steps: the planner's own estimate of the route length.
        start_values = plan.values[cells[chosen], torch.arange(chosen.numel())]
        self.planned_steps[chosen] = Planner.route_length(start_values, self.planner.gamma).round().long()
        there = self.arrived(cells[chosen], targets, exact)
        self.active[chosen] = ~there
        self.reached[chosen] = there
        self.exploring[chosen] = there & (self.explore != "epsilon_greedy") & options

    def untried_on_greedy_path(
        self, starts: torch.Tensor, goals: torch.Tensor, greedy_q_values
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per start and goal (B,): the first state on the greedy path from the start whose greedy move was never
        tried, and that move; (-1, -1) where the path reaches the goal, repeats a state or runs ``max_steps`` moves
        over tried ones first. The path takes the greedy action of ``greedy_q_values`` in each state and the
        count model's observed successor of each tried move (deterministic moves); it also ends at a move tried in
        the batch being collected, whose successor the count model has not counted yet."""
        known = torch.nonzero(self.frontier.known).squeeze(-1)  # every state the walk can be in, S included
        known = torch.unique(torch.cat((known, starts)))
        greedy = torch.full((goals.numel(), self.counts.n_states), -1, dtype=torch.int64)
        greedy[:, known] = greedy_q_values(known, goals).argmax(dim=-1)
        n = self.counts.n_states
        successor = self.counts.successors().view(n, self.counts.n_actions).tolist()
        tried = self.frontier.tried.tolist()
        cell_of = self.maze.cells(torch.arange(n)).tolist()
        states = torch.full((goals.numel(),), -1, dtype=torch.int64)
        moves = torch.full((goals.numel(),), -1, dtype=torch.int64)
        for i, (s, goal, policy) in enumerate(zip(starts.tolist(), goals.tolist(), greedy.tolist())):
            seen = {s}
            for _ in range(self.max_steps):
                a = policy[s]
                if not tried[s][a]:
                    states[i], moves[i] = s, a
                    break
                s = successor[s][a]
                if s < 0 or cell_of[s] == goal or s in seen:  # s < 0: tried in this batch, not counted yet
                    break
                seen.add(s)
        return states, moves

    def frontier_steps(self, copies: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(N,) for the copies of mask ``copies`` that begin with a guided phase: the fewest steps on the count model
        from S_ss to a frontier state (0 when S_ss is one; -1 when none can be reached, and for the other copies).
        A measurement for episodes.csv: it draws nothing from the controller's generator."""
        out = torch.full(copies.shape, -1, dtype=torch.int64)
        idx = torch.nonzero(copies & self.used).squeeze(-1)
        if idx.numel() == 0:
            return out
        terminal = self.frontier.states(goals[idx])
        targets = self.target[idx]
        on = terminal[torch.arange(idx.numel()), targets]
        out[idx[on]] = 0
        if bool((~on).any()):
            plan = self.planner.plan_to(self.counts, terminal[~on], torch.Generator().manual_seed(0))
            values = plan.values[targets[~on], torch.arange(int((~on).sum()))]
            out[idx[~on]] = Planner.route_length(values, self.planner.gamma).round().long()
        return out

    def guide(self, cells: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The controller's action for copies in the guided or exploration phase, ``action`` for the others.

        With ``guided_epsilon > 0`` a guided step is a uniformly random action with that probability (the route
        is then taken up again from wherever the agent is: the plan covers every visited state).
        """
        if bool(self.exploring.any()):
            action = self._explore(cells, action)
        first = (self.first_move >= 0) & ~self.active & self.reached  # arrived at S_ss: its untried greedy move
        if bool(first.any()):
            action = torch.where(first, self.first_move, action)
            self.first_move[first] = -1
        if not bool(self.active.any()):
            return action
        planned = self.route.gather(1, cells.unsqueeze(1)).squeeze(1)
        if self.guided_epsilon > 0:
            planned = epsilon_greedy(planned, self.guided_epsilon, self.generator, self.counts.n_actions)
        return torch.where(self.active, planned, action)

    def _explore(self, cells: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The exploration phase's actions: an untried move where the cell has one (uniformly at random among them);
        otherwise (``explore="frontier"``) the route to the nearest frontier state, replanned when the count model
        has grown since it was planned or the route ends here. A copy whose cell has no untried move leaves the phase
        with ``explore="untried"``, and with ``"frontier"`` once no frontier state is left; where the model does not
        lead on from the cell yet (a cell entered in this batch), the policy's action is taken and the phase goes on.
        """
        copies = self.exploring.clone()
        self.explore_steps += copies.long()
        untried = self.frontier.untried(cells)  # (N, A)
        has = untried.any(dim=1)
        pick = random_argmax(untried.to(torch.float64), dim=1, generator=self.generator)
        out = torch.where(copies & has, pick, action)
        walking = copies & ~has
        if self.explore == "untried":  # one move, then the policy
            self.exploring[copies] = False
            return out
        if not bool(walking.any()):
            return out
        version = self.counts.keys.numel()
        here = self.reach.gather(1, cells.unsqueeze(1)).squeeze(1)
        stale = walking & ((self.plan_version != version) | ~here)
        if bool(stale.any()):
            idx = torch.nonzero(stale).squeeze(-1)
            terminal = self.frontier.states(self.goal[idx])
            empty = ~terminal.any(dim=1)
            self.exploring[idx[empty]] = False  # nothing left to explore: the policy from here on
            walking &= self.exploring
            idx, terminal = idx[~empty], terminal[~empty]
            if idx.numel():
                plan = self.planner.plan_to(self.counts, terminal, self.generator)
                self.route[idx] = plan.policy
                self.reach[idx] = (plan.values.T > 0) & ~terminal
                self.plan_version[idx] = version
        here = self.reach.gather(1, cells.unsqueeze(1)).squeeze(1)
        routed = self.route.gather(1, cells.unsqueeze(1)).squeeze(1)
        return torch.where(walking & here, routed, out)

    def after_step(self, was_active: torch.Tensor, next_cells: torch.Tensor, done: torch.Tensor) -> None:
        """Advance the guided phases after an env step (``was_active``: the guided-phase mask before the step)."""
        self.exploring &= ~done
        if not bool(was_active.any()):
            return
        self.steps += was_active.long()
        arrived = was_active & self.arrived(next_cells, self.target, self.exact)
        self.reached |= arrived
        self.active &= ~arrived & ~done
        if self.guided_limit is not None:
            limit = (self.guided_limit * self.planned_steps.clamp(min=1).double()).ceil().long()
            self.active &= self.steps < limit
        if self.explore != "epsilon_greedy" and bool(arrived.any()) and self._options_on():
            self.exploring |= arrived & ~done

    def end_episodes(self, copies: torch.Tensor) -> None:
        self.episodes[copies] += 1
        self.active[copies] = False
        self.exploring[copies] = False
        self.first_move[copies] = -1

    STATE = ("episodes", "active", "used", "reached", "steps", "planned_steps", "target", "route")
    EXPLORE_STATE = ("exploring", "explore_steps", "reach", "plan_version", "goal", "first_move", "exact")

    def state_dict(self) -> dict:
        state = {name: getattr(self, name).clone() for name in self.STATE + self.EXPLORE_STATE}
        state.update(
            generator=self.generator.get_state(),
            decisions=self.decisions,
            greedy_path_decisions=self.greedy_path_decisions,
        )
        return state

    def load_state_dict(self, state: dict) -> None:
        for name in self.STATE:
            setattr(self, name, state[name].clone())
        for name in self.EXPLORE_STATE:  # absent from checkpoints written before the exploration options
            if name in state:
                setattr(self, name, state[name].clone())
        self.generator.set_state(state["generator"])
        self.decisions = state["decisions"]
        self.greedy_path_decisions = state.get("greedy_path_decisions", 0)  # absent before smart_start.greedy_path
        self.frontier.sync()
