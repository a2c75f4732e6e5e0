"""Atomic checkpoints: everything a run needs to continue exactly where it stopped."""

from __future__ import annotations

import copy
import os
import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from ss_drl.training.config import ConfigError
from ss_drl.training.outputs import CHECKPOINT_FILE, EPISODES_FILE, EVAL_FILE, SUMMARY_FILE

#: Config sections that may differ between a run and its resumption (budgets, logging, the resume flag itself).
RESUMABLE_CHANGES = ("trainer", "logger", "hydra")

#: The checkpoint's format, stored under :data:`FORMAT_KEY` by :meth:`~ss_drl.training.trainer.Trainer.state_dict`.
#: 2: the learners renamed (issue 48: ``agent=dqn`` is the replay-only DQN, ``agent=dqn_bounded`` the model-bounded
#: one; no ``method`` key, no deleted options). A checkpoint without it was written at :data:`LAST_OLD_COMMIT` or
#: before, under the old names: resuming it would continue a run whose config means something else now.
FORMAT = 2
FORMAT_KEY = "format"
#: The last commit that writes and resumes checkpoints of the old format (docs/migration.md).
LAST_OLD_COMMIT = "7ac5009"


def save(state: dict, run_dir: Path) -> Path:
    """Write ``state`` to ``run_dir/checkpoint.pt`` through a temp file and a rename, so a kill never leaves half."""
    path = Path(run_dir) / CHECKPOINT_FILE
    tmp = path.with_suffix(".pt.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def load(run_dir: Path, mmap: bool = False) -> dict:
    """The checkpoint of ``run_dir``; ``mmap``: map the tensors' storage instead of reading it (a cheap look at the
    format and the config, before a run starts)."""
    return torch.load(Path(run_dir) / CHECKPOINT_FILE, map_location="cpu", weights_only=False, mmap=mmap)


def peek(run_dir: Path) -> dict:
    """The checkpoint of ``run_dir`` with its tensors mapped, not read (read whole where torch cannot map the file,
    e.g. one of its legacy format): a cheap look at the format and the config."""
    try:
        return load(run_dir, mmap=True)
    except Exception:  # noqa: BLE001  (torch.load raises many kinds; the plain load raises the one to report)
        return load(run_dir)


def written_before_rename(state) -> bool:
    """Whether a checkpoint was written under the old learner names (no :data:`FORMAT_KEY`, or an older format)."""
    found = state.get(FORMAT_KEY) if isinstance(state, dict) else None
    return found is None or (isinstance(found, int) and not isinstance(found, bool) and found < FORMAT)


def format_problem(state, path: Path) -> str | None:
    """Why a checkpoint cannot be used by this version, its format being another (one line), or None when it can."""
    if written_before_rename(state):
        return f"{path} was written before the learners were renamed (docs/migration.md)"
    if state[FORMAT_KEY] != FORMAT:
        return f"{path} has checkpoint format {state[FORMAT_KEY]!r}, which this version (format {FORMAT}) cannot read"
    return None


def check_format(state, path: Path) -> None:
    """Refuse (:class:`ConfigError`, one line naming ``trainer.resume``) to continue a checkpoint of another
    format: one written under the old learner names continues only with a checkout of :data:`LAST_OLD_COMMIT`."""
    problem = format_problem(state, path)
    if problem is None:
        return
    if written_before_rename(state):
        problem += f": continue it with a checkout of {LAST_OLD_COMMIT}, or start a new run"
    raise ConfigError(f"trainer.resume: {problem}")


def check_resume(cfg: DictConfig, run_dir: Path) -> None:
    """Before anything is written (:class:`~ss_drl.cli.ValidateBeforeRun`): a run that resumes must find a checkpoint
    in ``run_dir`` (``trainer.resume=true`` or a directory), readable, of this :data:`FORMAT`, and written with the
    same config outside :data:`RESUMABLE_CHANGES`. Raises :class:`ConfigError` (one line) otherwise; the trainer
    checks the same when it loads the checkpoint."""
    try:
        if not should_resume(cfg, run_dir):
            return
    except FileNotFoundError as exc:
        raise ConfigError(str(exc)) from None
    path = Path(run_dir) / CHECKPOINT_FILE
    try:
        state = peek(run_dir)
    except Exception as exc:  # noqa: BLE001  (torch.load raises many kinds on a file it cannot read)
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ConfigError(f"trainer.resume: {path} cannot be read ({type(exc).__name__}: {message})") from None
    check_format(state, path)
    if "config" not in state:
        raise ConfigError(f"trainer.resume: {path} holds no config; start the run anew")
    check_compatible(state["config"], task_config(cfg))


def task_config(cfg: DictConfig) -> dict:
    """The resolved config the task (the trainer) sees: ``cfg`` without its ``hydra`` node, as Hydra passes it."""
    if "hydra" in cfg:
        cfg = copy.deepcopy(cfg)
        with read_write(cfg), open_dict(cfg):
            del cfg["hydra"]
    return OmegaConf.to_container(cfg, resolve=True)


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
    """A new run never starts in a directory that holds another run's outputs: it would delete them. That is a run
    with ``trainer.resume`` false, or with ``auto`` in a directory holding a finished run (its summary) but no
    checkpoint to continue. Raises :class:`ConfigError` naming ``key``, the directory and its files."""
    resume = cfg.trainer.resume
    held = run_files(run_dir)
    if not held:
        return
    if resume == "auto" and SUMMARY_FILE in held and CHECKPOINT_FILE not in held:
        raise ConfigError(
            f"{key}: {run_dir} holds a finished run ({', '.join(held)}) but no {CHECKPOINT_FILE} that "
            "trainer.resume=auto could continue; give another directory"
        )
    if resumes(resume):
        return
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
            raise ConfigError(f"trainer.resume: config '{key}' differs from the checkpoint's; resume with the same one")


def rng_state() -> dict:
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
