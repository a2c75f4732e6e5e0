"""Stochastic moves (``env.slip``, issue 50): both envs against the closed-form transition probabilities, seeded
determinism, the bounds that assume deterministic moves turned off before training (one line), and a run with slips
that resumes from a checkpoint as if it had never stopped."""

from __future__ import annotations

import csv
import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import TINY, assert_resume_equals_uninterrupted, compose_cfg
from tensordict import TensorDict

from ss_drl.envs.batched import BatchedMazeEnv
from ss_drl.envs.gridworld import MazeEnv
from ss_drl.envs.maze import action_probabilities, parse_maze
from ss_drl.evaluate import main as evaluate_main
from ss_drl.smart_start import CountModel
from ss_drl.training.outputs import EVAL_FILE, SUMMARY_FILE
from ss_drl.training.trainer import dqn_settings

R, D, L, U = range(4)
#: S in a corner: right leads on, down leads on, left and up bump (off the grid).
CORNER = "S..\n..G\n"
SLIP = 0.4


def closed_form(maze, cell: int, action: int) -> dict[int, float]:
    """P(s' | s, a) by hand: the chosen move with 1 - slip + slip / 4, each other move with slip / 4."""
    table = maze.transition_table()
    out: Counter = Counter()
    for b in range(4):
        out[int(table[cell, b])] += (1 - SLIP) * (b == action) + SLIP / 4
    return dict(out)


def test_action_probabilities_by_hand():
    p = action_probabilities(0.4)
    assert p[R].tolist() == pytest.approx([0.7, 0.1, 0.1, 0.1])
    assert np.allclose(p.sum(axis=1), 1.0)
    assert np.array_equal(action_probabilities(0.0), np.eye(4))


def _within(counts: Counter, expected: dict[int, float], n: int) -> None:
    assert set(counts) <= set(expected)
    for cell, p in expected.items():
        sigma = (p * (1 - p) / n) ** 0.5
        assert abs(counts[cell] / n - p) < 5 * sigma, (cell, counts[cell] / n, p)


@pytest.mark.parametrize("action", [R, L])
def test_batched_env_moves_with_the_closed_form_frequencies(action):
    maze = parse_maze(CORNER)
    n = 40_000
    env = BatchedMazeEnv(maze, num_envs=n, slip=SLIP, seed=1)
    env.reset()
    out = env.step(TensorDict({"action": torch.full((n,), action)}, batch_size=[n]))
    counts = Counter(out["next", "observation"].tolist())
    expected = closed_form(maze, maze.start_cell, action)
    assert expected == pytest.approx({0: 0.2 + 0.6 * (action == L), 1: 0.1 + 0.6 * (action == R), 3: 0.1})
    _within(counts, expected, n)


@pytest.mark.parametrize("action", [R, L])
def test_gymnasium_env_moves_with_the_closed_form_frequencies(action):
    maze = parse_maze(CORNER)
    env = MazeEnv(maze, slip=SLIP)
    env.reset(seed=3)
    n, counts = 20_000, Counter()
    for _ in range(n):
        env.reset()
        obs, *_ = env.step(action)
        counts[maze.cell(tuple(obs["observation"]))] += 1
    _within(counts, closed_form(maze, maze.start_cell, action), n)


def test_slips_are_seeded():
    maze = parse_maze(CORNER)

    def batched(seed):
        env = BatchedMazeEnv(maze, num_envs=64, slip=SLIP, seed=seed, max_steps=50)
        env.reset()
        return torch.stack(
            [env.step(TensorDict({"action": torch.full((64,), R)}, batch_size=[64]))["next", "observation"]
             for _ in range(3)]
        )  # fmt: skip

    assert torch.equal(batched(5), batched(5)) and not torch.equal(batched(5), batched(6))

    def gym_walk(seed):
        env = MazeEnv(maze, slip=SLIP)
        env.reset(seed=seed)
        return [tuple(env.step(D)[0]["observation"]) for _ in range(30)]

    assert gym_walk(7) == gym_walk(7) and gym_walk(7) != gym_walk(8)


def test_no_slip_draws_nothing():
    env = BatchedMazeEnv(parse_maze(CORNER), num_envs=4, seed=0)
    before = env.rng_state().clone()
    env.reset()
    env.step(TensorDict({"action": torch.full((4,), R)}, batch_size=[4]))
    assert torch.equal(env.rng_state(), before)


