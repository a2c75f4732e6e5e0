"""Atomic checkpoints: everything a run needs to continue exactly where it stopped."""

from __future__ import annotations

import copy
import dataclasses
import os
import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from ss_drl.training.config import ConfigError
from ss_drl.training.outputs import CHECKPOINT_FILE, CHECKPOINT_PREV_FILE, EPISODES_FILE, EVAL_FILE, SUMMARY_FILE

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


def save(state: dict, run_dir: Path, keep_previous: bool = True) -> Path:
    """Write ``state`` to ``run_dir/checkpoint.pt``, keeping the checkpoint it replaces as ``checkpoint.prev.pt``
    (when ``keep_previous``). Three steps, each atomic:

    1. ``state`` goes to ``checkpoint.pt.tmp``, flushed to disk (fsync);
    2. ``checkpoint.pt`` is renamed to ``checkpoint.prev.pt`` (replacing the one before it);
    3. ``checkpoint.pt.tmp`` is renamed to ``checkpoint.pt``, and the directory is flushed.

    A kill or a crash at any point leaves a whole, readable checkpoint: before step 2, ``checkpoint.pt`` as it was
    (the temp file is never read); between steps 2 and 3, ``checkpoint.prev.pt`` (``checkpoint.pt`` is missing, and
    :func:`resume_from` continues from the previous one); after step 3, both. The caller passes ``keep_previous``
    false when ``checkpoint.pt`` is not known to be readable (a resume that fell back past it): step 2 is skipped, so
    a damaged file never becomes ``checkpoint.prev.pt``, and the two files are never two copies of a damaged one."""
    run_dir = Path(run_dir)
    path = run_dir / CHECKPOINT_FILE
    tmp = path.with_suffix(".pt.tmp")
    torch.save(state, tmp)
    _fsync(tmp)
    if keep_previous and path.exists():
        os.replace(path, run_dir / CHECKPOINT_PREV_FILE)
    os.replace(tmp, path)
    _fsync(run_dir)
    return path


