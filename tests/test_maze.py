"""Maze layouts: the shipped presets, parsing and its error messages, and the random maze generator.

Reference answers (layouts, moves, BFS distances) are computed here from the raw maze files with code independent of
``ss_drl.envs.maze``, so a bug there cannot also hide in the expected values.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from helpers import SHORTEST

from ss_drl.envs import PRESETS, Maze, MazeError, load_maze, parse_maze, random_maze

MAZE_DIR = Path(__file__).resolve().parents[1] / "ss_drl" / "mazes"


#: action -> (d_row, d_col): 0 right, 1 down, 2 left, 3 up.
MOVES = {0: (0, 1), 1: (1, 0), 2: (0, -1), 3: (-1, 0)}


# --- independent reference helpers ---------------------------------------------------------------------------------
def read_raw(name: str) -> tuple[np.ndarray, tuple[int, int], tuple[int, int]]:
    """(walls, start, goal) read straight from a shipped maze file, without ss_drl."""
    rows = [line for line in (MAZE_DIR / f"{name}.txt").read_text().split("\n") if line]
    walls = np.array([[ch == "#" for ch in row] for row in rows], dtype=bool)
    start = next((r, c) for r, row in enumerate(rows) for c, ch in enumerate(row) if ch == "S")
    goal = next((r, c) for r, row in enumerate(rows) for c, ch in enumerate(row) if ch == "G")
    return walls, start, goal


def ref_move(walls: np.ndarray, pos: tuple[int, int], action: int) -> tuple[int, int]:
    dr, dc = MOVES[action]
    r, c = pos[0] + dr, pos[1] + dc
    if r < 0 or c < 0 or r >= walls.shape[0] or c >= walls.shape[1] or walls[r, c]:
        return pos
    return (r, c)


def bfs(walls: np.ndarray, src: tuple[int, int]) -> np.ndarray:
    """BFS distance from ``src`` to every cell (-1: wall or unreachable), by frontier shifts with numpy."""
    free = ~walls
    dist = np.full(walls.shape, -1, dtype=np.int64)
    frontier = np.zeros(walls.shape, dtype=bool)
    frontier[src] = True
    dist[src] = 0
    d = 0
    while frontier.any():
        d += 1
        grown = np.zeros_like(frontier)
        grown[1:, :] |= frontier[:-1, :]
        grown[:-1, :] |= frontier[1:, :]
        grown[:, 1:] |= frontier[:, :-1]
        grown[:, :-1] |= frontier[:, 1:]
        frontier = grown & free & (dist < 0)
        dist[frontier] = d
    return dist


def diameter(walls: np.ndarray) -> int:
    """Longest shortest path between any two free cells (all-sources BFS; for small mazes only)."""
    return max(int(bfs(walls, (int(r), int(c))).max()) for r, c in np.argwhere(~walls))


def assert_same_maze(a: Maze, b: Maze) -> None:
    assert a.walls.shape == b.walls.shape
    assert np.array_equal(a.walls, b.walls)
    assert tuple(a.start) == tuple(b.start)
    assert tuple(a.goal) == tuple(b.goal)


def write(tmp_path: Path, text: str, name: str = "bad.txt") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def load_error(path: Path) -> str:
    with pytest.raises(MazeError) as info:
        load_maze(path)
    message = str(info.value)
    assert str(path) in message, message
    return message


# --- shipped presets -----------------------------------------------------------------------------------------------
def test_presets_are_the_shipped_files():
    assert sorted(PRESETS) == sorted(p.stem for p in MAZE_DIR.glob("*.txt"))
    assert set(PRESETS) == set(SHORTEST)


@pytest.mark.parametrize("name", sorted(SHORTEST))
def test_preset_loads_as_written(name):
    walls, start, goal = read_raw(name)
    maze = load_maze(name)
    assert maze.name == name
    assert maze.walls.dtype == bool
    assert np.array_equal(maze.walls, walls)
    assert maze.start == start and maze.goal == goal
    assert (maze.height, maze.width) == walls.shape
    assert maze.n_cells == walls.size and maze.n_free == int((~walls).sum())
    # Loading the same file by path gives the same layout.
    assert_same_maze(load_maze(MAZE_DIR / f"{name}.txt"), maze)
    assert_same_maze(load_maze(str(MAZE_DIR / f"{name}.txt")), maze)


@pytest.mark.parametrize("name", sorted(SHORTEST))
def test_preset_shortest_path_length(name):
    maze = load_maze(name)
    assert bfs(maze.walls, maze.start)[maze.goal] == SHORTEST[name]
    assert maze.shortest_path_length == SHORTEST[name]
    walls, start, goal = read_raw(name)
    assert bfs(walls, start)[goal] == SHORTEST[name]


@pytest.mark.parametrize("name", sorted(SHORTEST))
def test_distances_from_matches_reference_bfs(name):
    maze = load_maze(name)
    for src in (maze.start, maze.goal):
        assert np.array_equal(maze.distances_from(src), bfs(maze.walls, src))


@pytest.mark.parametrize("name", sorted(SHORTEST))
def test_move_and_transition_table_match_reference(name):
    maze = load_maze(name)
    table = maze.transition_table()
    assert table.shape == (maze.n_cells, 4)
    assert table.dtype == np.int64
    expected = np.empty_like(table)
    for r, c in itertools.product(range(maze.height), range(maze.width)):
        for a in range(4):
            nxt = ref_move(maze.walls, (r, c), a)
            expected[r * maze.width + c, a] = nxt[0] * maze.width + nxt[1]
            if not maze.walls[r, c]:
                assert maze.move((r, c), a) == nxt
    assert np.array_equal(table[~maze.walls.ravel()], expected[~maze.walls.ravel()])


def test_move_directions_and_bumps():
    # 3x3, wall in the middle of the top row.
    maze = parse_maze("S#.\n...\n..G\n")
    assert maze.move((1, 1), 0) == (1, 2)  # right
    assert maze.move((1, 1), 1) == (2, 1)  # down
    assert maze.move((1, 1), 2) == (1, 0)  # left
    assert maze.move((1, 1), 3) == (1, 1)  # up, into the wall: stays
    assert maze.move((0, 0), 0) == (0, 0)  # right, into the wall
    assert maze.move((0, 0), 3) == (0, 0)  # up, off the grid
    assert maze.move((0, 0), 2) == (0, 0)  # left, off the grid
    assert maze.move((2, 2), 1) == (2, 2)  # down, off the grid
    assert maze.move((2, 2), 0) == (2, 2)  # right, off the grid


def test_cell_and_pos_are_inverse():
    maze = load_maze("easy_small")
    cells = [maze.cell((r, c)) for r in range(maze.height) for c in range(maze.width)]
    assert cells == list(range(maze.n_cells))
    assert all(maze.cell(maze.pos(i)) == i for i in range(maze.n_cells))
    assert maze.start_cell == maze.start[0] * maze.width + maze.start[1]
    assert maze.goal_cell == maze.goal[0] * maze.width + maze.goal[1]


@pytest.mark.parametrize("name", sorted(SHORTEST))
def test_preset_text_round_trip(name):
    maze = load_maze(name)
    assert maze.to_text() == (MAZE_DIR / f"{name}.txt").read_text()
    assert_same_maze(parse_maze(maze.to_text()), maze)


def test_parse_accepts_crlf_and_missing_final_newline():
    expected = parse_maze("S..\n.#.\n..G\n")
    assert_same_maze(parse_maze("S..\r\n.#.\r\n..G\r\n"), expected)
    assert_same_maze(parse_maze("S..\n.#.\n..G"), expected)
    assert_same_maze(parse_maze("S..\n.#.\n..G\n\n  \n"), expected)  # trailing blank lines are ignored
    assert expected.start == (0, 0) and expected.goal == (2, 2)
    assert expected.walls.tolist() == [[False] * 3, [False, True, False], [False] * 3]


# --- bad maze files: one test per rule -----------------------------------------------------------------------------
def test_bad_file_no_start(tmp_path):
    path = write(tmp_path, "...\n.#.\n..G\n")
    message = load_error(path)
    assert "'S'" in message and "start" in message


def test_bad_file_no_goal(tmp_path):
    path = write(tmp_path, "S..\n.#.\n...\n")
    message = load_error(path)
    assert "'G'" in message and "goal" in message


def test_bad_file_two_starts(tmp_path):
    path = write(tmp_path, "S..\n.#.\n.SG\n")
    message = load_error(path)
    assert f"{path}:3:2" in message  # the second S
    assert "more than one" in message and "'S'" in message


def test_bad_file_two_goals(tmp_path):
    path = write(tmp_path, "S.G\n.#.\n..G\n")
    message = load_error(path)
    assert f"{path}:3:3" in message  # the second G
    assert "more than one" in message and "'G'" in message


def test_bad_file_unknown_character(tmp_path):
    path = write(tmp_path, "S..\n.#.\n.o.\n..G\n")
    message = load_error(path)
    assert f"{path}:3:2" in message
    assert "'o'" in message
    # A space (e.g. trailing whitespace on a row) is not a free cell either.
    path = write(tmp_path, "S.. \n.#.G\n", name="space.txt")
    assert f"{path}:1:4" in load_error(path)


def test_bad_file_ragged_rows(tmp_path):
    path = write(tmp_path, "S...\n..\n...G\n")  # line 2 is short: its column 3 is missing
    message = load_error(path)
    assert f"{path}:2:3" in message
    assert "ragged" in message
    path = write(tmp_path, "S..\n.#.\n....\n..G\n", name="long.txt")  # line 3 has an extra 4th column
    assert f"{path}:3:4" in load_error(path)


def test_bad_file_goal_unreachable(tmp_path):
    path = write(tmp_path, "S#.\n.#G\n..#\n")
    message = load_error(path)
    assert f"{path}:2:3" in message  # the goal
    assert "unreachable" in message


@pytest.mark.parametrize("text", ["", "\n", "   \n\t\n  ", "\r\n\r\n"])
def test_bad_file_empty(tmp_path, text):
    path = write(tmp_path, text)
    assert "empty" in load_error(path)


def test_parse_maze_names_its_source():
    with pytest.raises(MazeError, match=r"^my-source:1:2: "):
        parse_maze("SxG\n", source="my-source")


def test_load_missing_file(tmp_path):
    path = tmp_path / "does_not_exist.txt"
    message = load_error(path)
    assert "not found" in message
    with pytest.raises(MazeError, match="not found"):
        load_maze(tmp_path)  # a directory is not a maze file


def test_load_unknown_preset():
    with pytest.raises(MazeError) as info:
        load_maze("impossible")
    message = str(info.value)
    assert "impossible" in message
    assert all(name in message for name in PRESETS)  # says which presets exist


def test_load_undecodable_file(tmp_path):
    path = tmp_path / "binary.txt"
    path.write_bytes(b"S.\xff\xfe\n..G\n")
    load_error(path)


# --- random mazes --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("height", "width", "scale"), [(9, 11, 1), (10, 7, 2), (5, 5, 3)])
def test_random_maze_same_seed_same_maze(height, width, scale):
    a = random_maze(height, width, scale=scale, seed=123)
    b = random_maze(height, width, scale=scale, seed=123)
    assert_same_maze(a, b)


def test_random_maze_different_seeds_differ():
    mazes = [random_maze(11, 11, seed=seed) for seed in range(8)]
    for a, b in itertools.combinations(mazes, 2):
        assert not np.array_equal(a.walls, b.walls)


CASES = [(h, w, s, seed) for (h, w, s) in [(9, 11, 1), (8, 10, 1), (7, 7, 2), (3, 3, 1), (3, 4, 3)] for seed in (0, 1)]


@pytest.mark.parametrize(("height", "width", "scale", "seed"), CASES)
def test_random_maze_structure(height, width, scale, seed):
    maze = random_maze(height, width, scale=scale, seed=seed)
    assert maze.walls.shape == (height * scale, width * scale)
    assert maze.walls.dtype == bool
    assert not maze.walls[maze.start] and not maze.walls[maze.goal]
    assert maze.start != maze.goal
    dist = bfs(maze.walls, maze.start)
    # Every free cell is reachable from S.
    assert np.all((dist >= 0) == ~maze.walls)
    # G is a farthest cell from S ...
    assert dist[maze.goal] == dist.max()
    assert maze.shortest_path_length == dist.max()
    # ... and S-G is (close to) the longest shortest path in the maze.
    longest = diameter(maze.walls)
    if scale == 1:
        assert dist[maze.goal] == longest  # a perfect maze is a tree: two BFS sweeps find the exact diameter
    else:
        assert dist[maze.goal] >= 0.9 * longest


@pytest.mark.parametrize(("scale", "seed"), [(1, 2), (1, 3), (1, 4), (1, 5), (2, 2), (3, 4)])
def test_random_maze_start_and_goal_come_from_two_bfs_sweeps(scale, seed):
    """What random_maze's docstring says: S is a farthest free cell from (0, 0), G a farthest free cell from S; for
    scale 1 (a tree) the S-G distance is then exactly the maze's diameter."""
    maze = random_maze(11, 9, scale=scale, seed=seed)
    from_corner = bfs(maze.walls, (0, 0))
    assert from_corner[maze.start] == from_corner.max()
    from_start = bfs(maze.walls, maze.start)
    assert from_start[maze.goal] == from_start.max() == maze.shortest_path_length
    if scale == 1:
        assert maze.shortest_path_length == diameter(maze.walls)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_maze_scale_one_is_perfect(seed):
    """A perfect maze: the free cells form a tree (connected, with exactly n_free - 1 adjacent free pairs)."""
    walls = random_maze(13, 9, seed=seed).walls
    free = ~walls
    edges = int((free[:, 1:] & free[:, :-1]).sum() + (free[1:, :] & free[:-1, :]).sum())
    assert edges == int(free.sum()) - 1