@pytest.mark.parametrize("method", ["ss_her", "ss_her_bounded"])
def test_both_learners_turn_their_deterministic_bounds_off_in_one_line(method, capsys):
    cfg = compose_cfg(f"+experiment=easy_small_{method}", "env.slip=0.1")
    settings = dqn_settings(cfg)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("ss-drl:")]
    assert len(lines) == 1 and "deterministic moves" in lines[0]
    on_before = [k for k in ("hindsight_bound", "n_step_max", "distance_floor", "distance_ceiling", "model_targets")
                 if cfg.agent[k]]  # fmt: skip
    assert on_before and all(f"agent.{k}" in lines[0] for k in on_before)
    assert not any(getattr(settings, k) for k in on_before)
    # What summary.json lists as bounds_in_force: nothing, for either learner.
    from ss_drl.agents.targets import STOCHASTIC_MAZE, make_td_target
    from ss_drl.envs import load_maze
    from ss_drl.smart_start.counts import CountModel

    maze = load_maze("easy_small")
    assert make_td_target(settings, maze, CountModel(maze.n_cells), None, holds=STOCHASTIC_MAZE).in_force == []
    # Without slips nothing is turned off.
    dqn_settings(compose_cfg(f"+experiment=easy_small_{method}"))
    assert "turned off" not in capsys.readouterr().err


def test_a_deterministic_bound_set_on_the_command_line_is_refused_under_slips():
    from helpers import ROOT
    from hydra import compose, initialize_config_dir

    from ss_drl.training.config import ConfigError, validate_config

    overrides = ["+experiment=easy_small_ss_her", "env.slip=0.1", "agent.hindsight_bound=true"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides, return_hydra_config=True)  # the command line is known
    with pytest.raises(ConfigError, match=r"^agent.hindsight_bound=true: this environment breaks"):
        validate_config(cfg)


def test_the_frontier_explorer_refuses_slips():
    from ss_drl.training.config import ConfigError, validate_config

    with pytest.raises(ConfigError, match=r"^env.slip: 0.1 is out of range for the frontier explorer"):
        validate_config(compose_cfg("+experiment=easy_small_frontier", "env.slip=0.1"))


