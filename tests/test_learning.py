"""Learning tests: fixed seeds, small budgets, and assertions that the agents really learn."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import NO_COUNT_MODEL, compose_cfg

from ss_drl.agents.dqn import DQNAgent
from ss_drl.agents.settings import COUNT_MODEL_KEYS, DQNSettings
from ss_drl.envs.batched import BatchedMazeEnv
from ss_drl.envs.maze import load_maze
from ss_drl.her import HindsightReplayBuffer
from ss_drl.training.collector import MazeCollector
from ss_drl.training.greedy import greedy_rollout
from ss_drl.training.trainer import Trainer

pytestmark = pytest.mark.slow

#: The replay-only SS+HER learning test's budget on easy_small (the maze's own is 10k).
BUDGET = 6000


def test_model_bounded_ss_her_learns_medium_small_by_the_rule(tmp_path):
    """Issue 12's rule on medium_small (shortest path 35) with the model-bounded SS+HER setting (the shared setting
    this test was written for, ``medium_small_ss_her`` before issue 48 named it ``medium_small_ss_her_bounded``): the
    greedy path from S is within 1.05x the shortest path in at least 90% of the evaluations of the last quarter of the
    budget, and ``learned_env_step`` is the first evaluation of that streak.

    The budget is 10k env steps, a third of the maze's 30k: nothing in the setting depends on the budget, so the run
    is the 30k run's first 10k, and seed 0 learns at 3.0k in both. Its last quarter (7.5k-10k) has six evaluations,
    so all six must be within the bound. At 30k this one run took 1,423 s of a 1,986 s CI suite on a slow 2-core
    machine; at 10k it takes a third of that. (The replay-only SS+HER passes this test too, but learns only at 7.0k,
    500 steps short of the bound; its learning test is on easy_small.)"""
    experiment = "+experiment=medium_small_ss_her_bounded"
    maze_budget = compose_cfg(experiment).trainer.total_env_steps
    assert maze_budget == 30000
    budget = maze_budget // 3
    cfg = compose_cfg(experiment, "seed=0", f"trainer.total_env_steps={budget}")
    assert all(cfg.agent[key] for key in COUNT_MODEL_KEYS)  # the model-bounded learner
    summary = Trainer(cfg, tmp_path).train()
    assert summary["optimal_length"] == 35
    lengths = np.loadtxt(tmp_path / "eval.csv", delimiter=",", skiprows=1, usecols=(0, 2))
    assert lengths[0, 1] == 1000  # the untrained greedy policy does not reach G
    last_quarter = lengths[lengths[:, 0] >= 0.75 * budget, 1]
    assert len(last_quarter) >= 5
    assert np.mean(last_quarter <= 1.05 * 35) >= 0.9, lengths
    assert summary["last_quarter_within"] >= 0.9
    learned = summary["learned_env_step"]
    assert learned is not None and learned <= 0.75 * budget
    (at_learned,) = lengths[lengths[:, 0] == learned, 1]  # the streak starts at an evaluation ...
    assert at_learned <= 1.05 * 35  # ... within the bound


def test_tabular_learns_easy_small_optimally(tmp_path):
    # w_q = 0: S_ss by visit counts alone, the regime of the paper's experiment ("the value function will be zero").
    # With w_q = 1 the smart start state settles next to G once G is known, and the route the agent then always
    # takes is 2 steps longer than optimal (see the README's results). Like Keulen's tabular agent on Easy (9 of 10
    # seeds optimal in our sweep), a seed can settle on a slightly longer route for a while: three seeds, every one
    # must learn a greedy path to G, and most learn the shortest by the rule.
    finals = []
    for seed in range(3):
        cfg = compose_cfg(
            "+experiment=easy_small_tabular_ss",
            "smart_start.w_q=0",
            "trainer.total_env_steps=6000",
            "trainer.eval_interval=500",
            f"seed={seed}",
        )
        summary = Trainer(cfg, tmp_path / str(seed)).train()
        assert summary["first_goal_env_step"] is not None
        lengths = np.loadtxt(tmp_path / str(seed) / "eval.csv", delimiter=",", skiprows=1, usecols=2)
        assert lengths[0] == 1000  # the untrained greedy policy does not reach G
        assert summary["optimal_length"] == 19
        finals.append((summary["final_eval_length"], summary["learned_env_step"]))
    assert all(length < 1000 for length, _ in finals), finals  # the greedy path reaches G in every seed ...
    assert sum(learned is not None for _, learned in finals) >= 2, finals  # ... and most learn it by the rule


def test_dqn_her_learns_easy_small_optimally(tmp_path):
    """The replay-only DQN+HER, one update per 4 env steps: seed 1 first takes the 19-step path at 11,005 env steps
    and keeps it to the end of the 16k budget (measured at e46c275), so the rule's last quarter is all within bound."""
    cfg = compose_cfg("+experiment=easy_small_dqn_her", "seed=1", "agent.train_freq=4", "trainer.total_env_steps=16000")
    summary = Trainer(cfg, tmp_path).train()
    assert summary["first_goal_env_step"] is not None
    lengths = np.loadtxt(tmp_path / "eval.csv", delimiter=",", skiprows=1, usecols=2)
    assert lengths[0] == 1000  # the untrained greedy policy does not reach G ...
    # ... the trained one has learned by the rule: the shortest path in 90% of the last quarter's evaluations
    assert summary["learned_env_step"] is not None and summary["last_quarter_within"] >= 0.9, summary
    assert summary["final_eval_length"] == 19


