"""Shared test helpers: the repo root, in-process Hydra composition of the project's config, and a run that crashes
right after a checkpoint save (to resume it and compare its CSVs with an uninterrupted run's)."""

from __future__ import annotations

import csv
import subprocess
import time
from pathlib import Path

import pytest
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
    "agent.bounded_policy=false",
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

#: The CSV columns that measure wall-clock time: they differ between two runs that are otherwise the same.
WALL_CLOCK = ("wall_s", "updates_per_s")


class Crash(Exception):
    """A crash planted by a test."""


def crash_after_save(trainer, saves: int) -> list[int]:
    """Train ``trainer`` (a :class:`~ss_drl.training.trainer.Trainer`) and crash (raise :class:`Crash`, caught here)
    right after its ``saves``-th checkpoint save, leaving its run directory as a run killed there leaves it.

    Returns the env step of each save. Fails the test if the run ends before that save.
    """
    real_save = trainer.save_checkpoint
    steps: list[int] = []

    def save_then_crash():
        path = real_save()
        steps.append(trainer.collector.env_steps)
        if len(steps) == saves:
            raise Crash
        return path

    trainer.save_checkpoint = save_then_crash  # this instance only: a crashed trainer is not used again
    with pytest.raises(Crash):
        trainer.train()
    return steps


def rows_without_wall_clock(path: Path) -> list[list[str]]:
    """The rows of a CSV file, header included, without the :data:`WALL_CLOCK` columns."""
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    keep = [i for i, name in enumerate(rows[0]) if name not in WALL_CLOCK]
    return [[row[i] for i in keep] for row in rows]


def assert_resume_equals_uninterrupted(run: list[str], root: Path, saves: int = 2) -> Path:
    """Train the run of command-line overrides ``run`` twice under ``root``: once through (``root/full``), and once
    crashed right after its ``saves``-th checkpoint and resumed (``root/cut``); assert that the two give the same
    episodes.csv, eval.csv and train.csv (wall clock aside). Returns the uninterrupted run's directory."""
    from ss_drl.training.outputs import EPISODES_FILE, EVAL_FILE, TRAIN_FILE
    from ss_drl.training.trainer import Trainer

    full, cut = root / "full", root / "cut"
    Trainer(compose_cfg(*run), full).train()
    crash_after_save(Trainer(compose_cfg(*run), cut), saves)
    Trainer(compose_cfg(*run, "trainer.resume=true"), cut).train()
    for file in (EPISODES_FILE, EVAL_FILE, TRAIN_FILE):
        assert rows_without_wall_clock(cut / file) == rows_without_wall_clock(full / file), file
    return full


def wait_for(condition, what: str, proc: subprocess.Popen, timeout_s: float) -> None:
    """Poll ``condition`` until it holds; fail clearly if the child exits first or ``timeout_s`` passes."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if proc.poll() is not None:
            pytest.fail(f"the training run exited (code {proc.returncode}) before {what}")
        if time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            pytest.fail(f"no {what} within {timeout_s:.0f} s")
        time.sleep(0.05)
