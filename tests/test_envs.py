"""The gymnasium env (``MazeEnv``, ``SSDRL/*-v0``) and the batched TorchRL env (``BatchedMazeEnv``).

Expected positions come from a reference move function and BFS written here (not from ``ss_drl``): action 0 right
(0, +1), 1 down (+1, 0), 2 left (0, -1), 3 up (-1, 0); a bump into a wall or off the grid stays put and still counts
a step; reward 1.0 and terminated only on entering G; truncated (and not terminated) after ``max_steps`` steps.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from helpers import SHORTEST
from torchrl.envs.utils import check_env_specs

import ss_drl  # noqa: F401  (registers the SSDRL/*-v0 ids)
from ss_drl.envs import ENV_IDS, PRESETS, MazeEnv, MazeError, load_maze
from ss_drl.envs.batched import BatchedMazeEnv

NAMES = sorted(SHORTEST)
ID_OF = {preset: env_id for env_id, preset in ENV_IDS.items()}
MOVES = {0: (0, 1), 1: (1, 0), 2: (0, -1), 3: (-1, 0)}
ROOT = Path(__file__).resolve().parents[1]


# --- independent reference helpers ---------------------------------------------------------------------------------
def ref_move(walls: np.ndarray, pos: tuple[int, int], action: int) -> tuple[tuple[int, int], str | None]:
    """Next position and the kind of bump (None, "wall" or "edge")."""
    dr, dc = MOVES[int(action)]
    r, c = pos[0] + dr, pos[1] + dc
    if r < 0 or c < 0 or r >= walls.shape[0] or c >= walls.shape[1]:
        return pos, "edge"
    if walls[r, c]:
        return pos, "wall"
    return (r, c), None


def bfs(walls: np.ndarray, src: tuple[int, int]) -> dict[tuple[int, int], int]:
    dist = {src: 0}
    queue = [src]
    for cur in queue:
        for a in MOVES:
            nxt, _ = ref_move(walls, cur, a)
            if nxt not in dist:
                dist[nxt] = dist[cur] + 1
                queue.append(nxt)
    return dist


def shortest_actions(walls: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> list[int]:
    """A shortest action sequence from start to goal: BFS from the goal, then walk downhill."""
    to_goal = bfs(walls, goal)  # moves are symmetric, so distance from G equals distance to G
    actions, pos = [], start
    while pos != goal:
        action = next(a for a in MOVES if to_goal.get(ref_move(walls, pos, a)[0], -1) == to_goal[pos] - 1)
        actions.append(action)
        pos = ref_move(walls, pos, action)[0]
    return actions


def random_runs(rng: np.random.Generator, n: int) -> np.ndarray:
    """n actions in runs of one repeated action (so a walk travels and bumps into walls and edges)."""
    out: list[int] = []
    while len(out) < n:
        out += [int(rng.integers(4))] * int(rng.integers(1, 9))
    return np.array(out[:n], dtype=np.int64)


def make_gym(name: str, how: str, **kwargs) -> gym.Env:
    if how == "make":
        return gym.make(ID_OF[name], **kwargs)
    return MazeEnv(name, **kwargs)


def gym_pos(obs) -> tuple[int, int]:
    return (int(obs["observation"][0]), int(obs["observation"][1]))


def write_maze(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.txt"
    path.write_text("S.#\n..#\n#.G\n")
    return path


# --- gymnasium env semantics ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["class", "make"])
@pytest.mark.parametrize("name", NAMES)
def test_gym_shortest_path_reaches_goal(name, how):
    maze = load_maze(name)
    actions = shortest_actions(maze.walls, maze.start, maze.goal)
    assert len(actions) == SHORTEST[name]
    env = make_gym(name, how)
    obs, info = env.reset(seed=0)
    assert gym_pos(obs) == maze.start
    assert tuple(obs["desired_goal"]) == maze.goal
    assert info["is_success"] is False
    pos = maze.start
    for t, action in enumerate(actions, start=1):
        obs, reward, terminated, truncated, info = env.step(action)
        pos = ref_move(maze.walls, pos, action)[0]
        assert gym_pos(obs) == pos
        assert np.array_equal(obs["achieved_goal"], obs["observation"])
        assert tuple(obs["desired_goal"]) == maze.goal
        at_goal = t == len(actions)
        assert (pos == maze.goal) == at_goal
        assert reward == (1.0 if at_goal else 0.0)
        assert type(reward) is float
        assert terminated is at_goal
        assert truncated is False
        assert info["is_success"] is at_goal
    env.close()


@pytest.mark.parametrize("name", NAMES)
def test_gym_random_walk_matches_reference(name):
    maze = load_maze(name)
    env = gym.make(ID_OF[name], max_steps=100_000)
    rng = np.random.default_rng(1234)
    obs, _ = env.reset(seed=1)
    pos, bumps, goals = maze.start, {"wall": 0, "edge": 0}, 0
    for action in random_runs(rng, 600):
        obs, reward, terminated, truncated, info = env.step(action)
        pos, bump = ref_move(maze.walls, pos, action)
        if bump:
            bumps[bump] += 1
        assert gym_pos(obs) == pos
        at_goal = pos == maze.goal
        assert reward == float(at_goal)
        assert terminated is at_goal and info["is_success"] is at_goal
        assert truncated is False
        if terminated:
            goals += 1
            obs, _ = env.reset()
            pos = maze.start
            assert gym_pos(obs) == pos
    # The walk exercised both kinds of bump (a guard on the test itself).
    assert bumps["wall"] > 0 and bumps["edge"] > 0


@pytest.mark.parametrize("name", NAMES)
def test_gym_bump_counts_a_step(name):
    """Walk down until stuck at a wall or the bottom edge, then keep bumping: each bump is a step (truncation)."""
    maze = load_maze(name)
    pos, moves = maze.start, 0
    while ref_move(maze.walls, pos, 1)[1] is None:
        pos, moves = ref_move(maze.walls, pos, 1)[0], moves + 1
    env = gym.make(ID_OF[name], max_steps=moves + 5)
    env.reset()
    for t in range(1, moves + 6):
        obs, reward, terminated, truncated, _ = env.step(1)
        if t >= moves:
            assert gym_pos(obs) == pos
        assert (reward, terminated, truncated) == (0.0, False, t == moves + 5)


@pytest.mark.parametrize("name", NAMES)
def test_gym_truncation(name):
    maze = load_maze(name)
    env = gym.make(ID_OF[name], max_steps=7)
    rng = np.random.default_rng(7)
    for _episode in range(3):
        obs, _ = env.reset()
        assert gym_pos(obs) == maze.start
        pos = maze.start
        for t in range(1, 8):
            action = int(rng.integers(4))
            obs, reward, terminated, truncated, _ = env.step(action)
            pos = ref_move(maze.walls, pos, action)[0]
            assert gym_pos(obs) == pos
            assert reward == 0.0 and terminated is False
            assert truncated is (t == 7)


@pytest.mark.parametrize("name", NAMES)
def test_gym_goal_on_last_allowed_step_is_terminated(name):
    maze = load_maze(name)
    actions = shortest_actions(maze.walls, maze.start, maze.goal)
    n = len(actions)
    # max_steps == path length: the last allowed step enters G -> terminated, not truncated.
    env = gym.make(ID_OF[name], max_steps=n)
    env.reset()
    results = [env.step(a)[1:4] for a in actions]
    assert results[-1] == (1.0, True, False)
    assert all(r == (0.0, False, False) for r in results[:-1])
    # One step fewer: truncated one step before G.
    env = gym.make(ID_OF[name], max_steps=n - 1)
    env.reset()
    results = [env.step(a)[:4] for a in actions[:-1]]
    assert [r[1:] for r in results[:-1]] == [(0.0, False, False)] * (n - 2)
    obs, reward, terminated, truncated = results[-1]
    assert (reward, terminated, truncated) == (0.0, False, True)
    assert bfs(maze.walls, maze.goal)[gym_pos(obs)] == 1


def test_gym_reset_restarts_episode():
    maze = load_maze("easy_small")
    env = MazeEnv("easy_small", max_steps=3)
    env.reset()
    env.step(0)
    env.step(0)
    obs, _ = env.reset()
    assert gym_pos(obs) == maze.start
    # The step counter restarted: 2 more steps do not truncate, the 3rd does.
    assert env.step(1)[3] is False
    assert env.step(1)[3] is False
    assert env.step(1)[3] is True


def test_gym_invalid_arguments():
    with pytest.raises(ValueError):
        MazeEnv("easy_small", max_steps=0)
    with pytest.raises(ValueError):
        MazeEnv("easy_small", render_mode="human")
    env = MazeEnv("easy_small")
    env.reset()
    for bad in (4, -1):
        with pytest.raises(ValueError):
            env.step(bad)


def test_gym_accepts_maze_and_path_layouts(tmp_path):
    path = write_maze(tmp_path)
    maze = load_maze(path)
    for layout in (maze, path, str(path)):
        env = MazeEnv(layout, max_steps=10)
        obs, _ = env.reset()
        assert gym_pos(obs) == (0, 0) and tuple(obs["desired_goal"]) == (2, 2)
        # right, down, down (into (2,1)), right (into G)
        results = [env.step(a) for a in (0, 1, 1, 0)]
        assert [gym_pos(r[0]) for r in results] == [(0, 1), (1, 1), (2, 1), (2, 2)]
        assert [r[1] for r in results] == [0.0, 0.0, 0.0, 1.0]
        assert [r[2] for r in results] == [False, False, False, True]


# --- registration, checkers, GoalEnv interface, rendering ----------------------------------------------------------
def test_env_ids_cover_presets():
    assert sorted(ENV_IDS.values()) == sorted(PRESETS)
    assert all(env_id.startswith("SSDRL/") and env_id.endswith("-v0") for env_id in ENV_IDS)


def fresh_python(code: str) -> subprocess.CompletedProcess:
    """``code`` run in a fresh interpreter (nothing imported yet) from the repository root."""
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_import_registers_ids():
    out = fresh_python(
        "import gymnasium, ss_drl, ss_drl.envs as e\n"
        "ids = [*e.ENV_IDS, 'SSDRL/Maze-v0']\n"
        "missing = [i for i in ids if i not in gymnasium.registry]\n"
        "assert not missing, missing\n"
        "env = gymnasium.make('SSDRL/EasySmall-v0', max_steps=3)\n"
        "print(env.unwrapped.maze.shortest_path_length)\n"
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(SHORTEST["easy_small"])


def test_gymnasium_make_with_the_module_prefix_needs_no_import():
    """The README's ``gymnasium.make("ss_drl:SSDRL/Easy-v0")`` works in a fresh interpreter that never imported ss_drl
    (gymnasium imports the module before the lookup); without the prefix the id is unknown until ``import ss_drl``."""
    out = fresh_python(
        "import sys, gymnasium\n"
        "assert 'ss_drl' not in sys.modules\n"
        "print(gymnasium.make('ss_drl:SSDRL/Easy-v0').unwrapped.maze.shortest_path_length)\n"
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(SHORTEST["easy"])
    out = fresh_python("import gymnasium\ngymnasium.make('SSDRL/Easy-v0')\n")
    assert out.returncode != 0 and "SSDRL" in out.stderr


@pytest.mark.parametrize("env_id", [*ENV_IDS, "SSDRL/Maze-v0"])
def test_registered_id_makes_with_max_steps(env_id, tmp_path):
    kwargs = {"layout": str(write_maze(tmp_path))} if env_id == "SSDRL/Maze-v0" else {}
    env = gym.make(env_id, max_steps=4, **kwargs)
    expected = load_maze(kwargs.get("layout", ENV_IDS.get(env_id)))
    maze = env.unwrapped.maze
    assert np.array_equal(maze.walls, expected.walls)
    assert maze.start == expected.start and maze.goal == expected.goal
    assert env.unwrapped.max_steps == 4
    # No TimeLimit wrapper on top: the env's own max_steps truncates.
    assert env.spec.max_episode_steps is None
    obs, _ = env.reset(seed=3)
    assert gym_pos(obs) == expected.start
    truncs = [env.step(1)[3] for _ in range(4)]
    assert truncs == [False, False, False, True]
    check_env(env.unwrapped, skip_render_check=False)


def test_maze_v0_missing_layout_file(tmp_path):
    with pytest.raises(MazeError, match="not found"):
        gym.make("SSDRL/Maze-v0", layout=str(tmp_path / "missing.txt"))


@pytest.mark.parametrize("render_mode", ["ansi", "rgb_array"])
def test_check_env_with_render_modes(render_mode):
    env = gym.make("SSDRL/MediumSmall-v0", render_mode=render_mode, max_steps=20)
    check_env(env.unwrapped, skip_render_check=False)


def test_compute_reward_and_terminated_vectorized():
    env = gym.make("SSDRL/EasySmall-v0").unwrapped
    achieved = np.array([[1, 1], [10, 1], [1, 2], [1, 1], [0, 0]])
    desired = np.array([[1, 1], [1, 1], [1, 2], [2, 1], [0, 0]])
    expected = np.array([True, False, True, False, True])
    reward = env.compute_reward(achieved, desired, [{}] * 5)
    assert isinstance(reward, np.ndarray) and reward.shape == (5,)
    assert np.issubdtype(reward.dtype, np.floating)
    assert np.array_equal(reward, expected.astype(float))
    terminated = env.compute_terminated(achieved, desired, [{}] * 5)
    assert terminated.shape == (5,) and terminated.dtype == bool
    assert np.array_equal(terminated, expected)
    truncated = env.compute_truncated(achieved, desired, [{}] * 5)
    assert truncated.shape == (5,) and not truncated.any()
    # Broadcast: many achieved goals against one desired goal, and extra leading axes.
    assert np.array_equal(env.compute_reward(achieved, np.array([1, 1]), None), [1.0, 0.0, 0.0, 1.0, 0.0])
    grid = env.compute_reward(achieved.reshape(5, 1, 2), desired.reshape(1, 5, 2), None)
    assert grid.shape == (5, 5)
    assert np.array_equal(grid, (achieved[:, None] == desired[None]).all(-1).astype(float))
    # Single goals give scalars.
    assert env.compute_reward(np.array([1, 1]), np.array([1, 1]), {}) == 1.0
    assert env.compute_reward(np.array([1, 1]), np.array([1, 2]), {}) == 0.0
    assert bool(env.compute_terminated(np.array([3, 4]), np.array([3, 4]), {})) is True


def test_compute_reward_agrees_with_step():
    """HER relabelling relies on compute_reward(achieved, desired) reproducing the env's own reward."""
    maze = load_maze("easy_small")
    env = gym.make("SSDRL/EasySmall-v0")
    env.reset()
    for action in shortest_actions(maze.walls, maze.start, maze.goal):
        obs, reward, terminated, _, info = env.step(action)
        assert env.unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"], info) == reward
        assert bool(env.unwrapped.compute_terminated(obs["achieved_goal"], obs["desired_goal"], info)) == terminated


