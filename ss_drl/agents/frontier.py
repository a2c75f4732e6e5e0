"""The frontier explorer: a perfect-memory baseline for exploration, the reference the deep methods' first goal is
measured against (issue 49).

It knows nothing about where G is. Its memory is every transition it has taken, ``(s, a) -> s'`` (a bump into a wall
or off the grid is a tried move with ``s' == s``), kept across episodes. From wherever it stands:

* if its cell has an untried move, it tries one (uniformly at random among them);
* otherwise it walks a shortest known route to the nearest cell with an untried move (the nearest cells tie at
  random) and tries that move there.

A cell once entered with ``terminated`` (G) has no moves to try: the episode ends there. Once no cell with an untried
move can be reached (the maze is explored), it walks the shortest known route to the nearest terminal cell (G).
Every random choice comes from one seeded generator, saved in :meth:`FrontierExplorer.state_dict`, so a resumed run
equals an uninterrupted one.

It learns nothing by gradient or table updates: :meth:`FrontierExplorer.store` writes the memory and
:meth:`FrontierExplorer.updates_due` is always 0, so a run's train.csv holds its header only. For evaluation,
:meth:`FrontierExplorer.greedy_q_values` gives ``Q(s, a) = gamma^d(s')`` on the env's 0/1 scale, ``d`` the fewest
known steps from ``s'`` to the goal (1 for the move into it), and 0 for an untried move or an ``s'`` without a known
route: the greedy policy walks the shortest known route, which is optimal once the memory holds a shortest path.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase

from ss_drl.envs.maze import Maze
from ss_drl.graph import breadth_first

UNTRIED = -1  # the memory's entry for a move not tried yet


class FrontierExplorer:
    """The frontier explorer (an :class:`~ss_drl.agents.Agent` whose :meth:`update` is never due).

    The loop must let it see each transition before its next action (``trainer.frames_per_batch`` at most
    ``env.num_envs``; the config validator checks it). With several env copies the memory is shared and each copy
    keeps its own planned route, replanned whenever the memory has grown since it was planned.

    Args:
        cfg: ``gamma``, the discount of the values :meth:`greedy_q_values` reports.
        maze: the maze (its size only: the explorer learns the walls by bumping into them).
        seed: seeds its generator (which untried move, which of the nearest frontier cells, which shortest route).
    """

    name = "frontier"

    def __init__(self, cfg, maze: Maze, seed: int = 0):
        self.maze = maze
        self.gamma = float(cfg.gamma)
        self.n_actions = maze.n_actions
        self.generator = torch.Generator().manual_seed(seed)
        self.epsilon = 0.0  # no epsilon-greedy exploration (the loop's schedule is not applied: no eps_* keys)
        self.updates = 0  # never updated
        self._reset_memory()
        self._routes: dict[int, tuple[int, list[tuple[int, int]]]] = {}  # copy -> (version, [(cell, action), ...])
        self._values: dict[int, tuple[int, torch.Tensor]] = {}  # goal -> (version, Q table) for greedy_q_values

    # --- memory ------------------------------------------------------------------------------------------------
    def _reset_memory(self) -> None:
        n = self.maze.n_states
        self.successor: list[list[int]] = [[UNTRIED] * self.n_actions for _ in range(n)]  # (s, a) -> s'
        self.forward: list[list[int]] = [[] for _ in range(n)]  # known cells one move from s (bumps aside)
        self.backward: list[list[int]] = [[] for _ in range(n)]  # known cells one move into s'
        self.into: list[list[tuple[int, int]]] = [[] for _ in range(n)]  # (s, a) known to lead into s' (s != s')
        self.terminal: set[int] = set()  # cells entered with terminated (G): no move to try from them
        self.frontier: set[int] = set()  # known non-terminal cells with an untried move
        self.version = 0  # grows with every new fact: a planned route or value table is current while it is equal

    def _learn(self, s: int, a: int, s2: int, terminated: bool) -> None:
        """Remember one transition."""
        if terminated and s2 not in self.terminal:
            self.terminal.add(s2)
            self.frontier.discard(s2)
            self.version += 1
        row = self.successor[s]
        if row[a] != UNTRIED:  # known already (the mazes are deterministic)
            return
        row[a] = s2
        self.version += 1
        if s2 != s:
            if s2 not in self.forward[s]:
                self.forward[s].append(s2)
                self.backward[s2].append(s)
            self.into[s2].append((s, a))
        if UNTRIED in row:
            self.frontier.add(s)
        else:
            self.frontier.discard(s)
        if s2 not in self.terminal and UNTRIED in self.successor[s2]:
            self.frontier.add(s2)

    def untried(self, cell: int) -> list[int]:
        """The moves not tried yet in ``cell``, in action order ([] in a terminal cell)."""
        if cell in self.terminal:
            return []
        return [a for a, s2 in enumerate(self.successor[cell]) if s2 == UNTRIED]

    # --- acting ------------------------------------------------------------------------------------------------
    def _choice(self, options: list):
        """One of ``options`` uniformly at random (no draw when there is one)."""
        if len(options) == 1:
            return options[0]
        return options[int(torch.randint(len(options), (1,), generator=self.generator))]

    def plan(self, cell: int, targets: set[int]) -> list[tuple[int, int]] | None:
        """A shortest known route from ``cell`` to the nearest of ``targets``, as its ``(cell, action)`` steps: the
        nearest targets tie at random, and so do the shortest routes to the chosen one. None if none is reachable."""
        if not targets:
            return None
        dist = [-1] * self.maze.n_states
        dist[cell] = 0
        breadth_first([cell], dist, self.forward)
        reached = [(dist[t], t) for t in targets if dist[t] >= 0]
        if not reached:
            return None
        nearest = min(reached)[0]
        x = self._choice(sorted(t for d, t in reached if d == nearest))
        route = []
        while x != cell:  # back along known moves, one level nearer to ``cell`` at each step
            step = self._choice(sorted((s, a) for s, a in self.into[x] if dist[s] == dist[x] - 1))
            route.append(step)
            x = step[0]
        route.reverse()
        return route

    def _act_one(self, copy: int, cell: int) -> int:
        moves = self.untried(cell)
        if moves:
            self._routes.pop(copy, None)
            return self._choice(moves)
        planned = self._routes.get(copy)
        if planned is None or planned[0] != self.version or not planned[1] or planned[1][0][0] != cell:
            route = self.plan(cell, self.frontier)
            if route is None:  # nothing left to explore from here: the shortest known route to G, if G is known
                route = self.plan(cell, self.terminal)
            if not route:  # no known way on (never in a maze whose G can be reached from S)
                self._routes.pop(copy, None)
                return int(torch.randint(self.n_actions, (1,), generator=self.generator))
            planned = (self.version, route)
            self._routes[copy] = planned
        return planned[1].pop(0)[1]

    def act(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        """Each copy's move (the goal is not used: the explorer knows nothing about where G is)."""
        cells = observation.reshape(-1).tolist()
        actions = [self._act_one(copy, cell) for copy, cell in enumerate(cells)]
        return torch.tensor(actions, dtype=torch.int64).reshape(observation.shape)

    # --- values for evaluation ---------------------------------------------------------------------------------
    def _value_table(self, goal: int) -> torch.Tensor:
        """(n_cells, A): ``gamma^d(s')`` along known moves, ``d`` the fewest known steps from ``s'`` to ``goal``."""
        cached = self._values.get(goal)
        if cached is not None and cached[0] == self.version:
            return cached[1]
        dist = [-1] * self.maze.n_states
        goal_states = self.maze.states_in(goal)
        for state in goal_states:  # the goal cell's states (in a maze, the goal cell itself)
            dist[state] = 0
        breadth_first(goal_states, dist, self.backward)  # backwards along known moves: the steps to the goal
        dist = np.asarray(dist + [-1], dtype=np.int64)  # index -1 (an untried move) reads the extra -1
        steps = dist[np.asarray(self.successor, dtype=np.int64)]
        values = np.where(steps >= 0, self.gamma ** steps.clip(min=0), 0.0)
        table = torch.from_numpy(values).to(torch.float32)
        self._values = {goal: (self.version, table)}
        return table

    def greedy_q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, 4): ``Q(s, a) = gamma^d(s')`` for each goal (B,) and state (n,), on the env's 0/1 scale: 1 for the
        move into the goal, 0 for an untried move or one into a cell with no known route to the goal."""
        index = states.reshape(-1)
        return torch.stack([self._value_table(int(g))[index] for g in goals.reshape(-1).tolist()])

    #: The memory is the only estimate: collection (Smart Start, were it on) would read the same values.
    q_values = greedy_q_values

    # --- the loop's learning steps: the memory is written at store, nothing is updated -------------------------
    def store(self, batch: TensorDictBase) -> None:
        """Remember every transition of a collected (T, N) batch, in the order they happened."""
        s = batch.get("observation").reshape(-1).tolist()
        a = batch.get("action").reshape(-1).tolist()
        s2 = batch.get(("next", "observation")).reshape(-1).tolist()
        term = batch.get(("next", "terminated")).reshape(-1).tolist()
        for transition in zip(s, a, s2, term):
            self._learn(*transition)

    def updates_due(self, env_steps: int, new_steps: int) -> int:
        """Never: the memory is written by :meth:`store`."""
        return 0

    def update(self) -> torch.Tensor:
        raise RuntimeError("the frontier explorer has no learning update (updates_due is always 0)")

    # --- checkpoints -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "successor": np.asarray(self.successor, dtype=np.int64),
            "terminal": sorted(self.terminal),
            "version": self.version,
            "routes": {copy: (version, list(route)) for copy, (version, route) in self._routes.items()},
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self._reset_memory()
        self.terminal = set(state["terminal"])
        for s, row in enumerate(state["successor"].tolist()):
            for a, s2 in enumerate(row):
                if s2 != UNTRIED:
                    self._learn(s, a, s2, terminated=False)  # the terminal cells are known already
        self.version = state["version"]
        self._routes = {copy: (version, list(route)) for copy, (version, route) in state["routes"].items()}
        self._values = {}
        self.generator.set_state(state["generator"])