@pytest.mark.parametrize("scale", [2, 3])
def test_random_maze_scale_blows_up_the_layout(scale):
    base = random_maze(7, 9, scale=1, seed=5)
    big = random_maze(7, 9, scale=scale, seed=5)
    assert big.walls.shape == (7 * scale, 9 * scale)
    assert np.array_equal(big.walls, np.kron(base.walls, np.ones((scale, scale), dtype=bool)))
    assert big.n_free == base.n_free * scale**2


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(height=2, width=5),
        dict(height=5, width=2),
        dict(height=0, width=0),
        dict(height=-3, width=5),
        dict(height=5, width=5, scale=0),
        dict(height=5, width=5, scale=-2),
    ],
)
def test_random_maze_bad_arguments(kwargs):
    with pytest.raises(MazeError):
        random_maze(**kwargs, seed=0)


@pytest.mark.parametrize(("height", "width", "scale", "seed"), [(9, 11, 1, 0), (6, 8, 2, 3), (3, 3, 1, 7)])
def test_random_maze_text_round_trip(height, width, scale, seed):
    maze = random_maze(height, width, scale=scale, seed=seed)
    text = maze.to_text()
    assert text.count("S") == 1 and text.count("G") == 1
    assert set(text) <= set("#.SG\n")
    again = parse_maze(text)
    assert_same_maze(again, maze)
    assert again.to_text() == text


