"""The training loop: collect, count, store, update, evaluate, log, checkpoint.

Read top to bottom, one iteration is:

1. ``collector.rollout()``: ``frames_per_batch`` env steps with the epsilon-greedy policy; at each episode start
   Smart Start may choose S_ss and plan a route to it, which the copy follows first. The count model sees every step.
2. ``agent.observe(batch)``: the DQN stores the batch in the HER replay buffer and runs its due updates
   (the tabular agent runs its Q-learning updates on the batch).
3. Episode rows go to episodes.csv (and W&B); every ``eval_interval`` steps a greedy episode from S goes to eval.csv.
4. Every ``checkpoint_interval`` steps an atomic checkpoint is written.
"""

from __future__ import annotations

import random
import signal
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from ss_drl.envs.batched import BatchedMazeEnv
from ss_drl.envs.maze import Maze, load_maze
from ss_drl.smart_start import CountModel, Planner, SmartStart
from ss_drl.training import checkpoint as ckpt
from ss_drl.training.collector import MazeCollector
from ss_drl.training.config import validate_config
from ss_drl.training.evaluation import greedy_rollout
from ss_drl.training.outputs import SUMMARY_FILE, RunLogger, progress_bar, write_json_atomic


class TrainingInterrupted(Exception):
    """SIGINT/SIGTERM arrived; a final checkpoint was written."""


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def make_maze(env_cfg) -> Maze:
    return load_maze(env_cfg.layout if env_cfg.layout else env_cfg.preset)


def make_agent(cfg: DictConfig, maze: Maze, seed: int):
    """The learner named by ``agent.name``: ``dqn`` (with its HER replay buffer) or ``tabular``."""
    if cfg.agent.name == "tabular":
        from ss_drl.agents.tabular import TabularQAgent

        return TabularQAgent(cfg.agent, maze, seed=seed)
    from ss_drl.agents.dqn import DQNAgent
    from ss_drl.her import HindsightReplayBuffer

    buffer = HindsightReplayBuffer(
        capacity=cfg.agent.buffer_size,
        num_envs=cfg.env.num_envs,
        batch_size=cfg.agent.batch_size,
        strategy=cfg.her.strategy,
        k=cfg.her.k,
    )
    return DQNAgent(cfg.agent, maze, buffer, seed=seed)


def make_smart_start(cfg: DictConfig, maze: Maze, counts: CountModel, seed: int) -> SmartStart | None:
    ss = cfg.smart_start
    if ss.eta <= 0:
        return None
    planner = Planner(maze.width, gamma=ss.gamma, theta=ss.theta, tol=ss.tol, max_sweeps=ss.max_sweeps)
    generator = torch.Generator().manual_seed(seed + 1_000_003)
    return SmartStart(
        maze, counts, cfg.env.num_envs, ss.eta, ss.c_ss, ss.w_q, ss.theta, planner, generator, ss.guided_epsilon
    )