def test_replay_only_ss_her_learns_easy_small_by_the_rule(tmp_path):
    """Issue 48: the replay-only DQN (no count-model bound) with SS+HER, the seed paper's method as
    ``+experiment=easy_small_ss_her`` configures it, learns easy_small (shortest path 19) by issue 12's rule with seed
    0: the greedy path from S is within 1.05x the shortest path (so exactly 19 steps) in at least 90% of the
    evaluations of the last quarter of the budget. The budget is :data:`BUDGET` env steps (evaluations every 500:
    the last quarter's three, 4.5k-6k, must all be within bound). Seed 0 reached G first at 669 env steps and learned
    at 3.5k (every evaluation from 3.5k on took 19 steps); the run took 108 s on a 2-core machine busy with two other
    training jobs. It replaces the 8k run of the same experiment, whose first 6k steps it is."""
    cfg = compose_cfg("+experiment=easy_small_ss_her", "seed=0", f"trainer.total_env_steps={BUDGET}")
    assert not any(cfg.agent[key] for key in COUNT_MODEL_KEYS)  # the replay-only learner
    summary = Trainer(cfg, tmp_path).train()
    # Every episode start but the first is guided: the finished episodes but the first, plus the unfinished last one.
    assert summary["smart_start_decisions"] == summary["episodes"] > 0
    lengths = np.loadtxt(tmp_path / "eval.csv", delimiter=",", skiprows=1, usecols=(0, 2))
    assert lengths[0, 1] == 1000  # the untrained greedy policy does not reach G
    assert summary["optimal_length"] == 19
    learned = summary["learned_env_step"]
    assert learned is not None, lengths
    assert summary["last_quarter_within"] >= 0.9
    (at_learned,) = lengths[lengths[:, 0] == learned, 1]
    assert at_learned == 19  # the streak starts at an evaluation on the shortest path (1.05 x 19 < 20) ...
    assert summary["final_eval_length"] == 19  # ... and the last greedy path from S is the shortest


def _offline_goal_reaching(k: int) -> float:
    """Train on the same random-walk data with HER ratio k/(k+1); success rate of greedy paths to random goals."""
    torch.manual_seed(0)
    cfg = compose_cfg(
        "+experiment=easy_small_dqn_her",
        f"her.k={k}",
        "agent.encoder=coords",
        *NO_COUNT_MODEL,
    )
    maze = load_maze("easy_small")
    buffer = HindsightReplayBuffer(
        20_000,
        1,
        cfg.agent.batch_size,
        "future",
        k,
        n_step=cfg.agent.n_step,
        gamma=cfg.agent.gamma,
        goal_steps=cfg.agent.hindsight_bound,
        window_states=cfg.agent.n_step_max,
    )
    agent = DQNAgent(DQNSettings.from_config(cfg.agent), maze, buffer)
    agent.epsilon = 1.0
    collector = MazeCollector(BatchedMazeEnv(maze, 1, max_steps=100), agent, None, 3000)
    while collector.env_steps < 3000:  # a batch ends with its episode
        agent.store(collector.rollout()[0])
    for _ in range(1500):
        agent.update()
    rng = np.random.default_rng(0)
    free = np.flatnonzero(~maze.walls.reshape(-1))
    successes = 0
    for _ in range(40):
        start, goal = rng.choice(free, 2, replace=False)
        successes += greedy_rollout(agent, maze, 200, start=int(start), goal=int(goal)).success
    return successes / 40


def test_her_beats_no_her_on_reaching_arbitrary_goals():
    """Goal-rich task: reach any cell from any cell. The same data without HER only ever rewards G."""
    with_her, without_her = _offline_goal_reaching(4), _offline_goal_reaching(0)
    assert with_her >= 0.4
    assert with_her >= without_her + 0.3