# --- random mazes: the misleading placement (issue 49) -------------------------------------------------------------
DOCS_MAZES = Path(__file__).resolve().parents[1] / "docs" / "mazes"

#: The misleading mazes of docs/mazes/: file stem -> random_maze's keyword arguments (the call in docs/mazes/README.md).
MISLEADING = {f"misleading{seed}": dict(height=23, width=23, scale=1, seed=seed) for seed in range(3)}


def misleading_reference(walls: np.ndarray, start: tuple[int, int], radius: int) -> tuple[tuple[int, int], int]:
    """The rule's G for ``start``, brute force: every free cell other than S within Manhattan ``radius``, its distance
    by the reference BFS, the largest distance and, among ties, the first cell in row-major order."""
    dist = bfs(walls, start)
    best = None
    for r, c in itertools.product(range(walls.shape[0]), range(walls.shape[1])):
        if (r, c) == start or walls[r, c] or abs(r - start[0]) + abs(c - start[1]) > radius or dist[r, c] < 0:
            continue
        if best is None or dist[r, c] > best[1]:
            best = ((r, c), int(dist[r, c]))
    assert best is not None
    return best


def manhattan(a: tuple[int, int], b: tuple[int, int]) -> int:
    return abs(a[0] - b[0]) + abs(a[1] - b[1])


