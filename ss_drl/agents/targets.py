"""The TD target of the goal-conditioned DQN, as named parts.

For a sampled transition (s_t, a_t, g) whose window runs m steps (``n_steps``, set by the HER buffer):

1. **Base target** (:class:`TDTarget`): ``y = R + gamma^m (1 - terminated) Q'(s_{t+m}, argmax_a Q(s_{t+m}, a))``,
   with R the learner's return over the window (:func:`learner_reward`: the env's 0/1 goal reward, one shared
   rule, minus ``step_cost`` per step) and the double-DQN bootstrap (the online network picks, the target network
   evaluates; with ``double_dqn`` off the target network's max).
2. **Bounds** (:class:`Bound`): each gives a lower and/or an upper bound on the taken action's value, and, where it
   can, on every action of s_t. The target is then ``clamp(y, max(lower bounds), min(upper bounds))``: no target
   below the largest lower bound, none above the smallest upper bound (if they cross, the upper wins), and last
   ``clamp(value_range)`` (``agent.clip_targets``: the values a policy can have), which wins over both. A bound's
   own value is computed inside the bound: the distance floor with ``optimistic_floor`` takes the ceiling's steps
   where it knows no route into G (:meth:`DistanceFloor.floor_steps`), so that its "lower bound" there is optimism,
   not a bound.
3. **The other actions** (:class:`ModelTargets`, and the all-action bounds): every action of s_t but the taken one
   is *held to* a value, the value its prediction is regressed toward: the one-step target through the successor
   the count model observed for it, or else its own (detached) prediction, clamped the same way into its all-action
   bounds and the value range. The loss adds each one's distance to that held value; where neither a model target
   nor a bound moves it, the held value is the prediction itself clamped into the value range, so that action adds
   nothing unless its prediction lies outside that range.

Entering G ends every episode, whatever goal the agent pursues. For a relabeled goal g other than G, a window that
ends there is not terminal (g was not reached), so its target bootstraps from Q'(G||g): no transition leaves G, so
no sample trains that value, and it is the network's extrapolation. Counting it as terminal instead would give G, in
the shortest-path form, the value of reaching every goal. This is a modelling choice, and every run so far made it.

That order is the only one, and it is written once, in :meth:`TDTarget.__call__` (steps 1-3, with every bootstrap
of the update in one call: one batched pass per network).

Each bound states what it assumes (:data:`ASSUMPTIONS`). A run turns off a bound whose assumption its environment
breaks, before training, with one line naming it (:func:`resolve_bounds`); a bound the user set explicitly is
refused instead.

The bounds (switches in :class:`~ss_drl.agents.settings.DQNSettings`):

========================  =====================  ==================================================================
bound                     gives                  assumes
========================  =====================  ==================================================================
``hindsight_bound``       lower, taken action    the stored episode, deterministic moves
``n_step_max``            lower, taken action    the stored episode, deterministic moves, and target-network
                                                 values that do not overestimate (it bootstraps from them: a
                                                 heuristic bound while they do)
``distance_floor``        lower, all actions*    the count model, deterministic moves (+ the ceiling's grid
                                                 with ``optimistic_floor``, which makes it the ceiling where no
                                                 route into G is known: optimism, not a bound)
``distance_ceiling``      upper, all actions*    the count model, deterministic moves, a grid with four moves
                                                 (mazes) or with turns and forward moves (MiniGrid)
``model_targets``         the other actions      the count model, deterministic moves
========================  =====================  ==================================================================

(*) on every action of s_t with ``bound_all_actions``; the taken action's only without.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import torch
from tensordict import TensorDictBase

from ss_drl.agents.settings import COUNT_MODEL_KEYS
from ss_drl.envs.maze import ACTIONS, Maze, goal_reward, state_cells
from ss_drl.graph import breadth_first

#: What a bound may assume about the environment, and what each assumption means.
ASSUMPTIONS = {
    "stored_episode": "the stored episode's own steps (nothing outside the replay buffer)",
    "deterministic": "deterministic moves: the same action from the same state always leads to the same state",
    "grid_four_moves": "the state is a grid cell and each of the four moves leads to its neighbour or stays",
    "grid_turns": "the state holds a grid cell and a direction; forward moves one cell that way or stays, left and "
    "right turn, the other actions keep cell and direction",
    "count_model": "the count model's observed transitions",
}

#: What a Keulen maze (``env.preset`` / ``env.layout``) offers: every assumption but MiniGrid's turns.
MAZE = frozenset(ASSUMPTIONS) - {"grid_turns"}
#: What a maze with stochastic moves (``env.slip > 0``) offers: everything but deterministic moves.
STOCHASTIC_MAZE = MAZE - {"deterministic"}
#: What a MiniGrid task (``env.id``) offers: deterministic moves with a fixed layout, and a state that holds a cell
#: and a direction (plus doors and a carried object) with turns and forward moves, not four moves.
MINIGRID = (MAZE - {"grid_four_moves"}) | {"grid_turns"}


def environment_assumptions(env_cfg) -> frozenset[str]:
    """The assumptions an ``env`` config node's environment meets: :data:`MINIGRID` for a MiniGrid task
    (``env.id``), else :data:`MAZE`, or :data:`STOCHASTIC_MAZE` when its moves slip (``env.slip > 0``)."""
    if env_cfg.get("id"):
        return MINIGRID
    return STOCHASTIC_MAZE if float(env_cfg.get("slip", 0) or 0) > 0 else MAZE


#: A bootstrap: (states, goals) -> (..., 1) the target network's value of the online network's greedy action; with
#: ``double_rows=n``, of the online network's greedy action for the first n rows and its own max for the others.
Bootstrap = Callable[..., torch.Tensor]


def discounted_steps(steps: torch.Tensor, gamma: float) -> torch.Tensor:
    """sum_{j<m} gamma^j for m = ``steps``: what a cost of 1 per step adds up to over m steps."""
    return steps if gamma == 1 else (1 - gamma**steps) / (1 - gamma)


def learner_reward(
    env_return: torch.Tensor, steps: torch.Tensor | None, gamma: float, step_cost: float
) -> torch.Tensor:
    """The learner's return over ``steps`` steps (None: one step) whose env return (the discounted sum of the 0/1
    goal rewards of :func:`~ss_drl.envs.maze.goal_reward`) is ``env_return``: ``step_cost`` is taken off every
    step, so with ``step_cost = 1`` and ``gamma = 1`` a step costs -1 and entering the goal 0 (the shortest-path
    form)."""
    if not step_cost:
        return env_return
    if steps is None:
        return env_return - step_cost
    return env_return - step_cost * discounted_steps(steps.to(torch.float32), gamma)


def path_value(steps: torch.Tensor, gamma: float, step_cost: float) -> torch.Tensor:
    """The learner's value of entering the goal on the k-th step, k = ``steps`` (k - 1 steps, then the goal):
    ``gamma^(k-1) - step_cost * sum_{j<k} gamma^j``, ``-(k - 1)`` in the shortest-path form; -inf where k = 0
    (no such path known). Every distance bound is this function of a step count."""
    k = steps.to(torch.float32)
    value = gamma ** (k - 1) - step_cost * discounted_steps(k, gamma)
    return torch.where(steps > 0, value, torch.full_like(value, -torch.inf))


@dataclasses.dataclass(frozen=True)
class Scale:
    """The learner's reward scale, shared by the base target and every bound."""

    gamma: float
    step_cost: float