def _fsync(path: Path) -> None:
    """Flush a file's data, or a directory's entries (its renames), to disk (a no-op where the OS cannot)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # a directory on Windows
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class UnreadableCheckpoint(ConfigError):
    """A checkpoint file torch cannot read: ``str(err)`` is one line naming the file and the reason. ``damaged``:
    the file is truncated or corrupt (what :func:`resume_from` falls back past), not one it cannot open or whose
    pickle names code this version lacks (written by another version of ss-drl or of its libraries)."""

    def __init__(self, message: str, damaged: bool = True):
        super().__init__(message)
        self.damaged = damaged


#: What ``torch.load`` raises for a file that is whole but not for this code (a class or module it names is missing)
#: or one it may not open: refused, never fallen back past (the file would be overwritten at the next checkpoint).
NOT_DAMAGE = (ImportError, AttributeError, PermissionError, IsADirectoryError)


def read(path: Path, mmap: bool = False) -> dict:
    """The checkpoint in the file ``path``; ``mmap``: map the tensors' storage instead of reading it (a cheap look at
    the format and the config; a file torch cannot map, e.g. of its legacy format, is read whole). Raises
    :class:`UnreadableCheckpoint` (one line) when torch cannot read it: truncated, corrupt, or pickled by other code.
    """
    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=False, mmap=mmap)
    except Exception as exc:  # noqa: BLE001  (torch.load raises many kinds: pickle, zip, EOF, OS, Runtime errors)
        error = exc
    if mmap:
        try:
            return torch.load(path, map_location="cpu", weights_only=False)
        except Exception as exc:  # noqa: BLE001  (the plain load raises the one to report)
            error = exc
    raise UnreadableCheckpoint(f"{path} cannot be read ({_reason(error)})", damaged=not isinstance(error, NOT_DAMAGE))


def _reason(exc: Exception) -> str:
    """``Type: message`` in one line: the message's first line, up to its first sentence's end (torch appends a
    paragraph of advice to its zip reader's errors)."""
    lines = str(exc).strip().splitlines()
    message = lines[0].split(". ")[0] if lines else ""
    return f"{type(exc).__name__}: {message}" if message else type(exc).__name__


def load(run_dir: Path, mmap: bool = False) -> dict:
    """The checkpoint of ``run_dir`` (its ``checkpoint.pt``; :func:`read`)."""
    return read(Path(run_dir) / CHECKPOINT_FILE, mmap=mmap)


def peek(run_dir: Path) -> dict:
    """The checkpoint of ``run_dir`` with its tensors mapped, not read: a cheap look at the format and the config."""
    return load(run_dir, mmap=True)


@dataclasses.dataclass(frozen=True)
class Resumption:
    """The checkpoint a resumed run continues from (:func:`resume_from`)."""

    path: Path  # checkpoint.pt, or checkpoint.prev.pt when checkpoint.pt is damaged or missing
    state: dict
    warning: str | None  # one line, when it is checkpoint.prev.pt: which file was passed over and why

    @property
    def fell_back(self) -> bool:
        return self.warning is not None


def resume_from(run_dir: Path, mmap: bool = False) -> Resumption:
    """Which checkpoint of ``run_dir`` a resumed run continues from: the one function that decides, for the check
    before anything is written (:func:`check_resume`, ``mmap``) and for the trainer (the full load).

    ``checkpoint.pt`` when torch can read it and it is of this :data:`FORMAT`. When it is damaged (truncated or
    corrupt: :attr:`UnreadableCheckpoint.damaged`) or missing (a save cut between its renames, :func:`save`),
    ``checkpoint.prev.pt``, when that one is readable and of this format, with a one-line warning. Raises
    :class:`ConfigError` (one line naming ``trainer.resume``): :class:`UnreadableCheckpoint` when no file can be
    read, the format refusal of :func:`check_format` when the file chosen is of another format. A readable
    ``checkpoint.pt`` of another format is refused, never passed over: it is the run's latest state, written by
    another version, and continuing from the one before it would drop that version's progress and mix two versions.
    ``FileNotFoundError`` when neither file exists."""
    run_dir = Path(run_dir)
    path, prev = run_dir / CHECKPOINT_FILE, run_dir / CHECKPOINT_PREV_FILE
    if path.exists():
        try:
            state = read(path, mmap=mmap)
        except UnreadableCheckpoint as exc:
            if not exc.damaged or not prev.exists():
                hint = "" if not exc.damaged else f"; there is no {prev.name} to fall back to"
                raise UnreadableCheckpoint(f"trainer.resume: {exc}{hint}", exc.damaged) from None
            problem = str(exc)
        else:
            check_format(state, path)
            return Resumption(path, state, None)
    elif prev.exists():
        problem = f"{path} is missing"
    else:
        raise FileNotFoundError(f"trainer.resume: no checkpoint to resume at {path}")
    try:
        state = read(prev, mmap=mmap)
    except UnreadableCheckpoint as exc:
        raise UnreadableCheckpoint(f"trainer.resume: {problem}, and {exc}", exc.damaged) from None
    other = format_problem(state, prev)
    if other is not None:
        if written_before_rename(state):
            other += f": continue it with a checkout of {LAST_OLD_COMMIT}, or start a new run"
        raise ConfigError(f"trainer.resume: {problem}, and {other}")
    at = env_steps_done(state)
    where = "" if at is None else f" (env step {at})"
    warning = f"trainer.resume: {problem}; continuing from {prev}{where}, the checkpoint before it"
    return Resumption(prev, state, warning)


def written_before_rename(state) -> bool:
    """Whether a checkpoint was written under the old learner names (no :data:`FORMAT_KEY`, or an older format)."""
    if not isinstance(state, dict):  # not a checkpoint of any version (format_problem says so)
        return False
    found = state.get(FORMAT_KEY)
    return found is None or (isinstance(found, int) and not isinstance(found, bool) and found < FORMAT)


def format_problem(state, path: Path) -> str | None:
    """Why a checkpoint cannot be used by this version, its format being another (one line), or None when it can."""
    if not isinstance(state, dict):  # torch read it, but it holds no checkpoint (a list, a tensor, ...)
        return f"{path} holds a {type(state).__name__}, not a checkpoint"
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
    same config outside :data:`RESUMABLE_CHANGES`: ``checkpoint.pt``, or ``checkpoint.prev.pt`` when that one is
    damaged (:func:`resume_from`, which the trainer's load calls too, and which warns there). Raises
    :class:`ConfigError` (one line) otherwise; the trainer checks the same when it loads the checkpoint."""
    try:
        if not should_resume(cfg, run_dir):
            return
        resumption = resume_from(run_dir, mmap=True)
    except FileNotFoundError as exc:
        raise ConfigError(str(exc)) from None
    check_continuable(resumption.state, resumption.path, task_config(cfg))


def check_continuable(state: dict, path: Path, current: dict) -> None:
    """A checkpoint a run with the config ``current`` can continue: one the trainer can read (:func:`check_state`),
    written with the same config (:func:`check_compatible`), and not past ``trainer.total_env_steps``: a budget
    below the env steps already run would rewrite a finished run's outputs under a budget it did not run to (the
    last quarter that decides "learned" is the budget's). :class:`ConfigError` (one line) otherwise."""
    check_state(state, path, "trainer.resume: ")
    check_compatible(state["config"], current)
    done = env_steps_done(state)
    budget = (current.get("trainer") or {}).get("total_env_steps")
    if done is not None and isinstance(budget, int) and budget < done:
        raise ConfigError(
            f"trainer.total_env_steps: {budget} is below the {done} env steps {path} has run; continue it with a "
            f"budget of at least {done}"
        )


def env_steps_done(state: dict) -> int | None:
    """The env steps a checkpoint's run had taken (None when its collector state does not say)."""
    collector = state.get("collector")
    at = collector.get("env_steps") if isinstance(collector, dict) else None
    return at if isinstance(at, int) else None


#: What the trainer reads from a checkpoint of this :data:`FORMAT` (``eval_rng``, ``last_success_rate`` and
#: ``update_log`` may be absent: older checkpoints of the format lack them, and the trainer starts them anew).
STATE_KEYS = (
    "agent", "counts", "smart_start", "collector", "episodes", "first_goal", "last_accuracy", "evals", "next_eval",
    "next_checkpoint", "next_log", "ss_targets", "recent", "wall_s", "rows", "rng", "config",
)  # fmt: skip


def check_state(state: dict, path: Path, prefix: str = "") -> None:
    """A checkpoint of this format that the trainer can continue from: every :data:`STATE_KEYS` entry there, and the
    config a mapping. Raises :class:`ConfigError` (one line naming ``path``, after ``prefix``) otherwise: before the
    run starts (:func:`check_resume`), when the trainer loads it, and in evaluate.py."""
    if "evals" not in state and "agent" in state:  # written before 844f19d: no evaluation list, an older loop's state
        raise ConfigError(f"{prefix}{path} predates the list of evaluations; start the run anew")
    missing = [key for key in STATE_KEYS if key not in state]
    if missing:
        raise ConfigError(f"{prefix}{path} lacks {', '.join(missing)}: not a checkpoint this trainer wrote")
    if not isinstance(state["config"], dict):
        raise ConfigError(f"{prefix}{path} holds no config mapping; start the run anew")


def task_config(cfg: DictConfig) -> dict:
    """The resolved config the task (the trainer) sees: ``cfg`` without its ``hydra`` node, as Hydra passes it."""
    if "hydra" in cfg:
        cfg = copy.deepcopy(cfg)
        with read_write(cfg), open_dict(cfg):
            del cfg["hydra"]
    return OmegaConf.to_container(cfg, resolve=True)


#: Files whose presence shows that a run was written in a directory (a new run there would delete them).
RUN_FILES = (CHECKPOINT_FILE, CHECKPOINT_PREV_FILE, SUMMARY_FILE, EPISODES_FILE, EVAL_FILE)


def resumes(resume) -> bool:
    """Whether a ``trainer.resume`` value continues a run (true, ``auto`` or a run directory), not starts one."""
    return resume not in (False, None, "false", "")


def should_resume(cfg, run_dir: Path) -> bool:
    """Whether this run continues from a checkpoint in ``run_dir``: ``trainer.resume`` true or a path (the
    checkpoint must exist), or ``auto`` (continue if there is one, else start the run). ``checkpoint.prev.pt``
    counts: :func:`resume_from` continues from it when ``checkpoint.pt`` is missing (a save cut between its renames).
    """
    resume = cfg.trainer.resume
    if not resumes(resume):
        return False
    path = Path(run_dir) / CHECKPOINT_FILE
    found = path.exists() or (Path(run_dir) / CHECKPOINT_PREV_FILE).exists()
    if resume == "auto":
        return found
    if not found:
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
    if resume == "auto" and SUMMARY_FILE in held and CHECKPOINT_FILE not in held and CHECKPOINT_PREV_FILE not in held:
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


#: Config keys added after runs of this checkpoint format (:data:`FORMAT`, from 327f876) were written, each with the
#: value that reproduces what those runs did (the option off, or a setting those runs' code had no other way of
#: doing): a checkpoint whose config lacks one resumes as if it held that value (and is refused if the resumption sets
#: another). Filled in only where the resuming config has the key (a tabular run's agent has none of the DQN's).
ADDED_KEYS = {
    ("agent", "factored_bootstrap"): False,  # 0abc644
    ("agent", "successor_double_dqn"): True,  # 0abc644: the successors took the online network's greedy action
    ("agent", "sparse_tables"): False,  # f49bbcc
    ("env", "slip"): 0.0,  # 24e1157
    ("smart_start", "select"): "visited",  # cfc9e1d: the paper's Smart Start
    ("smart_start", "explore"): "epsilon_greedy",  # cfc9e1d
    ("smart_start", "explore_after_goal"): True,  # cfc9e1d (with the paper's select and explore, either reads alike)
    ("smart_start", "guided_limit"): None,  # 4d36adf (a limit only under slips, which did not exist)
    ("smart_start", "explore_from_start"): False,  # ed255e7
    ("smart_start", "greedy_path"): False,  # cde4c7c
}


def check_compatible(saved: dict, current: dict) -> None:
    """Resuming with a different maze, agent, HER or Smart Start setup, or seed, would mix two runs: refuse it."""
    saved = copy.deepcopy(saved)
    for (section, key), value in ADDED_KEYS.items():
        if isinstance(saved.get(section), dict) and key in (current.get(section) or {}):
            saved[section].setdefault(key, value)
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