@pytest.mark.parametrize(
    ("height", "width", "scale", "seed", "radius", "path_range"),
    [
        (23, 23, 1, 0, 6, (150, 250)),
        (23, 23, 1, 1, 6, (150, 250)),
        (23, 23, 1, 2, 6, (150, 250)),
        (15, 13, 1, 3, 3, (20, 60)),
        (15, 15, 1, 4, 4, (30, 100)),
        (9, 11, 2, 5, 6, (30, 80)),
    ],
)
def test_random_maze_misleading_placement(height, width, scale, seed, radius, path_range):
    """The misleading placement of `random_maze`: G is within Manhattan distance `radius` of S, and farthest along the
    path among such cells (ties: the first in row-major order); the path is within `path_range`; the walls are the
    default placement's."""
    maze = random_maze(
        height, width, scale=scale, seed=seed, placement="misleading", radius=radius, path_range=path_range
    )
    assert not maze.walls[maze.start] and not maze.walls[maze.goal] and maze.start != maze.goal
    assert manhattan(maze.start, maze.goal) <= radius
    goal, length = misleading_reference(maze.walls, maze.start, radius)
    assert maze.goal == goal
    assert maze.shortest_path_length == length == bfs(maze.walls, maze.start)[maze.goal]
    assert path_range[0] <= length <= path_range[1]
    assert np.array_equal(maze.walls, random_maze(height, width, scale=scale, seed=seed).walls)
    assert "placement=misleading" in maze.name