# --- bounds -------------------------------------------------------------------------------------------------------
class Bound:
    """A bound on the TD target. Subclasses override what they give; ``None`` means "no bound of this kind".

    ``key`` is its switch in the agent settings; ``assumes`` what must hold of the environment (keys of
    :data:`ASSUMPTIONS`).
    """

    key: str = ""
    assumes: frozenset[str] = frozenset()

    def bootstrap_states(self, sample: TensorDictBase) -> torch.Tensor | None:
        """(B, k) extra states whose bootstrapped values :meth:`lower` needs, evaluated in the base target's own
        pass (None: none)."""
        return None

    def lower(self, sample: TensorDictBase, values: torch.Tensor | None) -> torch.Tensor | None:
        """(B, 1) a lower bound on the taken action's value (``values``: the bootstraps of
        :meth:`bootstrap_states`)."""
        return None

    def upper(self, sample: TensorDictBase) -> torch.Tensor | None:
        """(B, 1) an upper bound on the taken action's value."""
        return None

    def lower_all(self, sample: TensorDictBase) -> torch.Tensor | None:
        """(B, A) a lower bound on every action's value."""
        return None

    def upper_all(self, sample: TensorDictBase) -> torch.Tensor | None:
        """(B, A) an upper bound on every action's value."""
        return None


class HindsightBound(Bound):
    """He et al. 2017's lower bound from the stored path: a sample whose goal the stored episode reached k =
    ``goal_steps`` steps on (a relabeled goal achieved later, or G in an episode that entered it) has
    ``Q*(s_t, a_t||g) >= path_value(k)``, since the same k actions reach g again (``agent.hindsight_bound``)."""

    key = "hindsight_bound"
    assumes = frozenset({"stored_episode", "deterministic"})

    def __init__(self, scale: Scale):
        self.scale = scale

    def lower(self, sample, values):
        return path_value(sample.get("goal_steps"), self.scale.gamma, self.scale.step_cost)


class NStepMax(Bound):
    """The k-step maximum (``agent.n_step_max``): each k-step target of the sample's window, k = 1..m - 1 (no goal
    entered and no episode end before step m), is itself the return of a path the agent walked, bootstrapped, so
    in a deterministic maze it bounds the target from below as far as the target network's values are not too high
    (it bootstraps from them; where it crosses an upper bound, the upper wins); steps of the window that head away
    from the goal (a guided phase, an exploratory action) then no longer drag the target down."""

    key = "n_step_max"
    assumes = frozenset({"stored_episode", "deterministic"})

    def __init__(self, scale: Scale, n_step: int):
        self.scale = scale
        k = torch.arange(1, int(n_step), dtype=torch.float32)
        self.k = torch.arange(1, int(n_step))
        # The learner's return over the window's first k = 1..n-1 steps, none of which entered the goal.
        self.window_reward = -scale.step_cost * discounted_steps(k, scale.gamma)
        self.discount = scale.gamma ** self.k.to(torch.float32)

    def bootstrap_states(self, sample):
        window = sample.get("window_observation")
        return window[:, :-1] if window.shape[-1] >= 2 else None  # the states after k = 1..n-1 steps

    def lower(self, sample, values):
        if values is None:
            return None
        shorter = self.window_reward + self.discount * values
        shorter = torch.where(self.k < sample.get("n_steps"), shorter, torch.full_like(shorter, -torch.inf))
        return shorter.amax(-1, keepdim=True)