def test_render_ansi():
    maze = load_maze("easy_small")
    text = (ROOT / "ss_drl" / "mazes" / "easy_small.txt").read_text()
    rows = [list(row) for row in text.splitlines()]
    env = gym.make("SSDRL/EasySmall-v0", render_mode="ansi")
    env.reset()

    def expected(agent):
        chars = [row[:] for row in rows]
        chars[agent[0]][agent[1]] = "A"
        return ["".join(row) for row in chars]

    out = env.render()
    assert isinstance(out, str)
    assert out.splitlines() == expected(maze.start)
    obs, *_ = env.step(3)  # up from S
    assert gym_pos(obs) != maze.start
    out = env.render()
    assert out.splitlines() == expected(gym_pos(obs))
    assert out.count("A") == 1 and out.count("S") == 1 and out.count("G") == 1


@pytest.mark.parametrize("cell_pixels", [None, 3])
def test_render_rgb_array(cell_pixels):
    maze = load_maze("easy_small")
    kwargs = {} if cell_pixels is None else {"cell_pixels": cell_pixels}
    env = gym.make("SSDRL/EasySmall-v0", render_mode="rgb_array", **kwargs)
    env.reset()
    img = env.render()
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.ndim == 3
    px = img.shape[0] // maze.height
    assert px >= 1 and img.shape == (maze.height * px, maze.width * px, 3)
    if cell_pixels is not None:
        assert px == cell_pixels

    def blocks(image):
        cells = image.reshape(maze.height, px, maze.width, px, 3)
        assert (cells == cells[:, :1, :, :1]).all()  # every cell is one flat colour
        return cells[:, 0, :, 0]

    colour = blocks(img)
    wall_colours = {tuple(c) for c in colour[maze.walls]}
    free = ~maze.walls
    free[maze.start] = free[maze.goal] = False
    free_colours = {tuple(c) for c in colour[free]}
    assert len(wall_colours) == 1 and len(free_colours) == 1 and wall_colours != free_colours
    agent_colour = tuple(colour[maze.start])
    goal_colour = tuple(colour[maze.goal])
    assert len({agent_colour, goal_colour, *wall_colours, *free_colours}) == 4
    # The agent's colour moves with the agent.
    obs, *_ = env.step(0)
    colour = blocks(env.render())
    assert tuple(colour[gym_pos(obs)]) == agent_colour
    assert tuple(colour[maze.start]) not in (agent_colour, *free_colours, *wall_colours)  # S is marked
    assert tuple(colour[maze.goal]) == goal_colour