class Trainer:
    """One training run in ``run_dir``, configured by the resolved Hydra config ``cfg``."""

    def __init__(self, cfg: DictConfig, run_dir: str | Path):
        validate_config(cfg)
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        torch.set_num_threads(int(cfg.trainer.torch_threads))
        seed_everything(int(cfg.seed))
        self.maze = make_maze(cfg.env)
        self.optimal_length = self.maze.shortest_path_length
        self.env = BatchedMazeEnv(self.maze, num_envs=cfg.env.num_envs, max_steps=cfg.env.max_steps)
        self.agent = make_agent(cfg, self.maze, int(cfg.seed))
        self.counts = CountModel(self.maze.n_cells)
        self.smart_start = make_smart_start(cfg, self.maze, self.counts, int(cfg.seed))
        self.collector = MazeCollector(
            self.env, self.agent, self.counts, self.smart_start, cfg.trainer.frames_per_batch
        )
        self.episodes = 0
        self.first_goal = (None, None)  # (env step, episode) of the first success
        self.last_eval = None
        self.last_accuracy = None  # greedy accuracy at the last evaluation
        self.next_eval = 0
        self.next_checkpoint = cfg.trainer.checkpoint_interval
        self.wall_before = 0.0  # wall time of earlier sessions of a resumed run
        self.ss_targets: list[int] = []
        self._recent: deque[bool] = deque(maxlen=100)  # successes of the latest episodes, for the progress bar
        self.resolved = OmegaConf.to_container(cfg, resolve=True)
        resume_rows = None
        if ckpt.should_resume(cfg, self.run_dir):
            resume_rows = self._restore()
        self.logger = RunLogger(self.run_dir, cfg, self.resolved, resume_rows=resume_rows)
        self._stop_signal = None

    # --- the loop ----------------------------------------------------------------------------------------------
    def train(self) -> dict:
        cfg = self.cfg
        total = int(cfg.trainer.total_env_steps)
        start = time.perf_counter()
        self.start_time = start - self.wall_before
        bar = progress_bar(total, initial=self.collector.env_steps)
        handlers = self._install_signal_handlers()
        try:
            while self.collector.env_steps < total:
                batch, finished = self.collector.rollout(max_frames=total - self.collector.env_steps)
                self._set_epsilon()
                self.agent.observe(batch, self.collector.env_steps)
                for episode in finished:
                    self._log_episode(episode)
                if self.collector.env_steps >= self.next_eval:
                    self.evaluate()
                if self.collector.env_steps >= self.next_checkpoint:
                    self.save_checkpoint()
                    self.next_checkpoint += cfg.trainer.checkpoint_interval
                bar.update(batch.numel())
                if self.episodes and bar.n % 1000 < batch.numel():
                    bar.set_postfix(episodes=self.episodes, success=f"{self._recent_success():.2f}")
                if self._stop_signal is not None:
                    self.save_checkpoint()
                    raise TrainingInterrupted(
                        f"{self._stop_signal} received: checkpoint written at {self.collector.env_steps} env steps "
                        f"in {self.run_dir}; resume with trainer.resume=true"
                    )
            if self.last_eval is None or self.last_eval[0] != self.collector.env_steps:
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

    def _set_epsilon(self) -> None:
        agent = self.cfg.agent
        frac = min(1.0, self.collector.env_steps / max(1, agent.eps_decay_steps))
        self.agent.set_epsilon(agent.eps_start + frac * (agent.eps_end - agent.eps_start))

    # --- logging -----------------------------------------------------------------------------------------------
    def _log_episode(self, episode) -> None:
        self.episodes += 1
        if episode.success and self.first_goal[0] is None:
            self.first_goal = (episode.env_steps, self.episodes)
        if episode.smart_start:
            self.ss_targets.append(episode.ss_target)
        target = "" if episode.ss_target < 0 else "{}:{}".format(*self.maze.pos(episode.ss_target))
        row = {
            "episode": self.episodes,
            "env_id": episode.env_id,
            "env_steps": episode.env_steps,
            "length": episode.length,
            "return": episode.ret,
            "success": int(episode.success),
            "smart_start": int(episode.smart_start),
            "ss_target": target,
            "ss_reached": int(episode.ss_reached),
            "ss_steps": episode.ss_steps,
            "epsilon": round(self.agent.epsilon, 6),
            "wall_s": round(time.perf_counter() - self.start_time, 3),
        }
        self.logger.log_episode(row)
        self._recent.append(episode.success)
        self.logger.log_metrics(
            {
                "train/episode": self.episodes,
                "train/return": episode.ret,
                "train/length": episode.length,
                "train/success": int(episode.success),
                "train/smart_start": int(episode.smart_start),
                "train/ss_steps": episode.ss_steps,
                "train/epsilon": self.agent.epsilon,
                "train/loss": getattr(self.agent, "last_loss", float("nan")),
                "time/env_steps_per_s": self.collector.env_steps / max(time.perf_counter() - self.start_time, 1e-9),
            },
            step=episode.env_steps,
        )

    def _recent_success(self) -> float:
        return sum(self._recent) / max(len(self._recent), 1)

    def evaluate(self) -> tuple[int, bool]:
        rollout = greedy_rollout(self.agent, self.maze, self.cfg.env.max_steps)
        steps = self.collector.env_steps
        self.logger.log_eval(
            {
                "env_steps": steps,
                "episode": self.episodes,
                "eval_length": rollout.length,
                "eval_success": int(rollout.success),
            }
        )
        self.logger.log_metrics(
            {
                "eval/length": rollout.length,
                "eval/success": int(rollout.success),
                "eval/optimal": self.optimal_length,
                "eval/greedy_accuracy": rollout.accuracy,
            },
            step=steps,
        )
        self.last_eval = (steps, rollout.length, rollout.success)
        self.last_accuracy = rollout.accuracy
        while self.next_eval <= steps:
            self.next_eval += self.cfg.trainer.eval_interval
        return rollout.length, rollout.success

    def summary(self, completed: bool, wall: float) -> dict:
        updates = getattr(self.agent, "updates", 0)
        return {
            "experiment": self.cfg.experiment,
            "method": self.cfg.method,
            "maze": self.maze.name,
            "seed": int(self.cfg.seed),
            "completed": completed,
            "first_goal_env_step": self.first_goal[0],
            "first_goal_episode": self.first_goal[1],
            "episodes": self.episodes,
            "env_steps": self.collector.env_steps,
            "final_eval_length": None if self.last_eval is None else self.last_eval[1],
            "final_greedy_accuracy": None if self.last_accuracy is None else round(self.last_accuracy, 4),
            "optimal_length": self.optimal_length,
            "wall_s": round(wall, 3),
            "env_steps_per_s": round(self.collector.env_steps / max(wall, 1e-9), 1),
            "updates_per_s": round(updates / max(wall, 1e-9), 1),
            "smart_start_decisions": 0 if self.smart_start is None else self.smart_start.decisions,
            "config": self.resolved,
        }

    def _write_end_of_run_figures(self) -> None:
        if self.smart_start is None:
            return
        from ss_drl.analysis.figures import plot_visit_counts

        path = self.run_dir / "smart_start.png"
        plot_visit_counts(self.maze, self.counts.state_counts, self.ss_targets, path)
        self.logger.log_image("smart_start/visits", path, step=self.collector.env_steps)

    # --- checkpoints -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "agent": self.agent.state_dict(),
            "counts": self.counts.state_dict(),
            "smart_start": None if self.smart_start is None else self.smart_start.state_dict(),
            "collector": self.collector.state_dict(),
            "episodes": self.episodes,
            "first_goal": self.first_goal,
            "last_eval": self.last_eval,
            "last_accuracy": self.last_accuracy,
            "next_eval": self.next_eval,
            "next_checkpoint": self.next_checkpoint,
            "ss_targets": list(self.ss_targets),
            "recent": list(self._recent),
            "wall_s": time.perf_counter() - self.start_time,
            "rows": (self.logger.episode_rows, self.logger.eval_rows),
            "rng": ckpt.rng_state(),
            "config": self.resolved,
        }

    def save_checkpoint(self) -> Path:
        self.logger.flush()
        return ckpt.save(self.state_dict(), self.run_dir)

    def _restore(self) -> tuple[int, int]:
        state = ckpt.load(self.run_dir)
        ckpt.check_compatible(state["config"], self.resolved)
        self.agent.load_state_dict(state["agent"])
        self.counts.load_state_dict(state["counts"])
        if self.smart_start is not None:
            self.smart_start.load_state_dict(state["smart_start"])
        self.collector.load_state_dict(state["collector"])
        self.episodes = state["episodes"]
        self.first_goal = tuple(state["first_goal"])
        self.last_eval = state["last_eval"]
        self.last_accuracy = state.get("last_accuracy")  # absent in checkpoints written before it existed
        self.next_eval, self.next_checkpoint = state["next_eval"], state["next_checkpoint"]
        self.ss_targets = list(state["ss_targets"])
        self._recent = deque(state["recent"], maxlen=100)
        self.wall_before = state["wall_s"]
        ckpt.set_rng_state(state["rng"])
        return tuple(state["rows"])

    def _install_signal_handlers(self):
        def handler(signum, frame):
            self._stop_signal = signal.Signals(signum).name

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
