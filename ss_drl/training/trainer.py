"""The training loop: collect, count, store, update, log, evaluate, checkpoint.

One iteration of :meth:`Trainer.train`, read top to bottom:

1. **Collect**: ``collector.rollout()`` steps the env for up to ``frames_per_batch`` transitions. An episode starts
   with Smart Start's guided phase where it applies (S_ss chosen by UCB, a route planned on the count model), then
   the agent's epsilon-greedy phase takes over. A batch ends where an episode ends.
2. **Count model**: every transition of the batch is counted (Smart Start reads the counts at the next episode start).
3. **Replay buffer**: ``agent.store(batch)`` (the DQN's HER buffer; the table queues the batch).
4. **Updates**: the ``agent.updates_due(...)`` learning updates; each returns its metrics as a tensor (no host sync).
5. **Log**: every ``log_interval`` updates a row of train.csv and W&B ``train/`` (the loss is checked for NaN then);
   every finished episode a row of episodes.csv; every ``eval_interval`` env steps a greedy episode from S to
   eval.csv; every ``checkpoint_interval`` env steps an atomic checkpoint.
"""

from __future__ import annotations

import dataclasses
import random
import signal
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from ss_drl.agents import UPDATE_METRICS, Agent
from ss_drl.envs.batched import BatchedMazeEnv
from ss_drl.envs.maze import Maze, load_maze, state_cells
from ss_drl.methods import method_label
from ss_drl.ops import linear_schedule
from ss_drl.smart_start import CountModel, Frontier, Planner, SmartStart
from ss_drl.training import checkpoint as ckpt
from ss_drl.training.collector import Episode, MazeCollector
from ss_drl.training.config import validate_config
from ss_drl.training.figures import plot_visit_counts
from ss_drl.training.greedy import evaluate_policy, evaluation_episodes, greedy_accuracy, greedy_policy, optimum
from ss_drl.training.learned import EvalRecord, learned
from ss_drl.training.outputs import (
    FAILED_FILE,
    SUMMARY_FILE,
    RunLogger,
    progress_bar,
    write_json_atomic,
)