def test_render_none_without_mode():
    env = MazeEnv("easy_small")
    env.reset()
    assert env.render() is None


# --- batched TorchRL env -------------------------------------------------------------------------------------------
def cell_of(maze, pos) -> int:
    return pos[0] * maze.width + pos[1]


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize("name", ["easy_small", "extreme"])
def test_batched_check_env_specs(name, num_envs):
    env = BatchedMazeEnv(name, num_envs=num_envs, max_steps=5)
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].shape == (num_envs,) and td["observation"].dtype == torch.int64
    assert td["desired_goal"].shape == (num_envs,)
    td = env.rand_step(td)
    assert td["next", "reward"].shape == (num_envs, 1) and td["next", "reward"].dtype == torch.float32
    for key in ("done", "terminated", "truncated"):
        assert td["next", key].shape == (num_envs, 1) and td["next", key].dtype == torch.bool


def test_batched_invalid_arguments():
    with pytest.raises(ValueError):
        BatchedMazeEnv("easy_small", num_envs=0)
    with pytest.raises(ValueError):
        BatchedMazeEnv("easy_small", max_steps=0)


def test_batched_accepts_maze_and_path_layouts(tmp_path):
    path = write_maze(tmp_path)
    for layout in (load_maze(path), path, str(path)):
        env = BatchedMazeEnv(layout, num_envs=2, max_steps=10)
        assert (env.maze.height, env.maze.width) == (3, 3)
        td = env.reset()
        assert td["observation"].tolist() == [0, 0] and td["desired_goal"].tolist() == [8, 8]
        cells, rewards = [], []
        for action in (0, 1, 1, 0):  # right, down, down, right: (0,1) (1,1) (2,1) G=(2,2)
            td["action"] = torch.tensor([action, 2])  # copy 1 bumps left at S
            td = env.step(td)
            cells.append(td["next", "observation"].tolist())
            rewards.append(td["next", "reward"].flatten().tolist())
            td = td["next"].clone()
        assert cells == [[1, 0], [4, 0], [7, 0], [8, 0]]
        assert rewards == [[0.0, 0.0]] * 3 + [[1.0, 0.0]]
        assert td["terminated"].flatten().tolist() == [True, False]