@pytest.mark.parametrize("seed", [0, 7])
def test_random_maze_misleading_is_deterministic(seed):
    kwargs = dict(placement="misleading", radius=4, path_range=(25, 80))
    a = random_maze(17, 17, seed=seed, **kwargs)
    assert_same_maze(a, random_maze(17, 17, seed=seed, **kwargs))
    assert_same_maze(parse_maze(a.to_text()), a)


def test_random_maze_misleading_breaks_ties_by_lowest_index():
    """A hand-made case for the tie rule: from S in the middle of an open 5x5 room, eight cells at Manhattan distance
    2 tie at path length 2; the rule takes (0, 2), the first in row-major order."""
    from ss_drl.envs.maze import _misleading_goal

    room = Maze(walls=np.zeros((5, 5), dtype=bool), start=(2, 2), goal=(0, 0))
    assert _misleading_goal(room, (2, 2), 2) == ((0, 2), 2)
    assert misleading_reference(room.walls, (2, 2), 2) == ((0, 2), 2)


def test_random_maze_default_placement_unchanged():
    """The default is the longest placement, and the issue-12 file random200 is still what its call makes."""
    for seed in (0, 1, 2):
        assert_same_maze(random_maze(23, 23, seed=seed), random_maze(23, 23, seed=seed, placement="longest"))
    maze = random_maze(23, 23, scale=1, seed=0)
    assert maze.to_text() == (DOCS_MAZES / "random200.txt").read_text()
    assert maze.shortest_path_length == 190 == diameter(maze.walls)
    assert maze.name == "random(23x23,scale=1,seed=0)"


def test_random_maze_misleading_refuses_when_no_start_works():
    with pytest.raises(MazeError, match=r"no start among the \d+ free cells"):
        random_maze(9, 9, seed=0, placement="misleading")  # paths of 150+ steps cannot fit in 41 free cells


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(placement="farthest"), r"unknown placement 'farthest'"),
        (dict(placement="misleading", radius=0), r"radius must be >= 1 \(got 0\)"),
        (dict(placement="misleading", path_range=(0, 10)), r"path_range must be \(low, high\)"),
        (dict(placement="misleading", path_range=(20, 10)), r"path_range must be \(low, high\)"),
        (dict(placement="misleading", path_range=(10,)), r"path_range must be \(low, high\)"),
    ],
)
def test_random_maze_misleading_bad_arguments(kwargs, message):
    # Each refusal is the argument check's own: on an 11x11 maze the default path range (150-250) fits no start, so a
    # bare ValueError would also come from the placement search, or from unpacking a one-element path_range.
    with pytest.raises(MazeError, match=message):
        random_maze(11, 11, seed=0, **kwargs)


def test_misleading_size_is_the_smallest_that_works_for_seeds_0_to_2():
    """docs/mazes/README.md's size rule: 23 is the smallest odd n for which random_maze(n, n, placement="misleading")
    finds an S for each of seeds 0-2."""
    for n in range(3, 23, 2):
        failed = False
        for seed in range(3):
            try:
                random_maze(n, n, seed=seed, placement="misleading")
            except MazeError:
                failed = True
                break
        assert failed, n
    for seed in range(3):
        random_maze(23, 23, seed=seed, placement="misleading")


@pytest.mark.parametrize("name", sorted(MISLEADING))
def test_docs_misleading_mazes_are_their_calls(name):
    """The files in docs/mazes/ are what their documented calls make, so they cannot drift from the rule."""
    kwargs = MISLEADING[name]
    maze = random_maze(**kwargs, placement="misleading")
    path = DOCS_MAZES / f"{name}.txt"
    assert path.read_text() == maze.to_text()
    loaded = load_maze(path)
    assert_same_maze(loaded, maze)
    assert manhattan(loaded.start, loaded.goal) <= 6
    assert 150 <= bfs(loaded.walls, loaded.start)[loaded.goal] <= 250
    # The README documents exactly this call and this maze's figures.
    readme = (DOCS_MAZES / "README.md").read_text()
    call = 'random_maze({height}, {width}, scale={scale}, seed={seed}, placement="misleading")'.format(**kwargs)
    row = next(line for line in readme.splitlines() if line.startswith(f"| {name} |"))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells == [
        name,
        f"`{call}`",
        f"{loaded.height} x {loaded.width}",
        str(loaded.start),
        str(loaded.goal),
        str(manhattan(loaded.start, loaded.goal)),
        str(loaded.shortest_path_length),
        f"`{name}.txt`",
    ]
