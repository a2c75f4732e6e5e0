"""MiniGrid tasks as discrete, fully observed worlds with a fixed layout (``pip install -e ".[minigrid]"``).

A :class:`MiniGridTask` is one MiniGrid environment (``env.id``) whose grid is built once from ``env.layout_seed``;
every reset puts the agent back in that same grid, because Smart Start's counts describe one environment.

**State.** The agent's cell, its direction, the state of each door (open, closed, locked) and the object it
carries. The actions are MiniGrid's minus ``drop`` and ``done`` (``left``, ``right``, ``forward``, ``pickup``,
``toggle``), so that this state is Markov: without ``drop`` an object once picked up is carried for good, and its
absence from the floor follows from the carried object.

**The state graph.** When the task is built, its reachable states are enumerated by breadth-first search from the
start, stepping MiniGrid's own ``step`` from each state (set through the agent's position and direction, the doors'
flags and the carried object) with every action. That gives the ids (0 is the start; numbered in the order the
search reaches them, so they are the same in every run and on every resume), the exact transition table
``next_state[s, a]``, and the optimum: the fewest actions from the start to the goal square. A task with more
reachable states than ``env.max_states`` is refused before training, in one line, never aliased. (The issue asked for
ids on first visit; the search knows the whole set before the first step, so ids are fixed from the start.)

**Goal and reward.** The goal is the goal square's cell (``row * width + col``), and a state's achieved goal is its
cell (:attr:`MiniGridTask.state_cell`). Reward 1 on entering the goal square, which ends the episode, as on the mazes.
MiniGrid's own return for an episode that reaches it in ``n`` steps is ``1 - 0.9 n / max_steps``
(:meth:`minigrid_return`).

**Supported tasks.** Any MiniGrid navigation task whose grid holds walls, floors, doors, keys, balls and exactly one
goal square (FourRooms, MultiRoom, DoorKey, ...). Lava, boxes and other objects change what a state must hold or how
an episode can end; such a task is refused in one line.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from collections import deque

import numpy as np
import torch

from ss_drl.graph import breadth_first

#: MiniGrid's action indices used here: left, right, forward, pickup, toggle (not drop 4, done 6).
ACTIONS = (0, 1, 2, 3, 5)
ACTION_NAMES = ("left", "right", "forward", "pickup", "toggle")
#: Object types the adapter supports; anything else in the grid refuses the task.
SUPPORTED_OBJECTS = ("wall", "floor", "door", "key", "ball", "goal")
#: Door state codes: 0 open, 1 closed, 2 locked.
DOOR_STATES = ("open", "closed", "locked")
#: The four experiments' tasks.
TASKS = {
    "fourrooms": "MiniGrid-FourRooms-v0",
    "multiroom_n4": "MiniGrid-MultiRoom-N4-S5-v0",
    "multiroom_n6": "MiniGrid-MultiRoom-N6-v0",
    "doorkey_8x8": "MiniGrid-DoorKey-8x8-v0",
}


class MiniGridError(ValueError):
    """A MiniGrid task that cannot be used; the message is one line naming the config key."""


def _import_minigrid():
    try:
        import minigrid  # noqa: F401  (registers the MiniGrid-* ids with gymnasium)
        from minigrid.minigrid_env import MiniGridEnv
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise MiniGridError('env.id: MiniGrid tasks need the minigrid extra: pip install -e ".[minigrid]"') from exc
    return MiniGridEnv


def make_minigrid(env_id: str):
    """The unwrapped MiniGrid env for ``env_id``, its own step limit out of the way (ours is ``env.max_steps``)."""
    import gymnasium as gym

    minigrid_env = _import_minigrid()
    if not isinstance(env_id, str) or env_id not in gym.registry:
        raise MiniGridError(f"env.id: unknown environment {env_id!r} (a MiniGrid id such as MiniGrid-FourRooms-v0)")
    try:
        with _needs_installed(env_id):
            env = gym.make(env_id, max_steps=2**62).unwrapped
    except TypeError as exc:
        raise MiniGridError(f"env.id: {env_id} is not a MiniGrid task ({exc})") from exc
    if not isinstance(env, minigrid_env):
        raise MiniGridError(f"env.id: {env_id} is not a MiniGrid task")
    return env


@contextlib.contextmanager
def _needs_installed(env_id: str):
    """A package that a task needs when it is made or its grid generated (the WFC tasks' imageio) is missing: one
    line naming it, not gymnasium's traceback."""
    import gymnasium as gym

    try:
        yield
    except gym.error.DependencyNotInstalled as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise MiniGridError(f"env.id: {env_id} needs a package that is not installed: {reason}") from exc


@dataclasses.dataclass(frozen=True)
class StateKey:
    """One discrete state: (col, row) of the agent, its direction, each door's code, the carried object (0 none,
    else 1 + its index among the grid's keys and balls)."""

    x: int
    y: int
    direction: int
    doors: tuple[int, ...]
    carrying: int


class MiniGridTask:
    """A MiniGrid task with a fixed layout, as a discrete world: states, a transition table, a goal cell.

    It offers what the trainer reads from a :class:`~ss_drl.envs.maze.Maze` (``n_states``, ``n_actions``,
    ``start_state``, ``goal_cell``, ``state_cell``, ``transition_table()``, ``distances_to_goal()``, the grid's
    ``height``, ``width`` and ``walls`` for figures), plus the per-state features of the network's state encoder.

    Args:
        env_id: a MiniGrid id (``MiniGrid-FourRooms-v0``).
        layout_seed: the seed of the grid (``env.layout_seed``).
        max_states: the most reachable states accepted (``env.max_states``).
    """

    def __init__(self, env_id: str, layout_seed: int = 0, max_states: int = 100_000):
        self.env_id, self.layout_seed, self.max_states = env_id, int(layout_seed), int(max_states)
        env = self.env = make_minigrid(env_id)
        with _needs_installed(env_id):
            env.reset(seed=self.layout_seed)
        env.gen_obs = _no_observation  # the enumeration steps millions of times; the egocentric view is not used
        self.height, self.width = int(env.height), int(env.width)
        # The task's name (summary.json's "maze", which plot.py groups by): the id, so that a task's layout seeds,
        # which are its run seeds, are one group; the layout seed is in the resolved config.
        self.name = env_id
        self.doors: list[tuple[object, tuple[int, int]]] = []
        self.pickables: list[tuple[object, tuple[int, int]]] = []
        self.walls = np.zeros((self.height, self.width), dtype=bool)
        goals = []
        for y in range(self.height):
            for x in range(self.width):
                obj = env.grid.get(x, y)
                if obj is None:
                    continue
                if obj.type not in SUPPORTED_OBJECTS:
                    raise MiniGridError(
                        f"env.id: {env_id} holds a {obj.type} at column {x}, row {y}: the adapter supports "
                        f"{', '.join(SUPPORTED_OBJECTS[:-1])} and one goal"
                    )
                if obj.type == "wall":
                    self.walls[y, x] = True
                elif obj.type == "door":
                    self.doors.append((obj, (x, y)))
                elif obj.type in ("key", "ball"):
                    self.pickables.append((obj, (x, y)))
                elif obj.type == "goal":
                    goals.append((y, x))
        if len(goals) != 1:
            raise MiniGridError(f"env.id: {env_id} has {len(goals)} goal squares; the adapter needs exactly one")
        if env.carrying is not None:
            raise MiniGridError(f"env.id: {env_id} starts with a carried object; the adapter does not support that")
        self.goal = goals[0]
        self.goal_cell = self.goal[0] * self.width + self.goal[1]
        start = self._key()
        self.start = (start.y, start.x)
        self._enumerate(start)

    # --- the state graph ---------------------------------------------------------------------------------------
    def _key(self) -> StateKey:
        env = self.env
        doors = tuple(0 if d.is_open else (2 if d.is_locked else 1) for d, _ in self.doors)
        carrying = 0
        if env.carrying is not None:
            carrying = 1 + next(i for i, (o, _) in enumerate(self.pickables) if o is env.carrying)
        return StateKey(int(env.agent_pos[0]), int(env.agent_pos[1]), int(env.agent_dir), doors, carrying)

    def _set(self, key: StateKey) -> None:
        """Put MiniGrid's env into state ``key``."""
        env = self.env
        env.agent_pos = (key.x, key.y)
        env.agent_dir = key.direction
        for (door, _), code in zip(self.doors, key.doors):
            door.is_open, door.is_locked = code == 0, code == 2
        for i, (obj, (x, y)) in enumerate(self.pickables):
            if key.carrying == i + 1:
                env.grid.set(x, y, None)
                obj.cur_pos = np.array([-1, -1])
            else:
                env.grid.set(x, y, obj)
                obj.cur_pos = np.array([x, y])
        env.carrying = self.pickables[key.carrying - 1][0] if key.carrying else None
        env.step_count = 0

    def _enumerate(self, start: StateKey) -> None:
        """Breadth-first search over the true state graph from ``start`` with MiniGrid's own step function."""
        ids = {start: 0}
        keys = [start]
        table: list[list[int]] = []
        queue = deque([start])
        while queue:
            key = queue.popleft()
            row = []
            if (key.y, key.x) == self.goal:  # terminal: never stepped from
                table.append([ids[key]] * len(ACTIONS))
                continue
            for action in ACTIONS:
                self._set(key)
                _, _, terminated, _, _ = self.env.step(action)
                nxt = self._key()
                if terminated and (nxt.y, nxt.x) != self.goal:
                    raise MiniGridError(f"env.id: {self.env_id} ends episodes off the goal square; not supported")
                if nxt not in ids:
                    if len(keys) >= self.max_states:
                        raise MiniGridError(
                            f"env.max_states: {self.name} layout {self.layout_seed} has more than {self.max_states} "
                            "reachable states; raise env.max_states"
                        )
                    ids[nxt] = len(keys)
                    keys.append(nxt)
                    queue.append(nxt)
                row.append(ids[nxt])
            table.append(row)
        self._set(start)
        self.keys = keys
        self.ids = ids
        self._table = np.asarray(table, dtype=np.int64)
        self._distances: np.ndarray | None = None
        self.state_cell = np.array([k.y * self.width + k.x for k in keys], dtype=np.int64)
        self._state_cell = torch.from_numpy(self.state_cell)
        n_doors = len(self.doors)
        # Features of the state encoder: cell, direction, carried object, then each door's code.
        self.features = np.zeros((len(keys), 3 + n_doors), dtype=np.int64)
        self.features[:, 0] = self.state_cell
        self.features[:, 1] = [k.direction for k in keys]
        self.features[:, 2] = [k.carrying for k in keys]
        if n_doors:
            self.features[:, 3:] = np.array([k.doors for k in keys], dtype=np.int64)

    # --- what the trainer reads --------------------------------------------------------------------------------
    @property
    def n_states(self) -> int:
        return len(self.keys)

    @property
    def n_actions(self) -> int:
        return len(ACTIONS)

    @property
    def n_cells(self) -> int:
        return self.height * self.width

    start_state = 0

    @property
    def n_doors(self) -> int:
        return len(self.doors)

    @property
    def n_pickables(self) -> int:
        return len(self.pickables)

    def cells(self, states: torch.Tensor) -> torch.Tensor:
        """The cell of each state (its achieved goal), where a state is compared with a goal."""
        return self._state_cell[states]

    def states_in(self, cell: int) -> list[int]:
        """The states whose cell is ``cell`` (one per direction, door state and carried object that reach it)."""
        return np.flatnonzero(self.state_cell == int(cell)).tolist()

    def transition_table(self) -> np.ndarray:
        """int64 (n_states, 5): the next state of every state and action (the goal's states loop on themselves)."""
        return self._table

    def distances_to_goal(self) -> np.ndarray:
        """(n_states,) fewest actions from each state to the goal square (-1 where it cannot be reached); computed
        once (every evaluation's greedy accuracy reads it)."""
        if self._distances is None:
            self._distances = self._search_back_from_goal()
            self._distances.setflags(write=False)
        return self._distances

    def _search_back_from_goal(self) -> np.ndarray:
        n = self.n_states
        into: list[list[int]] = [[] for _ in range(n)]
        for s, row in enumerate(self._table.tolist()):
            for t in set(row):
                if t != s:
                    into[t].append(s)
        dist = [-1] * n
        front = self.states_in(self.goal_cell)
        for s in front:
            dist[s] = 0
        breadth_first(front, dist, into)
        return np.asarray(dist, dtype=np.int64)

    @property
    def shortest_path_length(self) -> int:
        """The optimum: fewest actions from the start to the goal square."""
        return int(self.distances_to_goal()[self.start_state])

    def pos(self, state: int) -> tuple[int, int]:
        """(row, col) of a state's cell."""
        return divmod(int(self.state_cell[int(state)]), self.width)

    def label(self, state: int) -> str:
        """A state as episodes.csv writes it: ``row:col:direction`` (doors and carried object left out)."""
        key = self.keys[int(state)]
        return f"{key.y}:{key.x}:{key.direction}"

    @staticmethod
    def minigrid_return(success: bool, length: int, max_steps: int) -> float:
        """MiniGrid's own return of an episode (its ``_reward``): ``1 - 0.9 length / max_steps`` on reaching the
        goal, 0 otherwise."""
        return 1.0 - 0.9 * (length / max_steps) if success else 0.0

    def frame(self, state: int = 0, tile_size: int = 32) -> np.ndarray:
        """uint8 RGB image of the fully observed grid with the agent in ``state``."""
        self._set(self.keys[int(state)])
        image = self.env.grid.render(tile_size, self.env.agent_pos, self.env.agent_dir)
        self._set(self.keys[0])
        return image

    def __repr__(self) -> str:
        size = f"{self.height}x{self.width}"
        return f"MiniGridTask({self.name!r}, layout {self.layout_seed}, {size}, {self.n_states} states)"


@functools.lru_cache(maxsize=2)
def minigrid_task(env_id: str, layout_seed: int = 0, max_states: int = 100_000) -> MiniGridTask:
    """The :class:`MiniGridTask` of (id, layout seed, cap), built once per process: the config check, which builds
    the task to refuse an unsupported one before the run, and the trainer then share one state-graph search (on a
    large task such as LockedRoom, over 100k states, each search takes seconds). A refused task is not kept."""
    return MiniGridTask(env_id, int(layout_seed), int(max_states))


def _no_observation():
    return {}
