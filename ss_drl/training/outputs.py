"""The files a run writes: the single source of truth for their names and columns.

These are a contract: plots, sweeps and external scripts parse them.

* ``episodes.csv``: one row per finished training episode (``EPISODE_COLUMNS``).
* ``eval.csv``: one row per greedy evaluation (``EVAL_COLUMNS``).
* ``train.csv``: learning metrics every ``trainer.log_interval`` updates (``TRAIN_COLUMNS``).
* ``summary.json``: run-level numbers (``SUMMARY_KEYS``) and the resolved config.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
import warnings
from pathlib import Path

EPISODES_FILE = "episodes.csv"
EVAL_FILE = "eval.csv"
TRAIN_FILE = "train.csv"
SUMMARY_FILE = "summary.json"
CHECKPOINT_FILE = "checkpoint.pt"
CHECKPOINT_PREV_FILE = "checkpoint.prev.pt"  # the checkpoint before checkpoint.pt (resume falls back to it)
FAILED_FILE = "FAILED"  # written by a sweep job that failed (its message or traceback)

EPISODE_COLUMNS = (
    "episode",  # 1-based index over all finished training episodes of the run (all env copies)
    "env_id",  # which env copy ran the episode
    "env_steps",  # cumulative env steps of the run (all copies) when the episode ended
    "length",  # steps in the episode
    "return",  # undiscounted return (1 on reaching G, else 0)
    "success",  # 1 if G was reached
    "smart_start",  # 1 if the episode began with a Smart Start guided phase
    "ss_target",  # the smart start state S_ss as "row:col" ("" when no guided phase)
    "ss_reached",  # 1 if the guided phase reached S_ss (within theta)
    "ss_steps",  # steps spent in the guided phase
    "epsilon",  # exploration epsilon when the episode ended
    "end_state",  # the cell the episode ended in, as "row:col" (G on success; where the agent was when it was cut)
    "states_visited",  # exploration coverage: distinct cells departed from so far, this episode included
    "new_moves",  # moves (cell, action) tried for the first time in the run during this episode
    "new_moves_after_ss",  # of them, after the guided phase (0 without one)
    "explore_steps",  # steps of Smart Start's exploration phase (smart_start.explore; 0 without one)
    "ss_frontier_steps",  # steps on the count model from S_ss to the nearest untried move at the start (-1: none)
    "minigrid_return",  # MiniGrid's own return, 1 - 0.9 length / max_steps on reaching G, else 0 (empty on mazes)
    "wall_s",  # seconds since the run started (the last column)
)

EVAL_COLUMNS = (
    "env_steps",  # cumulative env steps at evaluation time
    "episode",  # finished training episodes at evaluation time
    "eval_length",  # steps of the greedy episode from S (max_steps when it fails); under slips the episodes' mean
    "eval_success",  # 1 if the greedy episode (every one of them, under slips) reached G
    "eval_success_rate",  # share of the evaluation's episodes that reached G (trainer.eval_episodes; 1 without slips)
    "wall_s",  # seconds since the run started (eval.csv files from before this column load without it)
)

TRAIN_COLUMNS = (
    "env_steps",  # cumulative env steps when the row was written
    "updates",  # learning updates so far (tabular: one per transition)
    "loss",  # mean TD loss over the updates since the previous row
    "q_mean",  # mean Q(s||g, a) of the sampled batches' actions, on the learner's reward scale
    "td_abs",  # mean |TD error| of the sampled batches
    "her_share",  # mean fraction of each batch whose goal HER relabeled
    "goal_share",  # mean fraction of each batch whose goal is the maze's goal G
    "epsilon",  # exploration epsilon
    "updates_per_s",  # learning updates per second since the previous row
    "wall_s",  # seconds since the run started
)

SUMMARY_KEYS = (
    "experiment",  # experiment name (e.g. "easy_ss_her")
    "method",  # the method label, derived from the resolved config (ss_drl/methods.py; e.g. "ss_her", "dqn_bounded")
    "maze",  # maze name (preset or file)
    "seed",
    "completed",  # True once the run reached trainer.total_env_steps
    "first_goal_env_step",  # env steps when G was first reached (null if never)
    "first_goal_episode",  # episode index when G was first reached (null if never)
    "episodes",  # finished training episodes
    "env_steps",  # env steps taken
    "final_eval_length",  # length of the last greedy evaluation
    "final_greedy_accuracy",  # at the last evaluation: fraction of states whose greedy action is on a shortest path
    "final_eval_success_rate",  # share of the last evaluation's episodes that reached G
    "optimal_length",  # BFS shortest path S -> G; under slips the optimal policy's expected steps from S
    "slip",  # env.slip: probability that an action is replaced by one drawn uniformly
    "eval_episodes",  # greedy episodes per evaluation (trainer.eval_episodes; derived from env.slip when null)
    # The "learned" rule (ss_drl.training.learned): an evaluation is within bound when it succeeds within
    # 1.05 x optimal_length; the run is learned when >= 90% of its last-quarter evaluations are.
    "learned_env_step",  # env steps at the first evaluation of the streak that stays within bound (null if not learned)
    "learned_wall_s",  # the run's wall seconds at that evaluation (null if not learned)
    "last_quarter_within",  # fraction of evaluations after 75% of the budget within bound (null if there are none)
    "wall_s",  # run time in seconds
    "env_steps_per_s",
    "updates_per_s",
    "smart_start_decisions",  # guided phases started (0 without Smart Start)
    "greedy_path_decisions",  # of them, sent to an untried move on the greedy path (smart_start.greedy_path)
    "bounds_in_force",  # the TD target's bounds that ran, then the switches shaping them (see DQNAgent.bounds_in_force)
    "config",  # the resolved Hydra config
)


def _csv_rows(path: Path) -> int:
    """Data rows in a CSV file (0 if missing)."""
    if not path.exists():
        return 0
    with path.open() as f:
        return max(sum(1 for _ in f) - 1, 0)


def _header(path: Path) -> list[str] | None:
    """The header row of a CSV file (None if the file is missing or empty)."""
    if not path.exists():
        return None
    with path.open(newline="") as f:
        return next(csv.reader(f), None)


def truncate_csv(path: Path, keep_rows: int) -> None:
    """Keep the header and the first ``keep_rows`` data rows (used on resume, to drop rows after the checkpoint)."""
    if not path.exists():
        return
    # newline="": the rows keep their bytes (the csv module ends them with \r\n); text mode would rewrite the kept
    # rows with \n and leave a file of mixed line endings once the resumed run appends.
    with path.open(newline="") as f:
        lines = f.readlines()
    tmp = path.with_suffix(path.suffix + ".tmp")
    with tmp.open("w", newline="") as f:
        f.write("".join(lines[: keep_rows + 1]))
    os.replace(tmp, path)


def write_json_atomic(path: Path, data: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False, default=str) + "\n")
    os.replace(tmp, path)


class RunLogger:
    """Writes episodes.csv and eval.csv (always), and mirrors metrics to W&B when it is on.

    W&B never blocks training: if wandb is missing or its init fails, the run goes on with CSV and one warning.
    """

    def __init__(self, run_dir: Path, cfg, resolved_config: dict, resume_rows: tuple[int, ...] | None = None):
        """``resume_rows``: the rows of episodes.csv, eval.csv and train.csv to keep (those the checkpoint had
        written); None starts the files anew."""
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.episodes_path = self.run_dir / EPISODES_FILE
        self.eval_path = self.run_dir / EVAL_FILE
        self.train_path = self.run_dir / TRAIN_FILE
        paths = (self.episodes_path, self.eval_path, self.train_path)
        if resume_rows is None:
            for path in paths:
                path.unlink(missing_ok=True)
        else:
            # Checked before any file is cut back, so that a refused resume leaves the run as it was.
            for path, columns in zip(paths, (EPISODE_COLUMNS, EVAL_COLUMNS, TRAIN_COLUMNS)):
                header = _header(path)
                if header is not None and tuple(header) != columns:
                    # Rows of another width appended under the old header would leave a file no one can parse.
                    raise ValueError(
                        f"trainer.resume: {path.name} has columns {','.join(header)} but this version writes "
                        f"{','.join(columns)}; start the run anew"
                    )
            for path, rows in zip(paths, resume_rows):
                truncate_csv(path, rows)
        self._episodes = self._open(self.episodes_path, EPISODE_COLUMNS)
        self._eval = self._open(self.eval_path, EVAL_COLUMNS)
        self._train = self._open(self.train_path, TRAIN_COLUMNS)
        self.episode_rows = _csv_rows(self.episodes_path)
        self.eval_rows = _csv_rows(self.eval_path)
        self.train_rows = _csv_rows(self.train_path)
        self.wandb = self._init_wandb(cfg, resolved_config)

    @property
    def rows(self) -> tuple[int, int, int]:
        """Rows written to episodes.csv, eval.csv and train.csv (kept in checkpoints, for resuming)."""
        return self.episode_rows, self.eval_rows, self.train_rows

    @staticmethod
    def _open(path: Path, columns: tuple[str, ...]):
        new = _header(path) is None
        handle = path.open("a", newline="")
        writer = csv.writer(handle)
        if new:
            writer.writerow(columns)
        return handle, writer

    def _init_wandb(self, cfg, resolved_config: dict):
        logger_cfg = cfg.logger
        if logger_cfg.backend != "wandb" or logger_cfg.mode == "disabled":
            return None
        try:
            import wandb

            from ss_drl.methods import method_label

            label = method_label(resolved_config)
            return wandb.init(
                project=logger_cfg.project,
                entity=logger_cfg.entity,
                group=wandb_group(logger_cfg.group, str(cfg.experiment), label),
                job_type=label,
                name=f"{cfg.experiment}-seed{cfg.seed}",
                mode=logger_cfg.mode,
                dir=str(self.run_dir),
                config=resolved_config,
                reinit="finish_previous",
                resume="allow",
                id=self._wandb_id(),
            )
        except Exception as exc:  # noqa: BLE001  (any failure of an optional dashboard must not stop training)
            warnings.warn(f"W&B is off for this run: wandb init failed ({type(exc).__name__}: {exc})", stacklevel=2)
            return None

    def _wandb_id(self) -> str:
        """A stable W&B run id per run directory, so a resumed run continues the same W&B run."""
        path = self.run_dir / ".wandb_id"
        if not path.exists():
            import secrets

            path.write_text(secrets.token_hex(8))
        return path.read_text().strip()

    def log_episode(self, row: dict) -> None:
        self._episodes[1].writerow([row[c] for c in EPISODE_COLUMNS])
        self.episode_rows += 1
        if self.episode_rows % 50 == 0:
            self._episodes[0].flush()

    def log_eval(self, row: dict) -> None:
        self._eval[1].writerow([row[c] for c in EVAL_COLUMNS])
        self.eval_rows += 1
        # Every evaluation brings all three files on disk up to date, so that a user (or a script) reading them
        # during a run sees each episode within one evaluation interval of its end.
        self.flush()

    def log_train(self, row: dict) -> None:
        self._train[1].writerow([row[c] for c in TRAIN_COLUMNS])
        self.train_rows += 1

    def log_metrics(self, metrics: dict, step: int) -> None:
        if self.wandb is not None:
            clean = {k: v for k, v in metrics.items() if not (isinstance(v, float) and math.isnan(v))}
            self.wandb.log(clean, step=step)

    def log_image(self, key: str, path: Path, step: int) -> None:
        if self.wandb is not None:
            import wandb

            self.wandb.log({key: wandb.Image(str(path))}, step=step)

    def flush(self) -> None:
        for handle, _ in (self._episodes, self._eval, self._train):
            handle.flush()

    def close(self, summary: dict | None = None) -> None:
        self.flush()
        for handle, _ in (self._episodes, self._eval, self._train):
            handle.close()
        if self.wandb is not None:
            if summary:
                for key, value in summary.items():
                    if key != "config" and value is not None:
                        self.wandb.summary[key] = value
            self.wandb.finish()
            self.wandb = None


def wandb_group(group: str | None, experiment: str, label: str) -> str:
    """The W&B group of a run: ``logger.group`` if set, else the experiment name when it names the method that ran
    (``easy_ss_her`` for ``ss_her``, ``easy_ss_her_bounded`` for ``ss_her_bounded``), else the experiment name with
    that method label (``easy_ss_her[ss_her_bounded]`` for ``+experiment=easy_ss_her agent=dqn_bounded``): a group
    never puts one learner's runs under the other's name."""
    if group:
        return str(group)
    if experiment == label or experiment.endswith("_" + label):
        return experiment
    return f"{experiment}[{label}]"


def progress_bar(total: int, initial: int = 0):
    """A tqdm bar on a terminal; quiet (disabled) when stderr is not a terminal."""
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="step", disable=not sys.stderr.isatty(), dynamic_ncols=True)
