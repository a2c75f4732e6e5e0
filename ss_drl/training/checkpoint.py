"""Atomic checkpoints: everything a run needs to continue exactly where it stopped."""

from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch

from ss_drl.training.outputs import CHECKPOINT_FILE

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


def should_resume(cfg, run_dir: Path) -> bool:
    """Whether this run continues from a checkpoint in ``run_dir`` (``trainer.resume`` true or a path)."""
    resume = cfg.trainer.resume
    if resume in (False, None, "false", ""):
        return False
    path = Path(run_dir) / CHECKPOINT_FILE
    if not path.exists():
        raise FileNotFoundError(f"trainer.resume: no checkpoint to resume at {path}")
    return True


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
