"""Atomic checkpoints: everything a run needs to continue exactly where it stopped."""

from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch

from ss_drl.training.config import ConfigError
from ss_drl.training.outputs import CHECKPOINT_FILE, EPISODES_FILE, EVAL_FILE, SUMMARY_FILE

#: Config sections that may differ between a run and its resumption (budgets, logging, the resume flag itself).
RESUMABLE_CHANGES = ("trainer", "logger", "hydra")


def save(state: dict, run_dir: Path) -> Path:
    """Write ``state`` to ``run_dir/checkpoint.pt`` through a temp file and a rename, so a kill never leaves half."""
    path = Path(run_dir) / CHECKPOINT_FILE
    tmp = path.with_suffix(".pt.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def load(run_dir: Path) -> dict:
    return torch.load(Path(run_dir) / CHECKPOINT_FILE, map_location="cpu", weights_only=False)


#: Files whose presence shows that a run was written in a directory (a new run there would delete them).
RUN_FILES = (CHECKPOINT_FILE, SUMMARY_FILE, EPISODES_FILE, EVAL_FILE)


def resumes(resume) -> bool:
    """Whether a ``trainer.resume`` value continues a run (true, ``auto`` or a run directory), not starts one."""
    return resume not in (False, None, "false", "")


def should_resume(cfg, run_dir: Path) -> bool:
    """Whether this run continues from a checkpoint in ``run_dir``: ``trainer.resume`` true or a path (the
    checkpoint must exist), or ``auto`` (continue if there is one, else start the run)."""
    resume = cfg.trainer.resume
    if not resumes(resume):
        return False
    path = Path(run_dir) / CHECKPOINT_FILE
    if resume == "auto":
        return path.exists()
    if not path.exists():
        raise FileNotFoundError(f"trainer.resume: no checkpoint to resume at {path}")
    return True


def run_files(run_dir: Path) -> list[str]:
    """The files of :data:`RUN_FILES` that ``run_dir`` holds."""
    return [name for name in RUN_FILES if (Path(run_dir) / name).is_file()]


def refuse_overwrite(cfg, run_dir: Path, key: str = "hydra.run.dir") -> None:
    """A new run (``trainer.resume`` false) never starts in a directory that holds another run's outputs: it
    would delete them. Raises :class:`ConfigError` naming ``key``, the directory and its files."""
    if resumes(cfg.trainer.resume):
        return
    held = run_files(run_dir)
    if held:
        raise ConfigError(
            f"{key}: {run_dir} already holds a run ({', '.join(held)}); continue it with trainer.resume=true "
            "(or auto), or give another directory"
        )


def check_compatible(saved: dict, current: dict) -> None:
    """Resuming with a different maze, agent, HER or Smart Start setup, or seed, would mix two runs: refuse it."""
    for key in sorted(set(saved) | set(current)):
        if key in RESUMABLE_CHANGES:
            continue
        if saved.get(key) != current.get(key):
            raise ValueError(f"trainer.resume: config '{key}' differs from the checkpoint's; resume with the same one")


def rng_state() -> dict:
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