@pytest.mark.parametrize("name", NAMES)
def test_batched_shortest_path_and_limits(name):
    """Copy 0 follows a shortest path, copy 1 only moves down, copy 2 walks at random; max_steps is the path length
    (copy 0 terminates on the last allowed step) or one less (copy 0 is truncated next to G)."""
    maze = load_maze(name)
    path = shortest_actions(maze.walls, maze.start, maze.goal)
    n = len(path)
    assert n == SHORTEST[name]
    rng = np.random.default_rng(5)
    actions = np.stack([path, [1] * n, rng.integers(4, size=n)], axis=0)
    for max_steps in (n, n - 1):
        env = BatchedMazeEnv(name, num_envs=3, max_steps=max_steps)
        td = env.reset()
        assert td["observation"].tolist() == [maze.start_cell] * 3
        assert td["desired_goal"].tolist() == [cell_of(maze, maze.goal)] * 3
        pos = [maze.start] * 3
        for t in range(1, max_steps + 1):
            td["action"] = torch.as_tensor(actions[:, t - 1])
            td = env.step(td)
            nxt = td["next"]
            pos = [ref_move(maze.walls, p, a)[0] for p, a in zip(pos, actions[:, t - 1])]
            assert nxt["observation"].tolist() == [cell_of(maze, p) for p in pos]
            assert nxt["desired_goal"].tolist() == [cell_of(maze, maze.goal)] * 3
            at_goal = [p == maze.goal for p in pos]
            assert nxt["reward"].flatten().tolist() == [float(g) for g in at_goal]
            assert nxt["terminated"].flatten().tolist() == at_goal
            assert nxt["truncated"].flatten().tolist() == [t == max_steps and not g for g in at_goal]
            assert nxt["done"].flatten().tolist() == [g or t == max_steps for g in at_goal]
            assert env.step_count.tolist() == [t] * 3
            td = td["next"].clone()
        assert at_goal[0] is (max_steps == n)
        assert not at_goal[1] and ref_move(maze.walls, pos[1], 1)[1] is not None  # copy 1 ended stuck, bumping


