"""scripts/evaluate.py: load a run's checkpoint, run the greedy policy, draw it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from ss_drl.evaluate import load_agent
from ss_drl.training.evaluation import greedy_rollout
from ss_drl.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_evaluate_reproduces_the_final_greedy_evaluation(tmp_path):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "+experiment=easy_small_ss_her",
                "trainer.total_env_steps=600",
                "agent.learning_starts=100",
                "agent.batch_size=16",
            ],
        )
    summary = Trainer(cfg, tmp_path).train()
    agent, maze, _ = load_agent(tmp_path)
    assert greedy_rollout(agent, maze, 1000).length == summary["final_eval_length"]

    result = subprocess.run(
        [sys.executable, "scripts/evaluate.py", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    assert f"length {summary['final_eval_length']}" in result.stdout
    png = tmp_path / "greedy_policy.png"
    assert png.stat().st_size > 1000
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_evaluate_without_checkpoint_is_a_clear_error(tmp_path):
    result = subprocess.run(
        [sys.executable, "scripts/evaluate.py", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2
    assert "no checkpoint.pt" in result.stderr
    assert "Traceback" not in result.stderr
