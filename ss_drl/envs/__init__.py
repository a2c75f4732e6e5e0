"""Maze environments: the layout (:mod:`.maze`), the gymnasium env (:mod:`.gridworld`) and the batched TorchRL env
(:mod:`.batched`). Importing this package registers the ``SSDRL/*-v0`` gymnasium ids."""

import gymnasium as gym

from ss_drl.envs.gridworld import MazeEnv
from ss_drl.envs.maze import (
    PRESETS,
    Maze,
    MazeError,
    load_maze,
    parse_maze,
    random_maze,
)

#: Registered id -> preset name. ``SSDRL/Maze-v0`` takes ``layout=<path to a maze file>``.
ENV_IDS = {
    "SSDRL/Easy-v0": "easy",
    "SSDRL/Medium-v0": "medium",
    "SSDRL/Hard-v0": "hard",
    "SSDRL/Extreme-v0": "extreme",
    "SSDRL/EasySmall-v0": "easy_small",
    "SSDRL/MediumSmall-v0": "medium_small",
    "SSDRL/HardSmall-v0": "hard_small",
}


def register_envs() -> None:
    """Register every ``SSDRL/*-v0`` id with gymnasium (idempotent)."""
    for env_id, preset in {**ENV_IDS, "SSDRL/Maze-v0": None}.items():
        if env_id in gym.registry:
            continue
        kwargs = {} if preset is None else {"layout": preset}
        # No TimeLimit wrapper: the env truncates at its own ``max_steps``.
        gym.register(id=env_id, entry_point="ss_drl.envs.gridworld:MazeEnv", kwargs=kwargs)


register_envs()

__all__ = ["ENV_IDS", "PRESETS", "Maze", "MazeEnv", "MazeError", "load_maze", "parse_maze", "random_maze"]
