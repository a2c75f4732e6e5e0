"""Hydra multirun through the joblib launcher, failure isolation, W&B that never blocks training."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings

import pytest
from helpers import ROOT, compose_cfg

from ss_drl.training.outputs import EPISODES_FILE, SUMMARY_FILE
from ss_drl.training.trainer import Trainer

TINY = [
    "trainer.total_env_steps=300",
    "agent.learning_starts=100",
    "agent.batch_size=16",
    "agent.hidden=[16,16]",
    "agent.embed_dim=8",
    "trainer.eval_interval=150",
]


@pytest.mark.slow
def test_joblib_multirun_isolates_a_failing_job_and_plot_skips_it(tmp_path):
    sweep = tmp_path / "sweep"
    result = subprocess.run(
        [
            sys.executable,
            "scripts/train.py",
            "-m",
            "+experiment=easy_small_dqn_her",
            "seed=0,1",
            "agent.gamma=0.9,1.5",  # the gamma=1.5 jobs fail validation
            *TINY,
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    assert "Launching 4 jobs locally" not in result.stdout  # the joblib launcher ran them, not the basic one
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert len(jobs) == 4
    done = [j for j in jobs if (j / SUMMARY_FILE).exists()]
    failed = [j for j in jobs if (j / "FAILED").exists()]
    assert len(done) == 2 and len(failed) == 2
    assert all("agent.gamma" in (j / "FAILED").read_text() for j in failed)
    assert {json.loads((j / SUMMARY_FILE).read_text())["seed"] for j in done} == {0, 1}

    plot = subprocess.run(
        [sys.executable, "scripts/plot.py", str(sweep), "--bootstrap", "50"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert plot.returncode == 0, plot.stderr
    assert plot.stderr.count("skipping") == 2
    assert (sweep / "plots" / "results.md").exists()


def _cfg(*overrides):
    return compose_cfg("+experiment=easy_small_dqn_her", *TINY, *overrides)


def test_wandb_offline_needs_no_network(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path))
    summary = Trainer(_cfg("logger=wandb", "logger.mode=offline"), tmp_path / "run").train()
    assert summary["completed"]
    assert list((tmp_path / "run").rglob("offline-run-*")), "no offline W&B run was written"


def test_failing_wandb_init_falls_back_to_csv(tmp_path, monkeypatch):
    import wandb

    def broken_init(*args, **kwargs):
        raise RuntimeError("no W&B here")

    monkeypatch.setattr(wandb, "init", broken_init)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = Trainer(_cfg("logger=wandb", "logger.mode=online"), tmp_path).train()
    assert summary["completed"]
    assert (tmp_path / EPISODES_FILE).exists()
    assert [w for w in caught if "W&B is off" in str(w.message)]