class _GoalDistance:
    """Steps to the real goal G per (s, a), kept in step with the count model, turned into a bound for the samples
    whose goal is G (other goals: no bound)."""

    def __init__(self, counts, goal: int, scale: Scale, all_actions: bool):
        self.counts, self.goal, self.scale, self.all_actions = counts, int(goal), scale, bool(all_actions)
        self._keys: torch.Tensor | None = None  # the key array the steps were computed from
        self._steps: torch.Tensor | None = None

    def steps(self) -> torch.Tensor:
        """(S * A,) float32, flat ``s * A + a``: the step count of the bound (0: none); cached until the count
        model sees a new transition."""
        keys = self.counts.keys
        if self._steps is None or keys is not self._keys:
            self._keys, self._steps = keys, self._compute()
        return self._steps

    def _compute(self) -> torch.Tensor:
        raise NotImplementedError

    def bound_for_g(self, sample: TensorDictBase, steps: torch.Tensor, other: float, all_actions: bool):
        """(B, 1) ``path_value`` of ``steps`` at (s_t, a_t) for samples whose goal is the real goal G (relabeled
        or not: the test is on the goal), ``other`` elsewhere; with ``all_actions``, (B, A) for every action of s_t."""
        obs = sample.get("observation")
        if all_actions:
            k = steps.view(-1, self.counts.n_actions)[obs]
        else:
            k = steps[obs * self.counts.n_actions + sample.get("action")]
        bound = path_value(k, self.scale.gamma, self.scale.step_cost).reshape(obs.shape[0], -1)
        real = (sample.get("desired_goal") == self.goal).reshape(-1, 1)
        return torch.where(real, bound, torch.full_like(bound, other))


class _Ceiling(_GoalDistance, Bound):
    """A distance ceiling: the steps to G in an optimistic world whose only walls are those the count model has
    seen, as an upper bound on the targets for G. A subclass gives the world (:meth:`known_walls`,
    :meth:`distances`) and the steps per (s, a) to a successor (:meth:`_per_action`)."""

    key = "distance_ceiling"
    _walls: np.ndarray | None = None
    _distance: np.ndarray | None = None

    def _observed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, a, s') of every transition the count model has seen, for :meth:`known_walls`."""
        n, a_n = self.counts.n_states, self.counts.n_actions
        keys = self.counts.keys.numpy()
        sa = keys // n
        return sa // a_n, sa % a_n, keys % n

    def _compute(self) -> torch.Tensor:
        walls = self.known_walls()
        if self._distance is None or not np.array_equal(walls, self._walls):  # a new wall: search again
            self._walls, self._distance = walls, self.distances(walls)
        return torch.from_numpy(1 + self._per_action(walls, self._distance)).to(torch.float32)

    def upper(self, sample):
        return self.bound_for_g(sample, self.steps(), torch.inf, all_actions=False)

    def upper_all(self, sample):
        return self.bound_for_g(sample, self.steps(), torch.inf, all_actions=True) if self.all_actions else None

    @classmethod
    def for_task(cls, counts, task, scale: Scale, all_actions: bool = False) -> _Ceiling:
        """The ceiling on ``task`` (a :class:`~ss_drl.envs.maze.Maze` or a MiniGrid task) with its count model."""
        return cls(counts, task, scale, all_actions)


