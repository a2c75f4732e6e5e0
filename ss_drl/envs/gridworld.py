"""The goal-conditioned gymnasium maze environment (the reference semantics, one maze, one agent)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ss_drl.envs.maze import Maze, goal_reward, load_maze

#: Colours of the rgb_array rendering.
COLORS = {
    "free": (255, 255, 255),
    "wall": (40, 40, 40),
    "start": (220, 50, 50),
    "goal": (40, 170, 60),
    "agent": (30, 90, 220),
}


class MazeEnv(gym.Env):
    """Keulen's grid world as a gymnasium ``GoalEnv``-style environment.

    Actions: 0 right, 1 down, 2 left, 3 up. A move into a wall or off the grid leaves the state unchanged and
    still costs a step. Reward 1.0 and ``terminated=True`` on entering G, else 0.0; ``truncated=True`` after
    ``max_steps`` steps. Observations are ``{"observation", "achieved_goal", "desired_goal"}``, each a (row, col)
    int64 array of shape (2,).

    ``slip``: with this probability the action taken is replaced by one of the four actions drawn uniformly (the
    batched env's convention; the draws come from ``self.np_random``, seeded by ``reset(seed=...)``).
    """

    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 10}

    def __init__(
        self,
        layout: str | Path | Maze = "easy",
        max_steps: int = 1000,
        render_mode: str | None = None,
        cell_pixels: int = 8,
        slip: float = 0.0,
    ):
        self.maze = layout if isinstance(layout, Maze) else load_maze(layout)
        if not 0.0 <= float(slip) <= 1.0:
            raise ValueError(f"slip must be in [0, 1] (got {slip})")
        self.slip = float(slip)
        if int(max_steps) < 1:
            raise ValueError(f"max_steps must be >= 1 (got {max_steps})")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} (got {render_mode!r})")
        self.max_steps = int(max_steps)
        self.render_mode = render_mode
        self.cell_pixels = int(cell_pixels)
        h, w = self.maze.height, self.maze.width
        cell_space = spaces.Box(low=np.array([0, 0]), high=np.array([h - 1, w - 1]), shape=(2,), dtype=np.int64)
        self.observation_space = spaces.Dict(
            {"observation": cell_space, "achieved_goal": cell_space, "desired_goal": cell_space}
        )
        self.action_space = spaces.Discrete(4)
        self._pos = self.maze.start
        self._steps = 0

    # --- GoalEnv interface -------------------------------------------------------------------------------------
    def compute_reward(self, achieved_goal, desired_goal, info) -> np.ndarray | float:
        """1.0 where the achieved (row, col) equals the desired one, else 0.0 (vectorized over leading axes)."""
        hit = np.all(goal_reward(np.asarray(achieved_goal), np.asarray(desired_goal)), axis=-1)
        return hit.astype(np.float64) if hit.ndim else float(hit)

    def compute_terminated(self, achieved_goal, desired_goal, info) -> np.ndarray | bool:
        """True where the desired goal was reached (vectorized over leading axes)."""
        hit = np.all(goal_reward(np.asarray(achieved_goal), np.asarray(desired_goal)), axis=-1)
        return hit if hit.ndim else bool(hit)

    def compute_truncated(self, achieved_goal, desired_goal, info) -> np.ndarray | bool:
        """Truncation depends on the step count only, never on goals."""
        shape = np.asarray(achieved_goal).shape[:-1]
        return np.zeros(shape, dtype=bool) if shape else False

    # --- gymnasium API -----------------------------------------------------------------------------------------
    def _obs(self) -> dict[str, np.ndarray]:
        pos = np.array(self._pos, dtype=np.int64)
        return {"observation": pos, "achieved_goal": pos.copy(), "desired_goal": np.array(self.maze.goal, np.int64)}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._pos = self.maze.start
        self._steps = 0
        return self._obs(), {"is_success": False}

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"invalid action {action!r}: must be an int in [0, 4)")
        action = int(action)
        if self.slip > 0 and self.np_random.random() < self.slip:
            action = int(self.np_random.integers(4))
        self._pos = self.maze.move(self._pos, action)
        self._steps += 1
        obs = self._obs()
        terminated = bool(self.compute_terminated(obs["achieved_goal"], obs["desired_goal"], None))
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], None))
        truncated = not terminated and self._steps >= self.max_steps
        return obs, reward, terminated, truncated, {"is_success": terminated}

    def render(self):
        if self.render_mode == "ansi":
            chars = [list(row) for row in self.maze.to_text().splitlines()]
            r, c = self._pos
            chars[r][c] = "A"
            return "\n".join("".join(row) for row in chars) + "\n"
        if self.render_mode == "rgb_array":
            return render_rgb(self.maze, agent=self._pos, cell_pixels=self.cell_pixels)
        return None


def render_rgb(maze: Maze, agent: tuple[int, int] | None = None, cell_pixels: int = 8) -> np.ndarray:
    """uint8 image (H*px, W*px, 3) of the maze, start, goal and (optionally) the agent."""
    img = np.empty((maze.height, maze.width, 3), dtype=np.uint8)
    img[:] = COLORS["free"]
    img[maze.walls] = COLORS["wall"]
    img[maze.start] = COLORS["start"]
    img[maze.goal] = COLORS["goal"]
    if agent is not None:
        img[tuple(agent)] = COLORS["agent"]
    return np.kron(img, np.ones((cell_pixels, cell_pixels, 1), dtype=np.uint8))