@pytest.mark.parametrize("name", NAMES)
def test_batched_random_walk_matches_reference(name):
    maze = load_maze(name)
    num_envs, steps = 4, 300
    env = BatchedMazeEnv(name, num_envs=num_envs, max_steps=100_000)
    rng = np.random.default_rng(99)
    actions = np.stack([random_runs(rng, steps) for _ in range(num_envs)])
    td = env.reset()
    pos = [maze.start] * num_envs
    bumps = set()
    for t in range(steps):
        td["action"] = torch.as_tensor(actions[:, t])
        out, td = env.step_and_maybe_reset(td)
        moved = [ref_move(maze.walls, p, a) for p, a in zip(pos, actions[:, t])]
        bumps |= {kind for _, kind in moved if kind}
        pos = [p for p, _ in moved]
        assert out["next", "observation"].tolist() == [cell_of(maze, p) for p in pos]
        at_goal = [p == maze.goal for p in pos]
        assert out["next", "reward"].flatten().tolist() == [float(g) for g in at_goal]
        assert out["next", "terminated"].flatten().tolist() == at_goal
        assert not out["next", "truncated"].any()
        pos = [maze.start if g else p for p, g in zip(pos, at_goal)]
        assert td["observation"].tolist() == [cell_of(maze, p) for p in pos]
    assert bumps == {"wall", "edge"}