class DistanceCeiling(_Ceiling):
    """The fewest steps to G the count model cannot rule out, as an upper bound on the targets for G
    (``agent.distance_ceiling``).

    In a grid maze a wall is a cell, and a move into it is seen as a bump: a tried (s, a) that stayed at s although
    the cell it points to lies inside the grid. The *optimistic maze* has as walls only the cells the count model
    has seen bumped into; every other cell, visited or not, is free. The true maze has more walls, so its distances
    are never shorter: d_opt(s, G) <= d(s, G). Per (s, a) the ceiling's steps are ``1 + d_opt(s')``, s' the observed
    successor of a tried (s, a), and for an untried one the nearer of its two possible successors (the neighbour,
    or s itself if the neighbour turns out to be a wall); their value bounds Q*(s, a||G) from above.
    """

    assumes = frozenset({"count_model", "deterministic", "grid_four_moves"})

    def __init__(self, counts, height: int, width: int, goal: int, scale: Scale, all_actions: bool = False):
        super().__init__(counts, goal, scale, all_actions)
        self.height, self.width = int(height), int(width)
        n = self.height * self.width
        if counts.n_states != n or counts.n_actions != len(ACTIONS):
            raise ValueError(f"count model has {counts.n_states} states x {counts.n_actions} actions, grid {n} x 4")
        rows, cols = np.divmod(np.arange(n), self.width)
        #: (S, A) the cell each move points to, -1 off the grid
        self.neighbour = np.full((n, len(ACTIONS)), -1, dtype=np.int64)
        for a, (dr, dc) in enumerate(ACTIONS):
            r, c = rows + dr, cols + dc
            inside = (r >= 0) & (r < self.height) & (c >= 0) & (c < self.width)
            self.neighbour[inside, a] = r[inside] * self.width + c[inside]

    @classmethod
    def for_task(cls, counts, task, scale: Scale, all_actions: bool = False) -> DistanceCeiling:
        return cls(counts, task.height, task.width, task.goal_cell, scale, all_actions)

    def known_walls(self) -> np.ndarray:
        """(S,) bool: cells the count model has seen a move bump into."""
        s, a, s2 = self._observed()
        target = self.neighbour[s, a]
        bumped = (s2 == s) & (target >= 0)
        walls = np.zeros(self.counts.n_states, dtype=bool)
        walls[target[bumped]] = True
        return walls

    def distances(self, walls: np.ndarray) -> np.ndarray:
        """(S,) steps from every cell to G in the maze whose only walls are ``walls``; a cell that cannot reach it
        gets S (more than any simple path). Moves are reversible in a grid, so the search runs from G."""
        n = walls.size
        blocked = walls.tolist()
        adjacency = [[y for y in row if y >= 0 and not blocked[y]] for row in self.neighbour.tolist()]
        dist = [-1] * n
        dist[self.goal] = 0
        breadth_first([self.goal], dist, adjacency)
        dist = np.asarray(dist, dtype=np.int64)
        dist[dist < 0] = n
        return dist

    def _per_action(self, walls: np.ndarray, dist: np.ndarray) -> np.ndarray:
        keys = self.counts.keys
        n, a_n = self.counts.n_states, self.counts.n_actions
        here = np.repeat(dist, a_n).reshape(n, a_n)  # s itself (a bump)
        target = self.neighbour
        there = np.where(target >= 0, dist[np.maximum(target, 0)], n)
        there = np.where((target >= 0) & walls[np.maximum(target, 0)], n, there)  # a known wall is no successor
        nearer = np.minimum(here, there).reshape(-1)  # untried (s, a): whichever successor it turns out to have
        known = keys.numpy()
        nearer[known // n] = dist[known % n]  # tried (s, a): the successor observed (one, in a deterministic maze)
        return nearer


class TurnDistanceCeiling(_Ceiling):
    """:class:`DistanceCeiling` for a MiniGrid task, whose agent turns and moves forward (``agent.distance_ceiling``).

    The *optimistic grid* relaxes the task: its states are (cell, direction) only, ``left`` and ``right`` turn,
    ``forward`` moves one cell the way the agent faces unless that cell is a known wall, and ``pickup`` and
    ``toggle`` move nothing; doors are open and objects gone. Every real transition is one of these moves (a real
    forward that stays is a move of the optimistic grid's kind ``stay``), so its distances are never longer than the
    true ones, whatever the doors and the carried object: d_opt(s, G) <= d(s, G). A wall is a cell that a tried
    forward was seen to stay in front of, unless a door or a key or ball stands there (those block a forward but can
    be opened or picked up). Per (s, a) the ceiling's steps are ``1 + d_opt(s')``, s' the observed successor of a
    tried (s, a); for an untried one the turned direction for a turn, s's own for ``pickup`` and ``toggle``, and
    for ``forward`` the nearer of the cell ahead and staying.
    """

    assumes = frozenset({"count_model", "deterministic", "grid_turns"})
    LEFT, RIGHT, FORWARD = 0, 1, 2
    #: (column, row) step of each MiniGrid direction: right, down, left, up
    DIRECTIONS = ((1, 0), (0, 1), (-1, 0), (0, -1))

    def __init__(self, counts, task, scale: Scale, all_actions: bool = False):
        super().__init__(counts, task.goal_cell, scale, all_actions)
        self.width = int(task.width)
        n_cells = int(task.height) * self.width
        features = np.asarray(task.features)
        #: (S,) each state's node of the optimistic grid: 4 * cell + direction
        self.node = features[:, 0] * 4 + features[:, 1]
        if counts.n_states != len(self.node) or counts.n_actions != 5:
            raise ValueError(
                f"count model has {counts.n_states} states x {counts.n_actions} actions, task {self.node.size} x 5"
            )
        rows, cols = np.divmod(np.arange(n_cells), self.width)
        #: (4 * cells, 5) the node each action leads to in the optimistic grid without walls; -1: forward off the grid
        self.move = np.empty((4 * n_cells, 5), dtype=np.int64)
        for d, (dx, dy) in enumerate(self.DIRECTIONS):
            nodes = 4 * np.arange(n_cells) + d
            r, c = rows + dy, cols + dx
            inside = (r >= 0) & (r < task.height) & (c >= 0) & (c < self.width)
            self.move[nodes, self.LEFT] = nodes - d + (d - 1) % 4
            self.move[nodes, self.RIGHT] = nodes - d + (d + 1) % 4
            self.move[nodes, self.FORWARD] = np.where(inside, 4 * (r * self.width + c) + d, -1)
            self.move[nodes, 3:] = nodes[:, None]
        #: cells that block a forward without being walls: doors, keys and balls
        self.openable = np.zeros(n_cells, dtype=bool)
        for _, (x, y) in (*task.doors, *task.pickables):
            self.openable[y * self.width + x] = True
        self.goal_nodes = 4 * int(task.goal_cell) + np.arange(4)

    def known_walls(self) -> np.ndarray:
        """(cells,) bool: cells a tried forward was seen to stay in front of (doors, keys and balls excepted)."""
        s, a, s2 = self._observed()
        ahead = self.move[self.node[s], self.FORWARD]
        bumped = (a == self.FORWARD) & (self.node[s2] == self.node[s]) & (ahead >= 0)
        walls = np.zeros(self.openable.size, dtype=bool)
        walls[ahead[bumped] // 4] = True
        walls &= ~self.openable
        return walls

    def distances(self, walls: np.ndarray) -> np.ndarray:
        """(nodes,) actions from every node to a node in G's cell in the optimistic grid whose only walls are
        ``walls``; a node that cannot reach one gets the node count (more than any simple path). The search runs
        backwards from G's nodes, on the moves' predecessor lists."""
        n_nodes = self.move.shape[0]
        into: list[list[int]] = [[] for _ in range(n_nodes)]
        blocked = walls.tolist()
        for u, row in enumerate(self.move[:, : self.FORWARD + 1].tolist()):
            for v in row:
                if v >= 0 and v != u and not blocked[v // 4]:
                    into[v].append(u)
        dist = [-1] * n_nodes
        for g in self.goal_nodes.tolist():
            dist[g] = 0
        breadth_first(self.goal_nodes.tolist(), dist, into)
        dist = np.asarray(dist, dtype=np.int64)
        dist[dist < 0] = n_nodes
        return dist

    def _per_action(self, walls: np.ndarray, dist: np.ndarray) -> np.ndarray:
        n = self.counts.n_states
        succ = self.move[self.node]  # (S, 5)
        steps = dist[np.maximum(succ, 0)]
        ahead = succ[:, self.FORWARD]
        ahead_open = (ahead >= 0) & ~walls[np.maximum(ahead, 0) // 4]
        there = np.where(ahead_open, steps[:, self.FORWARD], dist.size)
        steps[:, self.FORWARD] = np.minimum(dist[self.node], there)  # untried forward: the cell ahead, or staying
        nearer = steps.reshape(-1)
        known = self.counts.keys.numpy()
        nearer[known // n] = dist[self.node[known % n]]  # tried (s, a): the successor observed
        return nearer


class DistanceFloor(_GoalDistance, Bound):
    """The fewest steps to G along transitions the count model has observed, as a lower bound on the targets for G
    (``agent.distance_floor``): those steps are walked again by repeating their actions, so in a deterministic maze
    their value bounds Q*(s, a||G) from below (the hindsight bound with every stored episode stitched into one
    graph). Per tried (s, a) with observed successor s' the steps are ``1 + d_known(s')``; none where (s, a) is
    untried or s' has no observed route to G.

    With ``optimistic`` (``agent.optimistic_floor``) the floor where no observed route is known is the ceiling's
    value instead, so G's target there *is* the ceiling: optimism under the free-space assumption. Before the first
    goal the greedy policy for G heads for G through cells not yet known, and an untried action keeps that value
    until it is tried.
    """

    key = "distance_floor"
    assumes = frozenset({"count_model", "deterministic"})

    def __init__(
        self,
        counts,
        goal: int,
        scale: Scale,
        all_actions: bool = False,
        optimistic: DistanceCeiling | None = None,
        goal_states: Sequence[int] | None = None,
    ):
        super().__init__(counts, goal, scale, all_actions)
        # The states whose cell is G (a MiniGrid task has one per direction, door state and carried object): the
        # search starts from all of them. In a maze the goal cell is the one goal state.
        self.goal_states = [self.goal] if goal_states is None else [int(g) for g in goal_states]
        self.optimistic = optimistic
        if optimistic is not None:
            self.assumes = self.assumes | optimistic.assumes
        self._merged: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # (floor, ceiling, merged)

    def distances(self) -> np.ndarray:
        """(S,) d_known: the fewest observed transitions from each state into G; 0 at G, -1 where no observed route
        leads there. The search runs backwards from G's states on the count model's predecessor lists."""
        st = self.counts.structure()
        if not st.deterministic:
            raise ValueError(
                "agent.distance_floor needs a deterministic maze: some (s, a) was seen to lead to two cells"
            )
        into_state, preds = st.predecessors()
        n_v = st.states.numel()
        dist = [-1] * (n_v + 1)
        dist[n_v] = 0  # the dummy slot (unvisited cells) is never reached
        for goal in self.goal_states:
            slot = st.derived["slot"][goal]
            if slot < n_v:
                dist[slot] = 0  # the goal is terminal and normally never departed from, so it has no slot
        front = []
        for goal in self.goal_states:
            for y in into_state.get(goal, ()):
                if dist[y] < 0:
                    dist[y] = 1
                    front.append(y)
        breadth_first(front, dist, preds, n_v + 1)
        full = np.full(self.counts.n_states, -1, dtype=np.int64)
        full[st.states.numpy()] = dist[:n_v]
        full[self.goal_states] = 0
        return full

    def _compute(self) -> torch.Tensor:
        keys = self.counts.keys
        n = self.counts.n_states
        steps = np.zeros(n * self.counts.n_actions, dtype=np.int64)
        if keys.numel():
            dist = self.distances()
            known = keys.numpy()
            d = dist[known % n]
            steps[known[d >= 0] // n] = 1 + d[d >= 0]
        return torch.from_numpy(steps).to(torch.float32)

    def floor_steps(self) -> torch.Tensor:
        """:meth:`steps`, with the ceiling's where no route is known when ``optimistic``."""
        steps = self.steps()
        if self.optimistic is None:
            return steps
        ceiling, cached = self.optimistic.steps(), self._merged
        if cached is None or cached[0] is not steps or cached[1] is not ceiling:  # both cached until a new key
            self._merged = cached = (steps, ceiling, torch.where(steps > 0, steps, ceiling))
        return cached[2]

    def lower(self, sample, values):
        return self.bound_for_g(sample, self.floor_steps(), -torch.inf, all_actions=False)

    def lower_all(self, sample):
        return self.bound_for_g(sample, self.floor_steps(), -torch.inf, all_actions=True) if self.all_actions else None


# --- the other actions --------------------------------------------------------------------------------------------
class ModelTargets:
    """One-step targets for the actions not taken (``agent.model_targets``): every action of s_t that the count
    model has seen from s_t gets ``r - step_cost + gamma V'(s'||g)`` through the successor s' it observed, for the
    sample's goal (relabeled ones too; entering g ends). A bump (s' = s) is then held to one step's cost plus its
    own state's discounted value (in the shortest-path form: that value minus one), however rarely it was taken."""

    key = "model_targets"
    assumes = frozenset({"count_model", "deterministic"})

    def __init__(self, counts, scale: Scale, cells: Callable[[torch.Tensor], torch.Tensor] | None = None):
        self.counts, self.scale = counts, scale
        self.cells = cells  # a state's cell, to compare it with the goal (None: states are cells, as in a maze)

    def successors(self, sample: TensorDictBase) -> torch.Tensor:
        """(B, A) the successor the count model observed for each action of s_t; -1 for an untried one."""
        return self.counts.successors().view(-1, self.counts.n_actions)[sample.get("observation")]

    def __call__(
        self, sample: TensorDictBase, held: torch.Tensor, succ: torch.Tensor, values: torch.Tensor
    ) -> torch.Tensor:
        """(B, A) ``held`` with each action the count model has seen from s_t replaced by its one-step target;
        ``values`` (B, A): the bootstrapped values of the successors ``succ``."""
        reached = succ if self.cells is None else self.cells(succ.clamp(min=0))  # untried (-1) is masked below
        entered = goal_reward(reached, sample.get("desired_goal").reshape(-1, 1))
        reward = learner_reward(entered.to(torch.float32), None, self.scale.gamma, self.scale.step_cost)
        target = reward + self.scale.gamma * (~entered).to(values.dtype) * values
        return torch.where(succ >= 0, target, held)


# --- the target ---------------------------------------------------------------------------------------------------
def _clamp(x: torch.Tensor, lowers: list, uppers: list) -> torch.Tensor:
    """``x`` raised to the largest of ``lowers`` and then lowered to the smallest of ``uppers`` (``None`` entries:
    no bound): ``min(max(x, max lowers), min uppers)``, so where a lower and an upper bound cross the upper wins."""
    for low in lowers:
        if low is not None:
            x = torch.maximum(x, low)
    for high in uppers:
        if high is not None:
            x = torch.minimum(x, high)
    return x


class TDTarget:
    """The base target, clamped between the largest lower and the smallest upper bound, then clipped to
    ``value_range``; and what the other actions are held to (see the module's docstring).

    Every state whose value the target bootstraps (the state after the window, the bounds' extra states, the model
    targets' successors of the actions not taken) goes through one call of the bootstrap, so one batched pass of the
    target network and one of the online network (double DQN) per update. The taken action's successor is left out
    of it: what that action is held to is never used (the loss regresses it on the target), so its held entry is its
    prediction clamped into the bounds, as for an untried action. ``fused=False`` makes the model targets' successors
    a call of their own. Either change of the rows leaves the other rows' values the same numbers to float rounding (a
    matrix product's sums can round differently with the batch's size; on the development machine the runs came out
    the same bit for bit, docs/notebook, sessions 36 and 48).
    ``successor_double=False`` values the successors by the target network's own max, so that the online network's
    pass covers the window's states only (``agent.successor_double_dqn``).
    """

    def __init__(
        self,
        scale: Scale,
        bounds: Sequence[Bound] = (),
        model_targets: ModelTargets | None = None,
        value_range: tuple[float, float] | None = None,
        fused: bool = True,
        successor_double: bool = True,
    ):
        self.scale = scale
        self.successor_double = bool(successor_double)
        self.bounds = tuple(bounds)
        self.model_targets = model_targets
        self.value_range = value_range
        self.fused = bool(fused)
        self.bounds_all_actions = any(getattr(b, "all_actions", False) for b in self.bounds)

    @property
    def names(self) -> list[str]:
        """The switches of the bounds in force, in the order they are listed."""
        return [b.key for b in self.bounds] + ([self.model_targets.key] if self.model_targets is not None else [])

    @property
    def in_force(self) -> list[str]:
        """:attr:`names`, then the switches that shape those bounds: ``optimistic_floor`` (the floor takes the
        ceiling's steps where it knows no route: optimism) and ``bound_all_actions`` (the floor and ceiling hold every
        action of s_t). What ``summary.json`` lists as ``bounds_in_force``."""
        shaping = []
        if any(getattr(b, "optimistic", None) is not None for b in self.bounds):
            shaping.append("optimistic_floor")
        if self.bounds_all_actions:
            shaping.append("bound_all_actions")
        return self.names + shaping

    @property
    def holds_other_actions(self) -> bool:
        return self.model_targets is not None or self.bounds_all_actions

    def learner_return(self, sample: TensorDictBase) -> torch.Tensor:
        """(B, 1) the learner's return over the sample's m-step window."""
        return learner_reward(
            sample.get(("next", "reward")), sample.get("n_steps"), self.scale.gamma, self.scale.step_cost
        )

    def __call__(
        self, sample: TensorDictBase, q_all: torch.Tensor | None, bootstrap: Bootstrap
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(target, held)``: (B, 1) the taken action's target, and (B, A) what every action of s_t is held to (the
        taken one's entry, which the loss does not use, is its prediction clamped into the all-action bounds), or None
        when nothing holds the other actions or ``q_all`` (the online network's predictions for s_t) is None."""
        next_obs, next_goal = sample.get(("next", "observation")), sample.get(("next", "desired_goal"))
        extra = [(b, b.bootstrap_states(sample)) for b in self.bounds]
        extra = [(b, s) for b, s in extra if s is not None]
        # (B, 1 + k): the state after the window, then each bound's extra states, all for the sample's goal.
        states = torch.cat([next_obs.unsqueeze(1)] + [s for _, s in extra], dim=1)
        goals = next_goal.unsqueeze(1).expand_as(states)
        succ = None if self.model_targets is None else self.model_targets.successors(sample)
        if succ is None:
            values, succ_values = bootstrap(states.flatten(), goals.flatten()).view(states.shape), None
        else:
            # Only the actions not taken need their successors' values (the taken one's held entry is never used):
            # (B, A - 1) successors of the other actions, then scattered back into (B, A), the taken one left untried.
            action = sample.get("action").reshape(-1, 1)
            others = (action + torch.arange(1, succ.shape[-1])) % succ.shape[-1]
            other_succ = succ.gather(-1, others)
            succ_goals = sample.get("desired_goal").unsqueeze(1).expand_as(other_succ)
            if self.fused:
                both = (
                    torch.cat((states.flatten(), other_succ.clamp(min=0).flatten())),
                    torch.cat((goals.flatten(), succ_goals.flatten())),
                )
                out = bootstrap(*both) if self.successor_double else bootstrap(*both, double_rows=states.numel())
                values, other_values = out[: states.numel()].view(states.shape), out[states.numel() :]
            else:
                if not self.successor_double:
                    raise ValueError("successor_double=False needs the fused pass")
                values = bootstrap(states.flatten(), goals.flatten()).view(states.shape)
                other_values = bootstrap(other_succ.clamp(min=0).flatten(), succ_goals.flatten())
            succ_values = values.new_zeros(succ.shape).scatter_(-1, others, other_values.view(other_succ.shape))
            succ = succ.scatter(-1, action, -1)
        at, extra_values = 1, {}
        for b, s in extra:
            extra_values[id(b)] = values[:, at : at + s.shape[1]]
            at += s.shape[1]
        # 1. The base target.
        not_terminal = (~sample.get(("next", "terminated"))).to(values.dtype)
        discount = self.scale.gamma ** sample.get("n_steps").to(values.dtype)  # gamma^m after m steps
        target = self.learner_return(sample) + discount * not_terminal * values[:, :1]
        # 2. Between the largest lower and the smallest upper bound, then the value range.
        lowers = [b.lower(sample, extra_values.get(id(b))) for b in self.bounds]
        target = _clamp(target, lowers, [b.upper(sample) for b in self.bounds])
        if self.value_range is not None:
            target = target.clamp(*self.value_range)
        if q_all is None or not self.holds_other_actions:
            return target, None
        # 3. The other actions: the model target or the prediction, into the all-action bounds and the value range.
        held = q_all.detach()
        if self.model_targets is not None:
            held = self.model_targets(sample, held, succ, succ_values)
        return target, self.hold(sample, held)

    def hold(self, sample, q: torch.Tensor) -> torch.Tensor:
        """(B, A) ``q``, values of every action of the sample's states for its goals, clamped into the all-action
        bounds and then the value range (step 3's last part). ``sample``: any mapping with ``observation`` and
        ``desired_goal`` (B,). With ``agent.bounded_policy`` the learner's policy takes its greedy action from these
        held values (:meth:`~ss_drl.agents.dqn.DQNAgent.policy_q`)."""
        q = _clamp(q, [b.lower_all(sample) for b in self.bounds], [b.upper_all(sample) for b in self.bounds])
        return q if self.value_range is None else q.clamp(*self.value_range)

    def taken(self, sample: TensorDictBase, bootstrap: Bootstrap) -> torch.Tensor:
        """(B, 1) the target of the taken action a_t (the first part of :meth:`__call__`)."""
        return self(sample, None, bootstrap)[0]

    def others(self, sample: TensorDictBase, q_all: torch.Tensor, bootstrap: Bootstrap) -> torch.Tensor | None:
        """(B, A) what each action of s_t is held to (the second part of :meth:`__call__`)."""
        return self(sample, q_all, bootstrap)[1]


# --- building the target from the settings ------------------------------------------------------------------------


def ceiling_class(holds: frozenset[str]) -> type[_Ceiling]:
    """The distance ceiling of an environment that meets ``holds``: :class:`TurnDistanceCeiling` where the agent
    turns and moves forward (MiniGrid), else :class:`DistanceCeiling` (four moves)."""
    return TurnDistanceCeiling if "grid_turns" in holds else DistanceCeiling


def assumptions(settings, holds: frozenset[str] = MAZE) -> dict[str, frozenset[str]]:
    """Per switch that is on in ``settings`` (bounds and their modifiers), what it assumes, in an environment that
    meets ``holds`` (which picks the distance ceiling's kind)."""
    ceiling = ceiling_class(holds)
    out = {}
    if settings.hindsight_bound:
        out["hindsight_bound"] = HindsightBound.assumes
    if settings.n_step_max:
        out["n_step_max"] = NStepMax.assumes
    if settings.distance_floor:
        out["distance_floor"] = DistanceFloor.assumes
    if settings.distance_ceiling:
        out["distance_ceiling"] = ceiling.assumes
    if settings.model_targets:
        out["model_targets"] = ModelTargets.assumes
    if settings.optimistic_floor:
        out["optimistic_floor"] = DistanceFloor.assumes | ceiling.assumes
    all_actions = frozenset({"count_model", "deterministic"})  # what holding every action of s_t assumes
    if settings.bound_all_actions:
        out["bound_all_actions"] = all_actions
    if settings.bounded_policy:  # the policy reads those same all-action bounds
        out["bounded_policy"] = all_actions
    return out


def resolve_bounds(settings, holds: frozenset[str], explicit: Sequence[str] = ()):
    """The settings with every switch whose assumption the environment breaks turned off, and the line that says so
    (none when nothing is turned off). ``holds``: the assumptions the environment meets (:data:`MAZE` for a Keulen
    maze). ``explicit``: the agent keys the user set on the command line; such a switch is refused (``ValueError``)
    instead."""
    off, broken_all = {}, set()
    for key, needs in assumptions(settings, holds).items():
        broken = sorted(needs - holds)
        if not broken:
            continue
        if key in explicit:
            why = "; ".join(ASSUMPTIONS[b] for b in broken)
            raise ValueError(f"agent.{key}=true: this environment breaks what it assumes ({why})")
        off[key] = False
        broken_all.update(broken)
    if not off:
        return settings, []
    why = "; ".join(ASSUMPTIONS[b] for b in sorted(broken_all))
    line = f"turned off, since this environment breaks what they assume ({why}): " + ", ".join(
        f"agent.{key}" for key in off
    )
    return dataclasses.replace(settings, **off), [line]


def make_td_target(
    settings,
    maze: Maze,
    counts,
    value_range: tuple[float, float] | None,
    fused: bool = True,
    *,
    holds: frozenset[str],
) -> TDTarget:
    """The TD target that ``settings`` (a :class:`~ss_drl.agents.settings.DQNSettings`) names, on ``maze`` with its
    count model ``counts`` (read only by the bounds that need it); ``fused``: see :class:`TDTarget`. ``holds``: the
    assumptions the environment meets (:func:`environment_assumptions`), which pick the distance ceiling's kind as
    they do in :func:`assumptions`."""
    scale = Scale(float(settings.gamma), float(settings.step_cost))
    if counts is None and any(getattr(settings, k) for k in COUNT_MODEL_KEYS):
        raise ValueError("the count model's bounds need the count model (make_td_target(..., counts=...))")
    bounds: list[Bound] = []
    if settings.hindsight_bound:
        bounds.append(HindsightBound(scale))
    if settings.n_step_max:
        bounds.append(NStepMax(scale, settings.n_step))
    ceiling = None
    if settings.distance_ceiling:
        ceiling = ceiling_class(holds).for_task(counts, maze, scale, settings.bound_all_actions)
    cells = state_cells(maze)
    if settings.distance_floor:
        optimistic = ceiling if settings.optimistic_floor else None
        goal_states = maze.states_in(maze.goal_cell)
        bounds.append(DistanceFloor(counts, maze.goal_cell, scale, settings.bound_all_actions, optimistic, goal_states))
    if ceiling is not None:
        bounds.append(ceiling)
    model = ModelTargets(counts, scale, cells) if settings.model_targets else None
    return TDTarget(scale, bounds, model, value_range, fused, settings.successor_double_dqn)
