"""The training loop with Smart Start: eta = 0 equivalence, counts, guided phases, collected batches."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
import torch
from helpers import ROOT, compose_cfg

from ss_drl.training.collector import MazeCollector
from ss_drl.training.outputs import EPISODES_FILE
from ss_drl.training.trainer import Trainer

SMALL = ["agent.learning_starts=100", "agent.batch_size=32", "agent.hidden=[32,32]", "agent.embed_dim=8"]


def episode_rows(run_dir: Path) -> list[list[str]]:
    lines = (run_dir / EPISODES_FILE).read_text().splitlines()
    return [line.rsplit(",", 1)[0] for line in lines]  # wall_s is the last column


@pytest.mark.slow
def test_eta_zero_reproduces_the_run_without_smart_start(tmp_path):
    common = ["trainer.total_env_steps=2500", "env.max_steps=200", *SMALL]
    Trainer(compose_cfg("+experiment=easy_small_dqn_her", *common), tmp_path / "off").train()
    Trainer(compose_cfg("+experiment=easy_small_ss_her", "smart_start.eta=0", *common), tmp_path / "eta0").train()
    Trainer(compose_cfg("+experiment=easy_small_ss_her", *common), tmp_path / "on").train()
    off, eta0, on = (episode_rows(tmp_path / d) for d in ("off", "eta0", "on"))
    assert len(off) > 5
    assert eta0 == off
    assert on != off  # and Smart Start does change the run


def _run_collector(maze: str, steps: int, num_envs: int = 1, eta: float = 1.0, guided_epsilon: float = 0.0):
    cfg = compose_cfg(
        f"+experiment={maze}_ss_her",
        f"smart_start.eta={eta}",
        f"smart_start.guided_epsilon={guided_epsilon}",  # 0: the route is followed exactly
        f"env.num_envs={num_envs}",
        "env.max_steps=60",
        f"trainer.frames_per_batch={num_envs}",
        *SMALL,
    )
    trainer = Trainer(cfg, ROOT / "outputs" / "unused")  # nothing is written before train()
    collector: MazeCollector = trainer.collector
    batches, episodes = [], []
    while collector.env_steps < steps:
        batch, finished = collector.rollout()
        nxt = batch["next"]
        trainer.counts.update(batch["observation"], batch["action"], nxt["observation"], nxt["reward"])  # as the loop
        batches.append(batch)
        episodes += finished
    return trainer, torch.cat(batches), episodes


def test_counts_equal_the_transitions_taken():
    trainer, batch, episodes = _run_collector("easy_small", 900, num_envs=3)
    s, a = batch["observation"].reshape(-1).tolist(), batch["action"].reshape(-1).tolist()
    s2 = batch["next", "observation"].reshape(-1).tolist()
    counts = trainer.counts
    assert counts.total_visits == len(s) == trainer.collector.env_steps
    for state, n in Counter(s).items():
        assert counts.count(state) == n
    for (state, action), n in Counter(zip(s, a)).items():
        assert counts.count(state, action) == n
    for (state, action, nxt), n in Counter(zip(s, a, s2)).items():
        assert counts.count(state, action, nxt) == n
    assert sum(e.length for e in episodes) <= len(s)


def test_guided_phase_reaches_smart_start_state_in_planned_steps():
    trainer, batch, episodes = _run_collector("easy_small", 3000)
    guided = [e for e in episodes if e.smart_start]
    assert episodes[0].smart_start is False  # never in the first episode
    assert all(e.smart_start for e in episodes[1:])  # eta = 1
    reached = [e for e in guided if e.ss_reached]
    assert len(reached) >= 10
    for e in reached:
        assert e.ss_steps == e.ss_planned_steps
        assert e.ss_steps <= e.length
    # The transitions of the guided phase are in the batch: the first ss_steps actions of each episode follow
    # the planner, so every one of them is a move (a shortest route never bumps into a wall).
    obs, nxt = batch["observation"][:, 0], batch["next", "observation"][:, 0]
    start = 0
    for e in episodes:
        guided_part = slice(start, start + e.ss_steps)
        assert bool((obs[guided_part] != nxt[guided_part]).all())
        start += e.length


def test_network_acts_only_on_steps_outside_the_guided_phase(monkeypatch):
    from ss_drl.agents.dqn import DQNAgent

    calls = []
    act = DQNAgent.act
    monkeypatch.setattr(DQNAgent, "act", lambda self, obs, goal: calls.append(obs.numel()) or act(self, obs, goal))
    _, batch, episodes = _run_collector("easy_small", 3000)
    guided_steps = sum(e.ss_steps for e in episodes)
    assert guided_steps > 100
    running = batch.numel() - sum(e.length for e in episodes)  # steps of the unfinished last episode
    assert running >= 0 and len(calls) >= batch.numel() - guided_steps - running
    assert len(calls) <= batch.numel() - guided_steps


def test_eta_zero_never_guides():
    _, _, episodes = _run_collector("easy_small", 600, eta=0.0)
    assert episodes and not any(e.smart_start for e in episodes)