def test_batched_observations_are_not_overwritten():
    """A stored observation keeps its value after later steps and resets (replay buffers keep references)."""
    env = BatchedMazeEnv("easy_small", num_envs=2, max_steps=3)
    td = env.reset()
    kept, values = [], []
    for t in range(7):
        td["action"] = torch.tensor([t % 4, 3])
        out, td = env.step_and_maybe_reset(td)
        kept += [out["observation"], out["next", "observation"], td["observation"]]
        values += [t.clone() for t in kept[-3:]]
    for tensor, value in zip(kept, values):
        assert torch.equal(tensor, value)


def test_batched_partial_reset():
    maze = load_maze("easy_small")
    env = BatchedMazeEnv("easy_small", num_envs=3, max_steps=50)
    td = env.reset()
    td["action"] = torch.tensor([3, 3, 3])  # up from S: everyone moves
    td = env.step(td)["next"].clone()
    moved = cell_of(maze, (maze.start[0] - 1, maze.start[1]))
    assert td["observation"].tolist() == [moved] * 3
    # TorchRL's contract: the input carries the data of the copies that are not reset.
    td["_reset"] = torch.tensor([[False], [True], [False]])
    td = env.reset(td)
    assert td["observation"].tolist() == [moved, maze.start_cell, moved]
    assert env.step_count.tolist() == [1, 0, 1]


