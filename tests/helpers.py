"""Shared test helpers: the repo root and in-process Hydra composition of the project's config."""

from __future__ import annotations

from pathlib import Path

from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]


def compose_cfg(*overrides: str):
    """The config ``scripts/train.py`` would run with these command-line overrides."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides))


#: Overrides for a run of a few hundred env steps on a tiny network (end-to-end tests of the plumbing).
TINY = [
    "trainer.total_env_steps=300",
    "agent.learning_starts=100",
    "agent.batch_size=16",
    "agent.hidden=[16,16]",
    "agent.embed_dim=8",
    "trainer.eval_interval=150",
]

#: Overrides that turn off every target that reads the count model, for a DQNAgent built without one.
NO_COUNT_MODEL = [
    "agent.distance_ceiling=false",
    "agent.distance_floor=false",
    "agent.bound_all_actions=false",
    "agent.model_targets=false",
    "agent.optimistic_floor=false",
]

#: The spec: steps on a shortest S -> G path of every shipped maze.
SHORTEST = {
    "easy": 31,
    "medium": 72,
    "hard": 138,
    "extreme": 223,
    "easy_small": 19,
    "medium_small": 35,
    "hard_small": 84,
}
