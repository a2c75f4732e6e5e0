"""Smoke test of the benchmark script: every section runs in-process at tiny sizes and prints its table rows.

No timing is asserted: the numbers depend on the machine.
"""

from __future__ import annotations

import pytest
import torch

from ss_drl import benchmark


def _rows(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("|---")]


def test_env_section_rows():
    text = benchmark.bench_env(1, raw_steps=50, gym_steps=20, batched_iters=20, num_envs=(1, 4))
    rows = _rows(text)
    assert any("raw gymnasium" in row for row in rows)
    assert any("GymEnv" in row for row in rows)
    assert any("N=1," in row for row in rows) and any("N=4," in row for row in rows)
    assert "native N=1 / TorchRL GymEnv" in text and "exceeds 1,000,000 steps/s" in text


def test_train_section_rows():
    threads = torch.get_num_threads()
    try:
        text = benchmark.bench_train(1, steps=8, max_steps=20, learning_starts=20)
    finally:
        torch.set_num_threads(threads)
    rows = _rows(text)
    assert any("`easy_dqn_her`" in row for row in rows)
    assert any("`easy_ss_her`" in row for row in rows)
    assert any("agent.double_dqn=false agent.dueling=false (SB3's form)" in row for row in rows)
    assert any("the eager-PyTorch ceiling" in row for row in rows)
    if benchmark.sb3_available():
        assert any("SB3 `DQN` + `HerReplayBuffer`" in row for row in rows)
        assert "ratio ours/SB3" in text and "with SB3's form of DQN" in text and "ceiling/SB3" in text
    else:
        assert "stable-baselines3 is not installed" in text


def test_planner_section_rows():
    text = benchmark.bench_planner(1, mazes=("easy_small",))
    rows = _rows(text)
    assert sum(row.startswith("| easy_small |") for row in rows) == 2  # start and random visited target
    assert any("start (" in row for row in rows) and any("random visited (" in row for row in rows)


def test_her_section_rows():
    text = benchmark.bench_her(1, sizes=(500, 2_000), samples=3)
    rows = _rows(text)
    assert any(row.startswith("| 500 |") for row in rows)
    assert any(row.startswith("| 2,000 |") for row in rows)
    assert "ratio 2,000 / 500" in text


def test_cli_prints_command_and_table(capsys):
    threads = torch.get_num_threads()
    try:
        assert benchmark.main(["--section", "her", "--quick", "--repeats", "1"]) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert "`$ python scripts/benchmark.py --section her --quick --repeats 1`" in out
    assert "| 10,000 |" in out and "| 1,000,000 |" in out


def test_cli_threads_option(capsys):
    threads = torch.get_num_threads()
    try:
        assert benchmark.main(["--section", "planner", "--repeats", "1", "--threads", "2"]) == 0
        assert "(threads 2)" in capsys.readouterr().out
        with pytest.raises(SystemExit) as exc:
            benchmark.main(["--section", "planner", "--threads", "0"])
    finally:
        torch.set_num_threads(threads)
    assert exc.value.code != 0
    assert "--threads must be >= 1, got 0" in capsys.readouterr().err
