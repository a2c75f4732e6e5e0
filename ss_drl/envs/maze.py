"""Maze layouts: parsing, validation, shortest paths and random generation.

A maze is a grid of cells, row 0 at the top. ``#`` is a wall, ``.`` a free cell, ``S`` the start and ``G`` the goal.
There is no outer border: a move off the grid, like a move into a wall, leaves the agent where it is.

Cells are also addressed by a flat index ``row * width + col``; the environments, the count model and the Q-network
all speak in these indices.
"""

from __future__ import annotations

import dataclasses
from importlib import resources
from pathlib import Path

import numpy as np

from ss_drl.graph import breadth_first

WALL, FREE, START, GOAL = "#", ".", "S", "G"

#: Action ``a`` moves by ``ACTIONS[a]`` = (d_row, d_col): 0 right, 1 down, 2 left, 3 up (Keulen's order).
ACTIONS: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (0, -1), (-1, 0))


def action_probabilities(slip: float) -> np.ndarray:
    """(A, A): row a holds the probability that each action is taken when a is chosen, under ``env.slip``: with
    probability ``slip`` the action is replaced by one of the four drawn uniformly, so ``(1 - slip) [a == b] +
    slip / 4``. With the transition table, ``P(s' | s, a) = sum_b p[a, b] [table[s, b] == s']``."""
    n = len(ACTIONS)
    return (1.0 - slip) * np.eye(n) + slip / n


def goal_reward(achieved, goal):
    """The reward rule, written once: 1 for entering the goal, 0 otherwise (a bool tensor, or bool, of where
    ``achieved == goal``; callers cast). The env's reward for G, HER's reward for a relabeled goal and the count
    model's one-step targets all use it."""
    return achieved == goal


def state_cells(world):
    """``world.cells`` (a state's cell, its achieved goal) where states are not cells (a MiniGrid task); None in a
    maze, whose states are its cells, so that maze code paths stay as they are."""
    return None if isinstance(world, Maze) else world.cells


#: Preset name -> file shipped in ``ss_drl/mazes``.
PRESETS = ("easy", "medium", "hard", "extreme", "easy_small", "medium_small", "hard_small")


class MazeError(ValueError):
    """A maze layout that cannot be used. The message names the source and, where it applies, line and column."""


