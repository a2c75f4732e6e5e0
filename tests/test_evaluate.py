"""scripts/evaluate.py: load a run's checkpoint, run the greedy policy, draw it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from ss_drl.envs.maze import load_maze
from ss_drl.evaluate import load_agent
from ss_drl.training.greedy import greedy_accuracy, greedy_rollout
from ss_drl.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]


def _count_model_bounds(agent) -> dict[str, torch.Tensor]:
    """The step counts to G that the agent's count-model bounds hold (distance floor and ceiling), by switch."""
    return {bound.key: bound.steps() for bound in agent.td_target.bounds if hasattr(bound, "steps")}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("experiment", "options", "bounds"),
    [
        ("easy_small_ss_her_bounded", [], {"distance_floor", "distance_ceiling"}),
        (
            "easy_small_ss_her_bounded",
            ["agent.distance_floor=false", "agent.optimistic_floor=false"],
            {"distance_ceiling"},
        ),
        ("easy_small_ss_her", [], set()),
    ],
    ids=["bounded", "distance_ceiling", "replay_only"],
)
def test_evaluate_reproduces_the_final_greedy_evaluation(tmp_path, experiment, options, bounds):
    """For the model-bounded DQN, which reads the count model (its distance floor and ceiling: the checkpoint's
    counts are loaded), one with the ceiling alone, and the replay-only DQN, which reads none."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"+experiment={experiment}",
                "trainer.total_env_steps=600",
                "agent.learning_starts=100",
                "agent.batch_size=16",
                *options,
            ],
        )
    trainer = Trainer(cfg, tmp_path)
    summary = trainer.train()
    agent, maze, _ = load_agent(tmp_path)
    trained, loaded = _count_model_bounds(trainer.agent), _count_model_bounds(agent)
    assert set(trained) == set(loaded) == bounds
    for key in bounds:
        torch.testing.assert_close(loaded[key], trained[key])
    rollout = greedy_rollout(agent, maze, 1000)
    assert rollout.length == summary["final_eval_length"]
    assert round(rollout.accuracy, 4) == summary["final_greedy_accuracy"]

    result = subprocess.run(
        [sys.executable, "scripts/evaluate.py", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    assert f"length {summary['final_eval_length']}" in result.stdout
    assert f"greedy accuracy: {rollout.accuracy:.3f}" in result.stdout
    png = tmp_path / "greedy_policy.png"
    assert png.stat().st_size > 1000
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_evaluate_refuses_a_checkpoint_from_before_the_learners_were_renamed(tmp_path):
    """Its config names options and learners this version does not have: one line, exit 2, nothing drawn."""
    old_config = {"method": "ss_her", "agent": {"name": "dqn", "advantage_learning": False}}
    torch.save({"config": old_config}, tmp_path / "checkpoint.pt")
    result = subprocess.run(
        [sys.executable, "scripts/evaluate.py", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"evaluate.py: error: {tmp_path / 'checkpoint.pt'} was written before the learners were renamed "
        "(docs/migration.md): read it with a checkout of 7ac5009"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]


def test_evaluate_without_checkpoint_is_a_clear_error(tmp_path):
    result = subprocess.run(
        [sys.executable, "scripts/evaluate.py", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2
    assert "no checkpoint.pt" in result.stderr
    assert "Traceback" not in result.stderr


def _closer(maze, cell: int, action: int, dist) -> bool:
    """Independent of the code under test: one maze.move and the BFS distance to G."""
    return dist[maze.move(maze.pos(cell), action)] == dist[maze.pos(cell)] - 1


def test_greedy_accuracy_by_hand():
    maze = load_maze("easy_small")
    dist = maze.distances_from(maze.goal)
    reach = [c for c in range(maze.n_cells) if dist[maze.pos(c)] > 0]  # free cells that reach G, G aside
    # a shortest-path policy: accuracy 1
    best = torch.tensor([next((a for a in range(4) if _closer(maze, c, a, dist)), 0) for c in range(maze.n_cells)])
    assert greedy_accuracy(best, maze) == 1.0
    # one constant action everywhere: the fraction of cells where that action goes one step closer
    for action in range(4):
        expected = sum(_closer(maze, c, action, dist) for c in reach) / len(reach)
        assert 0 < expected < 1
        assert greedy_accuracy(torch.full((maze.n_cells,), action), maze) == pytest.approx(expected)
    # spoiling the best policy in k cells (with a move that is not closer) lowers it by exactly k / len(reach)
    spoiled = best.clone()
    worse = [c for c in reach if any(not _closer(maze, c, a, dist) for a in range(4))][:5]
    for c in worse:
        spoiled[c] = next(a for a in range(4) if not _closer(maze, c, a, dist))
    assert greedy_accuracy(spoiled, maze) == pytest.approx(1 - 5 / len(reach))


def test_evaluate_refuses_what_it_cannot_evaluate_in_one_line(tmp_path, capsys):
    """A checkpoint of this format that lacks what the trainer writes, one this version cannot rebuild an agent
    from, and an --out it cannot write: each one line naming the file and the problem, exit 2, before any
    evaluation (these were KeyError, ValueError and FileNotFoundError tracebacks)."""
    from ss_drl.evaluate import main
    from ss_drl.training.checkpoint import FORMAT, FORMAT_KEY, STATE_KEYS, task_config

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        config = task_config(compose("config", overrides=["+experiment=easy_small_ss_her"]))
    path = tmp_path / "checkpoint.pt"

    def refused(*argv) -> list[str]:
        assert main([str(tmp_path), *map(str, argv)]) == 2
        captured = capsys.readouterr()
        assert captured.out == ""  # nothing evaluated
        return captured.err.strip().splitlines()

    state = {FORMAT_KEY: FORMAT, **dict.fromkeys(STATE_KEYS), "config": config}
    torch.save({k: v for k, v in state.items() if k != "agent"}, path)
    assert refused() == [f"evaluate.py: error: {path} lacks agent: not a checkpoint this trainer wrote"]
    torch.save({**state, "counts": {}}, path)  # every key there, but no count model to load
    assert refused() == [f"evaluate.py: error: {path}: cannot rebuild the agent: KeyError: 'n_states'"]
    missing = tmp_path / "nowhere" / "x.png"
    assert refused("--out", missing) == [
        f"evaluate.py: error: --out: {missing}: its folder {missing.parent} does not exist"
    ]
    assert refused("--out", tmp_path) == [
        f"evaluate.py: error: --out: {tmp_path}: is a directory; give a file name such as greedy_policy.png"
    ]
    (line,) = refused("--out", tmp_path / "x.xyz")
    assert line.startswith(f"evaluate.py: error: --out: {tmp_path / 'x.xyz'}: unknown figure format '.xyz' (allowed: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]  # nothing written