class TrainingInterrupted(Exception):
    """SIGINT/SIGTERM arrived; a final checkpoint was written. ``signum`` is the signal."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum


@dataclasses.dataclass
class FirstGoal:
    """When G was first reached in training."""

    env_step: int | None = None
    episode: int | None = None


class UpdateLog:
    """The metrics of the updates since the last train.csv row, kept as tensors until the row is written."""

    def __init__(self, first_update: int = 0):
        self.rows: list[torch.Tensor] = []
        self.first_update = first_update  # update count before the first row held here
        self.start = time.perf_counter()

    def add(self, metrics: torch.Tensor) -> None:
        self.rows.append(metrics)

    def state_dict(self) -> dict:
        """The metrics held for the next row (kept in checkpoints: a resumed run's next row averages the same updates
        as an uninterrupted run's)."""
        return {"rows": list(self.rows), "first_update": self.first_update}

    def load_state_dict(self, state: dict) -> None:
        self.rows, self.first_update = list(state["rows"]), state["first_update"]

    def check_finite(self, updates: int) -> torch.Tensor | None:
        """The held metrics as one (rows, metrics) tensor (one host sync; None if empty). A non-finite loss raises
        ``FloatingPointError`` naming the first update that had it."""
        if not self.rows:
            return None
        values = torch.stack(self.rows).double()
        finite = torch.isfinite(values[:, 0])
        if not bool(finite.all()):
            bad = int((~finite).nonzero()[0, 0])
            per_row = (updates - self.first_update) / len(self.rows)  # the table's rows hold many updates each
            raise FloatingPointError(
                f"non-finite DQN loss ({float(values[bad, 0])}) at update {self.first_update + int(bad * per_row)}"
            )
        return values

    def drain(self, updates: int) -> tuple[dict[str, float], float]:
        """Mean of each metric over the held updates and their updates/s; then starts anew at ``updates``."""
        values = self.check_finite(updates)
        means = dict(zip(UPDATE_METRICS, values.mean(dim=0).tolist()))
        now = time.perf_counter()
        rate = (updates - self.first_update) / max(now - self.start, 1e-9)
        self.rows, self.first_update, self.start = [], updates, now
        return means, rate


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def make_maze(env_cfg):
    """The world of an ``env`` config node: a MiniGrid task with a fixed layout when ``env.id`` is set
    (:class:`~ss_drl.envs.minigrid.MiniGridTask`), else the maze of ``env.layout`` or ``env.preset``."""
    if env_cfg.get("id"):
        from ss_drl.envs.minigrid import minigrid_task

        return minigrid_task(env_cfg.id, int(env_cfg.layout_seed), int(env_cfg.max_states))
    return load_maze(env_cfg.layout if env_cfg.layout else env_cfg.preset)


def make_agent(cfg: DictConfig, maze: Maze, seed: int, counts: CountModel | None = None) -> Agent:
    """The learner named by ``agent.name``: ``dqn`` (with its HER replay buffer and its TD target, whose bounds read
    ``counts``), ``tabular`` or ``frontier`` (the frontier explorer, a baseline that keeps its own memory)."""
    if cfg.agent.name == "tabular":
        from ss_drl.agents.tabular import TabularQAgent

        return TabularQAgent(cfg.agent, maze, seed=seed)
    if cfg.agent.name == "frontier":
        from ss_drl.agents.frontier import FrontierExplorer

        return FrontierExplorer(cfg.agent, maze, seed=seed)
    from ss_drl.agents.dqn import DQNAgent, value_range
    from ss_drl.agents.targets import environment_assumptions, make_td_target
    from ss_drl.her import HindsightReplayBuffer

    settings = dqn_settings(cfg)
    buffer = HindsightReplayBuffer(
        capacity=settings.buffer_size,
        num_envs=cfg.env.num_envs,
        batch_size=settings.batch_size,
        strategy=cfg.her.strategy,
        k=cfg.her.k,
        n_step=settings.n_step,
        gamma=settings.gamma,
        goal_steps=settings.hindsight_bound,
        window_states=settings.n_step_max,
        cells=state_cells(maze),
    )
    clip = value_range(settings.gamma, settings.step_cost, cfg.env.max_steps) if settings.clip_targets else None
    td_target = make_td_target(settings, maze, counts, clip, holds=environment_assumptions(cfg.env))
    return DQNAgent(settings, maze, buffer, td_target, seed=seed, max_steps=cfg.env.max_steps)


def dqn_settings(cfg: DictConfig):
    """The DQN learner's typed settings, with every bound whose assumption the environment breaks turned off (one
    line each on stderr; :func:`~ss_drl.agents.targets.resolve_bounds`)."""
    from ss_drl.agents.settings import DQNSettings
    from ss_drl.agents.targets import environment_assumptions, resolve_bounds

    settings, lines = resolve_bounds(DQNSettings.from_config(cfg.agent), environment_assumptions(cfg.env))
    for line in lines:
        print(f"ss-drl: {line}", file=sys.stderr)
    return settings


def make_smart_start(
    cfg: DictConfig, maze: Maze, counts: CountModel, seed: int, frontier: Frontier | None = None
) -> SmartStart | None:
    ss = cfg.smart_start
    if ss.eta <= 0:
        return None
    planner = Planner(
        maze.width, gamma=ss.gamma, theta=ss.theta, tol=ss.tol, max_sweeps=ss.max_sweeps, cells=state_cells(maze)
    )
    generator = torch.Generator().manual_seed(seed + 1_000_003)
    return SmartStart(
        maze,
        counts,
        cfg.env.num_envs,
        ss.eta,
        ss.c_ss,
        ss.w_q,
        ss.theta,
        planner,
        generator,
        ss.guided_epsilon,
        frontier=frontier,
        select=ss.select,
        explore=ss.explore,
        explore_after_goal=ss.explore_after_goal,
        guided_limit=guided_limit(ss, float(cfg.env.slip)),
        explore_from_start=ss.explore_from_start,
        greedy_path=ss.greedy_path,
        max_steps=cfg.env.max_steps,
    )


def guided_limit(ss_cfg, slip: float) -> float | None:
    """``smart_start.guided_limit``, or when it is null the derived one: 3 under slips (the route's expected
    length grows with them, and rarely past twice the planned one at slip 0.25), none with deterministic moves (the
    route leads there; only ``guided_epsilon``'s random steps delay it)."""
    if ss_cfg.guided_limit is not None:
        return float(ss_cfg.guided_limit)
    return 3.0 if slip > 0 else None


class Trainer:
    """One training run in ``run_dir``, configured by the resolved Hydra config ``cfg``."""

    def __init__(self, cfg: DictConfig, run_dir: str | Path):
        validate_config(cfg)
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        ckpt.refuse_overwrite(cfg, self.run_dir)
        torch.set_num_threads(int(cfg.trainer.torch_threads))
        seed_everything(int(cfg.seed))
        self.maze = make_maze(cfg.env)
        # The optimum: the shortest path, or under slips the optimal policy's expected steps from S (value iteration
        # on the true model); each evaluation rolls the greedy policy out eval_episodes times in the env's dynamics.
        self.slip = float(cfg.env.slip)
        self.optimal_length = optimum(self.maze, self.slip)
        if self.optimal_length > cfg.env.max_steps:  # an evaluation's mean length (cut episodes count max_steps) can
            # then lie below the optimum, and few episodes reach G: said once, since the run is allowed
            print(
                f"ss-drl: warning: env.max_steps {cfg.env.max_steps} is below the optimal policy's expected steps from "
                f"S ({self.optimal_length:g} at slip {self.slip:g}): most episodes end before G",
                file=sys.stderr,
            )
        self.eval_episodes = evaluation_episodes(self.slip, cfg.trainer.eval_episodes)
        self.eval_generator = torch.Generator().manual_seed(int(cfg.seed) + 3_000_017)
        # The slips draw from the env's own generator, apart from the training RNG.
        self.env = BatchedMazeEnv(
            self.maze, cfg.env.num_envs, cfg.env.max_steps, slip=float(cfg.env.slip), seed=int(cfg.seed) + 2_000_003
        )
        self.counts = CountModel(self.maze.n_states, self.maze.n_actions)
        self.agent = make_agent(cfg, self.maze, int(cfg.seed), self.counts)
        self.frontier = Frontier(self.counts, state_cells(self.maze))
        self.smart_start = make_smart_start(cfg, self.maze, self.counts, int(cfg.seed), self.frontier)
        self.collector = MazeCollector(
            self.env, self.agent, self.smart_start, cfg.trainer.frames_per_batch, self.frontier
        )
        self.episodes = 0
        self.first_goal = FirstGoal()
        self.last_accuracy: float | None = None  # greedy accuracy at the last evaluation
        self.last_success_rate: float | None = None  # share of the last evaluation's episodes that reached G
        self.evals: list[EvalRecord] = []  # every evaluation of the run (kept in checkpoints), for the learned rule
        self.next_eval = 0
        self.next_checkpoint = cfg.trainer.checkpoint_interval
        self.log_interval = int(cfg.trainer.log_interval)
        self.next_log = self.log_interval  # update count at which the next train.csv row is written
        self.wall_before = 0.0  # wall time of earlier sessions of a resumed run
        self.ss_targets: list[int] = []
        self._recent: deque[bool] = deque(maxlen=100)  # successes of the latest episodes, for the progress bar
        self.resolved = OmegaConf.to_container(cfg, resolve=True)
        # Whether checkpoint.pt is known to be readable (this run wrote or loaded it): only then does a save keep it
        # as checkpoint.prev.pt, so that a damaged file is never kept in place of a good one (ckpt.save).
        self._keep_previous = True
        self._held_updates: dict | None = None  # a checkpoint's UpdateLog, for train() to continue
        resume_rows = None
        if ckpt.should_resume(cfg, self.run_dir):
            resume_rows = self._restore()
        self.logger = RunLogger(self.run_dir, cfg, self.resolved, resume_rows=resume_rows)
        # A sweep job that was stopped (SIGTERM) or refused wrote FAILED; this attempt replaces it.
        (self.run_dir / FAILED_FILE).unlink(missing_ok=True)
        self._stop_signal = None
        self.update_log: UpdateLog | None = None

    # --- the loop ----------------------------------------------------------------------------------------------
    def train(self) -> dict:
        cfg, agent, collector = self.cfg, self.agent, self.collector
        total = int(cfg.trainer.total_env_steps)
        schedule = cfg.agent if "eps_start" in cfg.agent else None  # epsilon's schedule (none: the frontier explorer)
        start = time.perf_counter()
        self.start_time = start - self.wall_before
        self.update_log = update_log = UpdateLog(agent.updates)
        if self._held_updates is not None:  # a resumed run: the updates since the checkpoint's last train.csv row
            update_log.load_state_dict(self._held_updates)
            self._held_updates = None
        bar = progress_bar(total, initial=collector.env_steps)
        handlers = self._install_signal_handlers()
        try:
            while collector.env_steps < total:
                # 1. Collect: guided phase (Smart Start) at episode starts, then epsilon-greedy.
                if schedule is not None:
                    agent.epsilon = linear_schedule(
                        collector.env_steps, schedule.eps_start, schedule.eps_end, schedule.eps_decay_steps
                    )
                batch, finished = collector.rollout(max_frames=total - collector.env_steps)
                # 2. Count model.
                self.counts.update(
                    batch.get("observation"),
                    batch.get("action"),
                    batch.get(("next", "observation")),
                    batch.get(("next", "reward")),
                )
                # 3. Replay buffer.
                agent.store(batch)
                # 4. Updates.
                for _ in range(agent.updates_due(collector.env_steps, batch.numel())):
                    update_log.add(agent.update())
                    # 5. Log: learning metrics every log_interval updates.
                    if agent.updates >= self.next_log:
                        self._log_updates(update_log)
                # 5. Log: episodes, evaluation, checkpoint.
                for episode in finished:
                    self._log_episode(episode)
                if collector.env_steps >= self.next_eval:
                    self.evaluate()
                if collector.env_steps >= self.next_checkpoint:
                    self.save_checkpoint()
                    self.next_checkpoint += cfg.trainer.checkpoint_interval
                self._show_progress(bar, batch.numel())
                if self._stop_signal is not None:
                    self.save_checkpoint()
                    raise TrainingInterrupted(
                        f"{self._stop_signal.name} received: checkpoint written at {collector.env_steps} env steps "
                        f"in {self.run_dir}; resume it with the same command and trainer.resume={self.run_dir}",
                        self._stop_signal,
                    )
            if update_log.rows:
                self._log_updates(update_log)
            if not self.evals or self.evals[-1].env_steps != collector.env_steps:
                self.evaluate()
            summary = self.summary(completed=True, wall=time.perf_counter() - self.start_time)
            self.save_checkpoint()
            self._write_end_of_run_figures()
            write_json_atomic(self.run_dir / SUMMARY_FILE, summary)
            self.logger.close(summary)
            return summary
        except BaseException:
            self.logger.close()
            raise
        finally:
            bar.close()
            self._restore_signal_handlers(handlers)

    # --- logging -----------------------------------------------------------------------------------------------
    def _log_updates(self, update_log: UpdateLog) -> None:
        """A train.csv row and W&B ``train/`` metrics: the means over the updates since the last row."""
        updates = self.agent.updates
        means, rate = update_log.drain(updates)
        row = {
            "env_steps": self.collector.env_steps,
            "updates": updates,
            **{k: round(v, 6) for k, v in means.items()},
            "epsilon": round(self.agent.epsilon, 6),
            "updates_per_s": round(rate, 1),
            "wall_s": round(time.perf_counter() - self.start_time, 3),
        }
        self.logger.log_train(row)
        metrics = {f"train/{k}": v for k, v in means.items()}
        metrics.update({"train/epsilon": self.agent.epsilon, "train/updates": updates, "time/updates_per_s": rate})
        self.logger.log_metrics(metrics, step=self.collector.env_steps)
        while self.next_log <= updates:
            self.next_log += self.log_interval

    def _log_episode(self, episode: Episode) -> None:
        self.episodes += 1
        if episode.success and self.first_goal.env_step is None:
            self.first_goal = FirstGoal(episode.env_steps, self.episodes)
        if episode.smart_start:
            self.ss_targets.append(episode.ss_target)
        target = "" if episode.ss_target < 0 else self.maze.label(episode.ss_target)
        visited = int(torch.count_nonzero(self.counts.state_counts))
        row = {
            "episode": self.episodes,
            "env_id": episode.env_id,
            "env_steps": episode.env_steps,
            "length": episode.length,
            "return": episode.episode_return,
            "success": int(episode.success),
            "smart_start": int(episode.smart_start),
            "ss_target": target,
            "ss_reached": int(episode.ss_reached),
            "ss_steps": episode.ss_steps,
            "epsilon": round(self.agent.epsilon, 6),
            "end_state": self.maze.label(episode.end_state),
            "states_visited": visited,
            "new_moves": episode.new_moves,
            "new_moves_after_ss": episode.new_moves_after_ss,
            "explore_steps": episode.explore_steps,
            "ss_frontier_steps": episode.ss_frontier_steps,
            "minigrid_return": "",
            "wall_s": round(time.perf_counter() - self.start_time, 3),
        }
        if hasattr(self.maze, "minigrid_return"):
            row["minigrid_return"] = round(
                self.maze.minigrid_return(episode.success, episode.length, int(self.cfg.env.max_steps)), 6
            )
        self.logger.log_episode(row)
        self._recent.append(episode.success)
        self.logger.log_metrics(
            {
                "train/episode": self.episodes,
                "train/return": episode.episode_return,
                "train/length": episode.length,
                "train/success": int(episode.success),
                "train/smart_start": int(episode.smart_start),
                "train/ss_steps": episode.ss_steps,
                "train/states_visited": visited,
                "time/env_steps_per_s": self.collector.env_steps / max(time.perf_counter() - self.start_time, 1e-9),
            },
            step=episode.env_steps,
        )

    def _show_progress(self, bar, new_steps: int) -> None:
        bar.update(new_steps)
        if self.episodes and bar.n % 1000 < new_steps:
            success = sum(self._recent) / max(len(self._recent), 1)
            bar.set_postfix(episodes=self.episodes, success=f"{success:.2f}")

    def evaluate(self) -> EvalRecord:
        policy = greedy_policy(self.agent, self.maze)
        accuracy = greedy_accuracy(policy, self.maze)
        max_steps = self.cfg.env.max_steps
        ev = evaluate_policy(policy, self.maze, max_steps, self.eval_episodes, self.slip, self.eval_generator)
        length = ev.lengths[0] if self.eval_episodes == 1 else round(ev.mean_length, 3)
        steps = self.collector.env_steps
        wall = round(time.perf_counter() - self.start_time, 3)
        self.logger.log_eval(
            {
                "env_steps": steps,
                "episode": self.episodes,
                "eval_length": length,
                "eval_success": int(ev.success),
                "eval_success_rate": round(ev.success_rate, 4),
                "wall_s": wall,
            }
        )
        self.logger.log_metrics(
            {
                "eval/length": length,
                "eval/success": int(ev.success),
                "eval/success_rate": ev.success_rate,
                "eval/optimal": self.optimal_length,
                "eval/greedy_accuracy": accuracy,
            },
            step=steps,
        )
        self.evals.append(EvalRecord(steps, length, bool(ev.success), wall))
        self.last_success_rate = ev.success_rate
        self.last_accuracy = accuracy
        while self.next_eval <= steps:
            self.next_eval += self.cfg.trainer.eval_interval
        return self.evals[-1]

    def summary(self, completed: bool, wall: float) -> dict:
        last = self.evals[-1] if self.evals else None
        rule = learned(self.evals, self.optimal_length, int(self.cfg.trainer.total_env_steps))
        return {
            "experiment": self.cfg.experiment,
            "method": method_label(self.resolved),
            "maze": self.maze.name,
            "seed": int(self.cfg.seed),
            "completed": completed,
            "first_goal_env_step": self.first_goal.env_step,
            "first_goal_episode": self.first_goal.episode,
            "episodes": self.episodes,
            "env_steps": self.collector.env_steps,
            "final_eval_length": None if last is None else last.length,
            "final_greedy_accuracy": None if last is None else round(self.last_accuracy, 4),
            "final_eval_success_rate": None if last is None else round(self.last_success_rate, 4),
            "optimal_length": self.optimal_length,
            "slip": self.slip,
            "eval_episodes": self.eval_episodes,
            "learned_env_step": rule.env_step,
            "learned_wall_s": rule.wall_s,
            "last_quarter_within": rule.last_quarter_within,
            "wall_s": round(wall, 3),
            "env_steps_per_s": round(self.collector.env_steps / max(wall, 1e-9), 1),
            "updates_per_s": round(self.agent.updates / max(wall, 1e-9), 1),
            "smart_start_decisions": 0 if self.smart_start is None else self.smart_start.decisions,
            "greedy_path_decisions": 0 if self.smart_start is None else self.smart_start.greedy_path_decisions,
            "bounds_in_force": list(getattr(self.agent, "bounds_in_force", [])),
            "config": self.resolved,
        }

    def _write_end_of_run_figures(self) -> None:
        if self.smart_start is None:
            return
        path = self.run_dir / "smart_start.png"
        plot_visit_counts(self.maze, self.counts.state_counts, self.ss_targets, path)
        self.logger.log_image("smart_start/visits", path, step=self.collector.env_steps)

    # --- checkpoints -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            ckpt.FORMAT_KEY: ckpt.FORMAT,  # a checkpoint without it predates the learners' names: refused on resume
            "agent": self.agent.state_dict(),
            "counts": self.counts.state_dict(),
            "smart_start": None if self.smart_start is None else self.smart_start.state_dict(),
            "collector": self.collector.state_dict(),
            "episodes": self.episodes,
            "first_goal": dataclasses.asdict(self.first_goal),
            "last_accuracy": self.last_accuracy,
            "evals": [tuple(e) for e in self.evals],
            "next_eval": self.next_eval,
            "next_checkpoint": self.next_checkpoint,
            "next_log": self.next_log,
            "ss_targets": list(self.ss_targets),
            "recent": list(self._recent),
            "wall_s": time.perf_counter() - self.start_time,
            "rows": self.logger.rows,
            "update_log": None if self.update_log is None else self.update_log.state_dict(),
            "rng": ckpt.rng_state(),
            "eval_rng": self.eval_generator.get_state(),
            "last_success_rate": self.last_success_rate,
            "config": self.resolved,
        }

    def save_checkpoint(self) -> Path:
        """An atomic checkpoint, the one it replaces kept as checkpoint.prev.pt; never of a network whose loss went
        non-finite since the last train.csv row."""
        if self.update_log is not None:
            self.update_log.check_finite(self.agent.updates)
        self.logger.flush()
        path = ckpt.save(self.state_dict(), self.run_dir, keep_previous=self._keep_previous)
        self._keep_previous = True
        return path

    def _restore(self) -> tuple[int, ...]:
        # checkpoint.pt, or checkpoint.prev.pt when checkpoint.pt is damaged: the same choice as ckpt.check_resume's
        # before the run started; of this format (checked before anything else of it is read).
        resumption = ckpt.resume_from(self.run_dir)
        if resumption.fell_back:
            print(f"ss-drl: warning: {resumption.warning}", file=sys.stderr)
            self._keep_previous = False  # checkpoint.pt is damaged: the next save replaces it, keeping prev
        state = resumption.state
        ckpt.check_continuable(state, resumption.path, self.resolved)
        self.agent.load_state_dict(state["agent"])
        self.counts.load_state_dict(state["counts"])
        if self.smart_start is not None:
            self.smart_start.load_state_dict(state["smart_start"])
        self.collector.load_state_dict(state["collector"])
        self.episodes = state["episodes"]
        self.first_goal = FirstGoal(**state["first_goal"])
        self.last_accuracy = state["last_accuracy"]
        self.evals = [EvalRecord(*e) for e in state["evals"]]
        if "eval_rng" in state:  # absent in checkpoints written before evaluations rolled out in the env
            self.eval_generator.set_state(state["eval_rng"])
            self.last_success_rate = state["last_success_rate"]
        elif self.evals:  # one deterministic episode per evaluation then: its success is the evaluation's rate
            self.last_success_rate = float(bool(self.evals[-1].success))
        self.next_eval, self.next_checkpoint = state["next_eval"], state["next_checkpoint"]
        self.next_log = state["next_log"]
        self.ss_targets = list(state["ss_targets"])
        self._recent = deque(state["recent"], maxlen=100)
        self.wall_before = state["wall_s"]
        self._held_updates = state.get("update_log")  # None in checkpoints written before it was kept
        ckpt.set_rng_state(state["rng"])
        return tuple(state["rows"])

    def _install_signal_handlers(self):
        def handler(signum, frame):
            self._stop_signal = signal.Signals(signum)

        previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                previous[sig] = signal.signal(sig, handler)
            except ValueError:  # not in the main thread (e.g. some launchers): no graceful stop
                pass
        return previous

    @staticmethod
    def _restore_signal_handlers(previous) -> None:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def train(cfg: DictConfig, run_dir: str | Path) -> dict:
    """Train one run; returns the summary (also written to ``run_dir/summary.json``)."""
    return Trainer(cfg, run_dir).train()