# --- batched env == gymnasium env ----------------------------------------------------------------------------------
def run_equivalence(name: str, actions: np.ndarray, max_steps: int) -> dict[str, int]:
    """Step N batched copies (auto-reset) and N gymnasium envs (reset on done) with the same per-copy actions and
    assert identical transitions; return how many episodes ended by terminated and by truncated."""
    maze = load_maze(name)
    num_envs, steps = actions.shape
    benv = BatchedMazeEnv(name, num_envs=num_envs, max_steps=max_steps)
    genvs = [gym.make(ID_OF[name], max_steps=max_steps) for _ in range(num_envs)]
    gobs = [g.reset(seed=i)[0] for i, g in enumerate(genvs)]
    td = benv.reset()
    goal = cell_of(maze, maze.goal)
    counts = {"terminated": 0, "truncated": 0}
    episode_steps = [0] * num_envs
    assert td["observation"].tolist() == [cell_of(maze, gym_pos(o)) for o in gobs]
    for t in range(steps):
        td["action"] = torch.as_tensor(actions[:, t])
        out, td = benv.step_and_maybe_reset(td)
        for i, genv in enumerate(genvs):
            obs, reward, terminated, truncated, info = genv.step(int(actions[i, t]))
            episode_steps[i] += 1
            assert int(out["next", "observation"][i]) == cell_of(maze, gym_pos(obs))
            assert int(out["next", "desired_goal"][i]) == cell_of(maze, tuple(obs["desired_goal"])) == goal
            assert float(out["next", "reward"][i]) == reward
            assert bool(out["next", "terminated"][i]) is terminated
            assert bool(out["next", "truncated"][i]) is truncated
            assert bool(out["next", "done"][i]) is (terminated or truncated)
            assert int(benv.step_count[i]) == (0 if terminated or truncated else episode_steps[i])
            if terminated or truncated:
                counts["terminated" if terminated else "truncated"] += 1
                obs, _ = genv.reset()
                episode_steps[i] = 0
            assert int(td["observation"][i]) == cell_of(maze, gym_pos(obs))
            assert int(td["desired_goal"][i]) == goal
    return counts


@pytest.mark.parametrize("max_steps", [7, 1000])
@pytest.mark.parametrize("name", NAMES)
def test_batched_matches_gym_random_actions(name, max_steps):
    rng = np.random.default_rng(2024)
    actions = np.stack([random_runs(rng, 60) for _ in range(3)])
    counts = run_equivalence(name, actions, max_steps)
    if max_steps == 7:
        assert counts["truncated"] == 3 * (60 // 7)  # G is farther than 7 steps on every maze


@pytest.mark.parametrize("max_steps", [19, 20, 1000, 18])
def test_batched_matches_gym_reaching_goal(max_steps):
    """easy_small: copy 0 follows a shortest path again and again, copy 1 the same path with random detours,
    copy 2 walks at random."""
    maze = load_maze("easy_small")
    path = shortest_actions(maze.walls, maze.start, maze.goal)
    rng = np.random.default_rng(11)
    steps = 4 * len(path)
    detour = list(path)
    for k in (15, 9, 4):
        detour[k:k] = [int(rng.integers(4))]
    actions = np.stack(
        [
            np.resize(path, steps),
            np.resize(detour, steps),
            rng.integers(4, size=steps),
        ]
    )
    counts = run_equivalence("easy_small", actions, max_steps)
    if max_steps >= len(path):
        assert counts["terminated"] >= 4  # copy 0 alone reaches G four times
    else:
        assert counts["terminated"] == 0 and counts["truncated"] >= 4