@pytest.mark.slow
def test_a_run_with_slips_resumes_as_if_uninterrupted_and_lists_its_bounds(tmp_path, capsys):
    run = [
        "+experiment=easy_small_ss_her_bounded",
        *(o for o in TINY if not o.startswith("trainer.total_env_steps=")),
        "env.slip=0.2", "trainer.total_env_steps=1200", "trainer.checkpoint_interval=300", "env.max_steps=100",
    ]  # fmt: skip
    full = assert_resume_equals_uninterrupted(run, tmp_path)
    summary = json.loads((full / SUMMARY_FILE).read_text())
    assert summary["bounds_in_force"] == []  # every bound of the model-bounded learner assumes deterministic moves
    maze = parse_maze((Path(__file__).parents[1] / "ss_drl" / "mazes" / "easy_small.txt").read_text())
    assert summary["slip"] == 0.2 and summary["eval_episodes"] == 48  # ceil(240 * 0.2)
    assert summary["optimal_length"] == round(float(maze.expected_steps(0.2)[0][maze.start_cell]), 3)
    assert summary["optimal_length"] > maze.shortest_path_length
    with (full / EVAL_FILE).open(newline="") as f:
        evals = list(csv.DictReader(f))
    for row in evals:  # a share of 48 episodes, rounded to 4 places
        assert abs(float(row["eval_success_rate"]) * 48 - round(float(row["eval_success_rate"]) * 48)) < 0.01
    for row in evals:  # success is "every episode reached G"
        assert (row["eval_success"] == "1") == (float(row["eval_success_rate"]) == 1.0)
    # The moves did slip in training: some (s, a) was seen to lead to two cells.
    saved = torch.load(full / "checkpoint.pt", weights_only=False)["counts"]
    counts = CountModel(saved["n_states"], saved["n_actions"])
    counts.load_state_dict(saved)
    assert not counts.structure().deterministic
    # evaluate.py evaluates as the trainer does: 48 episodes in the env's dynamics, against the same optimum.
    assert evaluate_main([str(full), "--out", str(tmp_path / "greedy.png")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("48 greedy episodes from S at slip 0.2 (seed 0): mean length ")
    assert f"(optimal {summary['optimal_length']})" in out[0]
    assert (tmp_path / "greedy.png").stat().st_size > 0


# --- the optimum and "learned" under slips --------------------------------------------------------------------------
def test_expected_steps_on_a_corridor_by_hand():
    """S . G in a row: from S only "right" leads on, with probability q = 1 - 3 slip / 4 (left, up and down bump);
    from the middle "right" enters G with q, "left" of the slipped ones goes back with slip / 4. So
    V1 = 1 + (slip / 4) V0 + (slip / 2) V1 and V0 = 1 + q V1 + (1 - q) V0, solved by hand."""
    maze = parse_maze("S.G\n")
    slip = 0.3
    q = 1 - 3 * slip / 4
    # V0 = 1 / q + V1; V1 (1 - slip / 2) = 1 + (slip / 4) (1 / q + V1)  =>  V1 = (1 + slip / (4 q)) / (1 - 3 slip / 4)
    v1 = (1 + slip / (4 * q)) / (1 - 3 * slip / 4)
    v0 = 1 / q + v1
    v, policy = maze.expected_steps(slip)
    assert v[0] == pytest.approx(v0, rel=1e-9) and v[1] == pytest.approx(v1, rel=1e-9) and v[2] == 0
    assert policy[:2].tolist() == [R, R]
    assert maze.expected_steps(0.0)[0][:3].tolist() == [2, 1, 0]


def test_evaluation_rolls_out_in_the_env_dynamics():
    """Episodes of a fixed policy under slips: seeded, their lengths' mean near the policy's expected steps, and
    without slips one deterministic walk (a loop ends it at max_steps)."""
    from ss_drl.training.greedy import evaluate_policy

    maze = parse_maze("S.G\n")
    v, policy = maze.expected_steps(SLIP)
    run = lambda seed: evaluate_policy(  # noqa: E731
        torch.from_numpy(policy), maze, 200, 4000, SLIP, torch.Generator().manual_seed(seed)
    )
    a, b = run(1), run(1)
    assert a.lengths == b.lengths and a.success and a.success_rate == 1.0
    sd = float(np.std(a.lengths)) / len(a.lengths) ** 0.5
    assert abs(a.mean_length - v[maze.start_cell]) < 5 * sd
    loop = torch.tensor([L, L, L])  # never gets anywhere
    stuck = evaluate_policy(loop, maze, 50)
    assert stuck.lengths == [50] and not stuck.success and stuck.path == [0, 0]


@pytest.mark.parametrize(("maze_name", "slip", "evals_in_last_quarter"), [
    ("easy", 0.1, 5), ("easy", 0.1, 6), ("medium", 0.1, 30), ("medium", 0.1, 31), ("easy", 0.25, 5), ("easy", 0.25, 6),
])  # fmt: skip
def test_the_optimal_policy_passes_the_learned_rule(maze_name, slip, evals_in_last_quarter):
    """With the derived ``trainer.eval_episodes``, the optimal policy simulated over 200 runs passes the learned rule
    (at least 90% of the last quarter's evaluations within 1.05x the expected steps, all episodes reaching G) in at
    least 95% of them. An evaluation comes at the first batch end at or past each 500 env steps, and the last quarter
    holds those strictly past 3/4 of the budget: 5 or 6 on Easy's budget (10k; 6 unless a batch ends exactly at
    7,500, as in most runs: a session-47 reading found 6 where this test had assumed 5), 30 or 31 on Medium's (60k).
    The mean length and the optimum are rounded as the trainer rounds them."""
    from fractions import Fraction

    from ss_drl.envs.maze import load_maze
    from ss_drl.training.greedy import eval_episodes, evaluate_policy
    from ss_drl.training.greedy import optimum as trainer_optimum
    from ss_drl.training.learned import SHARE, within_bound

    maze = load_maze(maze_name)
    _, policy = maze.expected_steps(slip)
    optimum = trainer_optimum(maze, slip)
    n = eval_episodes(slip)
    runs = 200
    ev = evaluate_policy(
        torch.from_numpy(policy), maze, 1000, runs * evals_in_last_quarter * n, slip, torch.Generator().manual_seed(0)
    )
    lengths = torch.tensor(ev.lengths).view(runs, evals_in_last_quarter, n).double()
    reached = torch.tensor(ev.successes).view(runs, evals_in_last_quarter, n)
    within = [
        [
            within_bound(round(float(lengths[r, e].mean()), 3), bool(reached[r, e].all()), optimum)
            for e in range(lengths.shape[1])
        ]
        for r in range(runs)
    ]
    passed = sum(Fraction(sum(w), len(w)) >= SHARE for w in within)
    assert passed >= 0.95 * runs, (passed, n)


@pytest.mark.parametrize("experiment", ["easy_tabular_ss", "easy_ss_her"])
def test_the_guided_phase_reaches_smart_start_under_slips(experiment):
    """Easy at slip 0.25, a count model learned from 10 tries of every move in the slipping env, S_ss drawn at
    random among the visited cells (a UCB with both weights 0, seeded): 200 guided phases, each stepped in the
    slipping env from S, follow the planner's policy from wherever the agent lands, with the experiment's own random
    steps (``smart_start.guided_epsilon``: 0 for tabular SS, 0.1 for the deep methods). At least 90% arrive within
    the derived limit (3x the planned route), and every phase ends by the limit."""
    from ss_drl.envs.maze import load_maze
    from ss_drl.smart_start import CountModel, Planner, SmartStart
    from ss_drl.training.trainer import guided_limit

    slip, n = 0.25, 200
    maze = load_maze("easy")
    table = torch.from_numpy(maze.transition_table())
    gen = torch.Generator().manual_seed(0)
    free = torch.from_numpy(np.flatnonzero(~maze.walls.reshape(-1)))
    s = free.repeat_interleave(4 * 10)
    a = torch.arange(4).repeat_interleave(10).repeat(free.numel())

    def slipping(cells, actions):
        slipped = torch.rand(cells.shape, generator=gen) < slip
        return table[cells, torch.where(slipped, torch.randint(0, 4, cells.shape, generator=gen), actions)]

    counts = CountModel(maze.n_cells)
    counts.update(s, a, slipping(s, a), torch.zeros(s.numel()))
    assert not counts.structure().deterministic
    settings = compose_cfg(f"+experiment={experiment}").smart_start
    limit = guided_limit(settings, slip)
    assert limit == 3.0
    ss = SmartStart(maze, counts, n, eta=1.0, c_ss=0.0, w_q=0.0, theta=0, planner=Planner(maze.width),
                    generator=torch.Generator().manual_seed(1), guided_limit=limit,
                    guided_epsilon=settings.guided_epsilon)  # fmt: skip
    ss.end_episodes(torch.ones(n, dtype=torch.bool))
    starts = torch.full((n,), maze.start_cell)
    ss.start_episodes(torch.ones(n, dtype=torch.bool), starts, torch.full((n,), maze.goal_cell),
                      lambda states, goals: torch.zeros(goals.numel(), states.numel(), 4))  # fmt: skip
    target = ss.target.clone()
    assert float(ss.planned_steps.double().mean()) > 20  # routes across the maze, not next door
    cells = starts.clone()
    for _ in range(2000):
        if not bool(ss.active.any()):
            break
        was = ss.active.clone()
        nxt = slipping(cells, ss.guide(cells, torch.zeros_like(cells)))
        cells = torch.where(was, nxt, cells)
        ss.after_step(was, cells, torch.zeros(n, dtype=torch.bool))
    assert not ss.active.any()
    limits = (limit * ss.planned_steps.double()).ceil().long()
    assert bool((ss.steps <= limits).all())
    assert float(ss.reached.double().mean()) >= 0.9, float(ss.reached.double().mean())
    assert bool((cells[ss.reached] == target[ss.reached]).all())


def test_an_episode_cut_below_the_optimum_is_said_at_the_start(tmp_path, capsys):
    """At slip 0.9 on easy_small (shortest path 19) the optimal policy needs far more than 19 steps on average: with
    env.max_steps 20 most episodes end before G, and an evaluation's mean length (cut episodes count 20) lies below
    the optimum. The run is allowed; it says so once. With slip 0 and the same cut it does not."""
    from ss_drl.training.greedy import optimum
    from ss_drl.training.trainer import Trainer

    cfg = compose_cfg("+experiment=easy_small_tabular_ss", "env.slip=0.9", "env.max_steps=20")
    trainer = Trainer(cfg, tmp_path / "slip")
    expected = optimum(trainer.maze, 0.9)
    assert trainer.optimal_length == expected > 20 * 3  # far beyond the cut
    err = capsys.readouterr().err.splitlines()
    assert err == [
        f"ss-drl: warning: env.max_steps 20 is below the optimal policy's expected steps from S ({expected:g} at "
        "slip 0.9): most episodes end before G"
    ]
    Trainer(compose_cfg("+experiment=easy_small_tabular_ss", "env.max_steps=20"), tmp_path / "deterministic")
    assert capsys.readouterr().err == ""  # 19 <= 20