@dataclasses.dataclass(frozen=True, eq=False)
class Maze:
    """An immutable maze layout.

    Attributes:
        walls: bool array of shape (height, width), True where a cell is a wall.
        start: (row, col) of S.
        goal: (row, col) of G.
        name: where the layout came from (a preset name, a file path or ``random(...)``).
    """

    walls: np.ndarray
    start: tuple[int, int]
    goal: tuple[int, int]
    name: str = "maze"

    @property
    def height(self) -> int:
        return int(self.walls.shape[0])

    @property
    def width(self) -> int:
        return int(self.walls.shape[1])

    @property
    def n_cells(self) -> int:
        return self.height * self.width

    @property
    def n_free(self) -> int:
        return int((~self.walls).sum())

    def cell(self, pos: tuple[int, int]) -> int:
        """Flat index of a (row, col) position."""
        return int(pos[0]) * self.width + int(pos[1])

    def pos(self, cell: int) -> tuple[int, int]:
        """(row, col) of a flat cell index."""
        return divmod(int(cell), self.width)

    @property
    def start_cell(self) -> int:
        return self.cell(self.start)

    # --- the world interface (shared with :class:`ss_drl.envs.minigrid.MiniGridTask`): a maze's states are its cells
    @property
    def n_states(self) -> int:
        """Discrete states: every cell, walls included (flat index ``row * width + col``)."""
        return self.n_cells

    @property
    def n_actions(self) -> int:
        return len(ACTIONS)

    @property
    def start_state(self) -> int:
        return self.start_cell

    def cells(self, states):
        """The cell of each state (its achieved goal): the state itself in a maze."""
        return states

    def states_in(self, cell: int) -> list[int]:
        """The states whose cell is ``cell``: the cell itself in a maze."""
        return [int(cell)]

    def label(self, state: int) -> str:
        """A state as episodes.csv writes it: ``row:col``."""
        return "{}:{}".format(*self.pos(state))

    def distances_to_goal(self) -> np.ndarray:
        """(n_states,) steps from each cell to G (-1: wall or unreachable); moves are reversible, so the BFS from G."""
        return self.distances_from(self.goal).reshape(-1)

    @property
    def goal_cell(self) -> int:
        return self.cell(self.goal)

    def move(self, pos: tuple[int, int], action: int) -> tuple[int, int]:
        """The position after taking ``action`` in ``pos``: a bump into a wall or off the grid stays put."""
        dr, dc = ACTIONS[int(action)]
        r, c = pos[0] + dr, pos[1] + dc
        if 0 <= r < self.height and 0 <= c < self.width and not self.walls[r, c]:
            return (r, c)
        return (int(pos[0]), int(pos[1]))

    def transition_table(self) -> np.ndarray:
        """int64 array (n_cells, 4): the next cell for every cell and action, computed with array shifts."""
        h, w = self.walls.shape
        rows, cols = np.divmod(np.arange(h * w), w)
        table = np.empty((h * w, len(ACTIONS)), dtype=np.int64)
        for a, (dr, dc) in enumerate(ACTIONS):
            r, c = rows + dr, cols + dc
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            r_in, c_in = np.where(inside, r, 0), np.where(inside, c, 0)
            ok = inside & ~self.walls[r_in, c_in]
            table[:, a] = np.where(ok, r_in * w + c_in, rows * w + cols)
        return table

    def distances_from(self, pos: tuple[int, int]) -> np.ndarray:
        """BFS distances (in steps) from ``pos`` to every cell; -1 for walls and unreachable cells."""
        dist = [-1] * self.n_cells
        start = self.cell(pos)
        dist[start] = 0
        breadth_first([start], dist, self.transition_table().tolist())
        return np.asarray(dist, dtype=np.int64).reshape(self.walls.shape)

    @property
    def shortest_path_length(self) -> int:
        """Steps on a shortest path from S to G (the optimal episode length)."""
        return int(self.distances_from(self.start)[self.goal])

    def expected_steps(
        self, slip: float, tol: float = 1e-9, max_sweeps: int = 1_000_000
    ) -> tuple[np.ndarray, np.ndarray]:
        """The optimal policy under ``env.slip`` and its expected steps to G, by value iteration on the true model.

        ``V(G) = 0`` and ``V(s) = 1 + min_a sum_b p[a, b] V(table[s, b])`` (:func:`action_probabilities`), swept
        from ``V = 0`` (Jacobi) until the largest change is below ``tol``. Returns ``(V, policy)``: float64
        ``(n_cells,)`` expected steps (``inf`` where G cannot be reached, walls included) and int64 ``(n_cells,)``
        greedy actions (lowest index on ties). With ``slip == 0`` V is the BFS distance to G.
        """
        table = self.transition_table()
        p = action_probabilities(slip)
        goal = self.goal_cell
        reach = self.distances_from(self.goal).reshape(-1) >= 0  # moves are reversible: reaches G iff G reaches it
        v = np.zeros(self.n_cells)
        for _ in range(max_sweeps):
            q = 1.0 + v[table] @ p.T  # (n_cells, A): q[s, a] = 1 + sum_b p[a, b] v[table[s, b]]
            new = np.where(reach, q.min(axis=1), 0.0)
            new[goal] = 0.0
            delta = float(np.abs(new - v).max())
            v = new
            if delta < tol:
                break
        else:
            raise RuntimeError(f"expected_steps: value iteration did not converge in {max_sweeps} sweeps")
        q = 1.0 + v[table] @ p.T
        policy = q.argmin(axis=1)
        return np.where(reach, v, np.inf), policy

    def to_text(self) -> str:
        chars = np.where(self.walls, WALL, FREE).astype("<U1")
        chars[self.start] = START
        chars[self.goal] = GOAL
        return "\n".join("".join(row) for row in chars) + "\n"

    def __repr__(self) -> str:
        return f"Maze({self.name!r}, {self.height}x{self.width}, start={self.start}, goal={self.goal})"


def parse_maze(text: str, source: str = "<string>") -> Maze:
    """Parse a maze from its text form; raise :class:`MazeError` naming ``source``, line and column on bad input."""
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise MazeError(f"{source}: the maze file is empty")
    width = len(lines[0])
    starts, goals = [], []
    for i, line in enumerate(lines):
        if len(line) != width:
            raise MazeError(
                f"{source}:{i + 1}:{min(len(line), width) + 1}: ragged rows: line {i + 1} has {len(line)} "
                f"characters, line 1 has {width}"
            )
        for j, ch in enumerate(line):
            if ch not in (WALL, FREE, START, GOAL):
                raise MazeError(f"{source}:{i + 1}:{j + 1}: unknown character {ch!r} (allowed: '#', '.', 'S', 'G')")
            if ch == START:
                starts.append((i, j))
            elif ch == GOAL:
                goals.append((i, j))
    for symbol, found, what in ((START, starts, "start"), (GOAL, goals, "goal")):
        if not found:
            raise MazeError(f"{source}: no {what} cell {symbol!r} in the maze")
        if len(found) > 1:
            (r, c) = found[1]
            raise MazeError(
                f"{source}:{r + 1}:{c + 1}: more than one {what} cell {symbol!r} (the first is at line "
                f"{found[0][0] + 1}, column {found[0][1] + 1})"
            )
    walls = np.array([[ch == WALL for ch in line] for line in lines], dtype=bool)
    maze = Maze(walls=walls, start=starts[0], goal=goals[0], name=source)
    if maze.distances_from(maze.start)[maze.goal] < 0:
        r, c = maze.goal
        raise MazeError(f"{source}:{r + 1}:{c + 1}: the goal 'G' is unreachable from the start 'S'")
    return maze


def preset_path(name: str) -> Path:
    """Path of a shipped preset maze file."""
    if name not in PRESETS:
        raise MazeError(f"unknown maze preset {name!r} (allowed: {', '.join(PRESETS)})")
    return Path(str(resources.files("ss_drl") / "mazes" / f"{name}.txt"))


def load_maze(path_or_preset: str | Path) -> Maze:
    """Load a preset by name (``"easy"``) or a maze file by path."""
    key = str(path_or_preset)
    if key in PRESETS:
        return dataclasses.replace(parse_maze(preset_path(key).read_text(), source=key), name=key)
    path = Path(key).expanduser()
    if not path.is_file():
        raise MazeError(f"{key}: maze file not found (nor a preset: {', '.join(PRESETS)})")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise MazeError(f"{key}: cannot read the maze file ({exc})") from exc
    return parse_maze(text, source=key)


#: ``random_maze``'s S/G placements: ``"longest"`` (S and G far apart) and ``"misleading"`` (G near S as the crow
#: flies, far along the corridors).
PLACEMENTS = ("longest", "misleading")


def random_maze(
    height: int,
    width: int,
    scale: int = 1,
    seed: int | None = None,
    *,
    placement: str = "longest",
    radius: int = 6,
    path_range: tuple[int, int] = (150, 250),
) -> Maze:
    """A random perfect maze by a seeded recursive backtracker, with S and G placed by ``placement``.

    Args:
        height, width: size of the *layout* in cells before scaling (each layout cell is a room or a wall).
        scale: corridor width: each layout cell becomes a ``scale x scale`` block, as in Keulen's presets.
        seed: RNG seed; the same seed gives the same maze. The walls depend only on the seed (and the sizes), never
            on ``placement``.
        placement: ``"longest"`` (the default) or ``"misleading"``, below.
        radius, path_range: the ``"misleading"`` placement's Manhattan radius and inclusive range of S-G path lengths
            (ignored by ``"longest"``).

    ``placement="longest"``: S and G come from two BFS sweeps of the final (scaled) grid: S is a free cell farthest
    from the top-left cell (0, 0), which is always free, and G is a free cell farthest from S. For ``scale == 1``
    the free cells form a tree, on which two sweeps find the two ends of a longest shortest path exactly (the S-G
    distance is the maze's diameter). For ``scale > 1`` the corridors are ``scale`` cells wide and the grid has
    cycles, so the sweeps carry no such guarantee: G is a farthest cell from S, and the S-G distance is close to the
    diameter (equal to it on the small mazes checked).

    ``placement="misleading"``: G lies near S as the crow flies but far from it along the corridors. After the walls,
    the same RNG draws a random order of all free cells of the final grid (``rng.permutation`` of their flat indices,
    ascending; so S is drawn again without repeats). For each S in that order, G is the free cell other than S within
    Manhattan distance ``radius`` of S that is farthest from S by BFS along the maze (ties: the lowest flat index);
    the first S whose S-G path length lies within ``path_range`` (inclusive) is kept. When no free cell qualifies,
    :class:`MazeError` (a ``ValueError``) says so.
    """
    if height < 3 or width < 3:
        raise MazeError(f"random maze: height and width must be >= 3 (got {height}x{width})")
    if scale < 1:
        raise MazeError(f"random maze: scale must be >= 1 (got {scale})")
    if placement not in PLACEMENTS:
        raise MazeError(f"random maze: unknown placement {placement!r} (allowed: {', '.join(PLACEMENTS)})")
    if placement == "misleading":
        if radius < 1:
            raise MazeError(f"random maze: radius must be >= 1 (got {radius})")
        if len(path_range) != 2 or not 1 <= path_range[0] <= path_range[1]:
            raise MazeError(f"random maze: path_range must be (low, high) with 1 <= low <= high (got {path_range})")
    rng = np.random.default_rng(seed)
    walls = np.ones((height, width), dtype=bool)
    rooms_r, rooms_c = (height + 1) // 2, (width + 1) // 2
    visited = np.zeros((rooms_r, rooms_c), dtype=bool)
    stack = [(int(rng.integers(rooms_r)), int(rng.integers(rooms_c)))]
    visited[stack[0]] = True
    walls[2 * stack[0][0], 2 * stack[0][1]] = False
    while stack:
        r, c = stack[-1]
        options = [
            (r + dr, c + dc)
            for dr, dc in ACTIONS
            if 0 <= r + dr < rooms_r and 0 <= c + dc < rooms_c and not visited[r + dr, c + dc]
        ]
        if not options:
            stack.pop()
            continue
        nr, nc = options[int(rng.integers(len(options)))]
        visited[nr, nc] = True
        walls[r + nr, c + nc] = False  # the wall between (2r, 2c) and (2nr, 2nc)
        walls[2 * nr, 2 * nc] = False
        stack.append((nr, nc))
    walls = np.kron(walls, np.ones((scale, scale), dtype=bool)).astype(bool)
    free = Maze(walls=walls, start=(0, 0), goal=(0, 0))
    name = f"random({height}x{width},scale={scale},seed={seed})"
    if placement == "misleading":
        start, goal = _misleading_placement(free, rng, radius, (int(path_range[0]), int(path_range[1])))
        return Maze(walls=walls, start=start, goal=goal, name=f"{name[:-1]},placement=misleading)")
    # Two BFS passes give (approximately, exactly on a tree) the two ends of the longest shortest path.
    a = np.unravel_index(np.argmax(free.distances_from((0, 0))), walls.shape)
    dist_a = free.distances_from(a)
    b = np.unravel_index(np.argmax(dist_a), walls.shape)
    start = (int(a[0]), int(a[1]))
    goal = (int(b[0]), int(b[1]))
    return Maze(walls=walls, start=start, goal=goal, name=name)


def _misleading_goal(maze: Maze, start: tuple[int, int], radius: int) -> tuple[tuple[int, int], int] | None:
    """The ``"misleading"`` placement's G for a given S: among the free cells other than ``start`` within Manhattan
    distance ``radius`` of it, the one farthest from ``start`` along the maze (BFS by :meth:`Maze.distances_from`;
    ties go to the lowest flat index). Returns (G, its path length), or None when no such cell is reachable."""
    dist = maze.distances_from(start)
    rows, cols = np.indices(dist.shape)
    near = (np.abs(rows - start[0]) + np.abs(cols - start[1]) <= radius) & (dist > 0)
    if not near.any():
        return None
    masked = np.where(near, dist, -1).ravel()
    cell = int(np.argmax(masked))  # the first maximum: the lowest flat index among ties
    return maze.pos(cell), int(masked[cell])


def _misleading_placement(
    maze: Maze, rng: np.random.Generator, radius: int, path_range: tuple[int, int]
) -> tuple[tuple[int, int], tuple[int, int]]:
    """S and G of ``random_maze``'s ``"misleading"`` placement on ``maze``'s walls, drawing S with ``rng``."""
    lo, hi = path_range
    free_cells = np.flatnonzero(~maze.walls.ravel())
    for cell in rng.permutation(free_cells):
        start = maze.pos(int(cell))
        found = _misleading_goal(maze, start, radius)
        if found is not None and lo <= found[1] <= hi:
            return (int(start[0]), int(start[1])), (int(found[0][0]), int(found[0][1]))
    raise MazeError(
        f"random maze: no start among the {len(free_cells)} free cells has a goal within Manhattan distance {radius} "
        f"whose path is {lo}-{hi} steps (try a larger maze or another path_range)"
    )
