"""ss_drl.analysis.diagnose and scripts/diagnose.py: greedy accuracy and value error by distance to G, Q along the
greedy path from S, and the training data, checked against numbers worked out by hand on easy_small."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from helpers import ROOT, compose_cfg
from omegaconf import OmegaConf

from ss_drl.agents.tabular import TabularQAgent
from ss_drl.analysis.diagnose import (
    DIAGNOSIS_FILE,
    DIAGNOSIS_MD,
    DiagnoseError,
    accuracy_by_distance,
    diagnose_agent,
    diagnose_run,
    exploration_before_first_goal,
    exploration_lines,
    format_markdown,
    training_data,
    value_gamma,
)
from ss_drl.envs.maze import load_maze
from ss_drl.training.greedy import greedy_policy
from ss_drl.training.outputs import EPISODE_COLUMNS, TRAIN_COLUMNS

RIGHT, DOWN, LEFT, UP = range(4)
GAMMA = 0.9


def hand_distance(r: int, c: int) -> int | None:
    """BFS distance to G = (1, 1) in easy_small, worked out from its layout (12 x 9): rows 0-2 all free (Manhattan),
    the corridor rows 3-8 at columns 6-8 (Manhattan: up to row 2, then left), rows 9-11 all free (left of column 6:
    right to column 6 first, 6 - c steps, then r - 1 + 5). None for walls."""
    if r <= 2 or c >= 6:
        return abs(r - 1) + abs(c - 1)
    if r >= 9:
        return (6 - c) + (r - 1) + 5
    return None


@pytest.fixture(scope="module")
def maze():
    return load_maze("easy_small")


@pytest.fixture(scope="module")
def free(maze):
    """{cell: hand distance} of the 71 free cells other than G."""
    out = {}
    for r in range(maze.height):
        for c in range(maze.width):
            d = hand_distance(r, c)
            if d:
                out[maze.cell((r, c))] = d
    return out


def test_hand_distances_are_the_maze(maze, free):
    assert len(free) == 71 and maze.n_free == 72
    dist = maze.distances_from(maze.goal)
    assert all(dist[maze.pos(c)] == d for c, d in free.items())
    assert free[maze.start_cell] == 19


def optimal_tabular(maze, free, gamma=GAMMA) -> TabularQAgent:
    """A tabular agent whose table holds the exact optimal values: Q*(s, a) = gamma^d(s') (d(G) = 0: 1)."""
    agent = TabularQAgent(OmegaConf.create({"gamma": gamma, "alpha": 0.1, "eps_start": 0.0}), maze)
    for cell in free:
        for a in range(4):
            nxt = maze.cell(maze.move(maze.pos(cell), a))
            agent.q[cell, a] = gamma ** (free.get(nxt, 0))
    return agent


# Bucket sizes by hand (width 10): d <= 10 are the 26 cells of rows 0-2 (d <= 8) and the 9 corridor cells with
# r + c - 2 <= 10; d = 21 only (11, 0); the other 35 are 11-20.
BUCKETS = [("1-10", 1, 10, 35), ("11-20", 11, 20, 35), ("21-30", 21, 30, 1)]


def test_optimal_table_is_accurate_everywhere_with_no_value_error(maze, free):
    agent = optimal_tabular(maze, free)
    d = diagnose_agent(agent, maze, GAMMA, max_steps=100)
    assert [(r["distances"], r["min"], r["max"], r["states"]) for r in d["accuracy_by_distance"]] == BUCKETS
    assert [r["accuracy"] for r in d["accuracy_by_distance"]] == [1.0, 1.0, 1.0]
    assert d["greedy_accuracy"] == 1.0
    for row in [*d["value_error_by_distance"], d["value_error"]]:
        assert row["mean_abs_error"] == pytest.approx(0, abs=1e-6)  # float32 of q_values
        assert row["mean_signed_error"] == pytest.approx(0, abs=1e-6)
    assert d["value_error"]["states"] == 71
    path = d["greedy_path"]
    assert path["success"] and path["length"] == 19 and path["optimal_length"] == 19
    assert path["first_off_shortest"] is None and not path["loops"]
    assert [s["distance"] for s in path["steps"]] == list(range(19, 0, -1))
    assert path["mean_abs_error"] == pytest.approx(0, abs=1e-6)
    assert [s["optimal"] for s in path["steps"]] == pytest.approx([GAMMA ** (k - 1) for k in range(19, 0, -1)])


def test_flipped_greedy_actions_by_hand(maze, free):
    agent = optimal_tabular(maze, free)
    s = maze.start_cell
    # Each flip moves away from G or bumps: (1, 2) d 1 right to d 2; S (10, 1) d 19 left to d 20; (11, 0) d 21 left
    # bumps off the grid.
    flips = {maze.cell((1, 2)): RIGHT, s: LEFT, maze.cell((11, 0)): LEFT}
    for cell, a in flips.items():
        agent.q[cell, a] = 1.5
    d = diagnose_agent(agent, maze, GAMMA, max_steps=100, width=10)
    assert [r["accuracy"] for r in d["accuracy_by_distance"]] == [34 / 35, 34 / 35, 0.0]
    assert d["greedy_accuracy"] == pytest.approx(68 / 71)
    # max Q is 1.5 in the flipped cells, exact elsewhere
    signed = [(1.5 - GAMMA**0) / 35, (1.5 - GAMMA**18) / 35, 1.5 - GAMMA**20]
    assert [r["mean_signed_error"] for r in d["value_error_by_distance"]] == pytest.approx(signed, abs=1e-6)
    assert [r["mean_abs_error"] for r in d["value_error_by_distance"]] == pytest.approx(signed, abs=1e-6)
    # From S the greedy step goes left to (10, 0) (d 20), whose best moves are right (back to S) and up, equal:
    # argmax takes the first, right, so the rollout loops at once.
    path = d["greedy_path"]
    assert not path["success"] and path["loops"]
    assert [(st["row"], st["col"], st["distance"]) for st in path["steps"]] == [(10, 1, 19), (10, 0, 20)]
    assert path["first_off_shortest"] == {"step": 0, "cell": s, "row": 10, "col": 1, "distance": 19}
    assert path["mean_abs_error"] == pytest.approx((1.5 - GAMMA**18) / 2, abs=1e-6)
    # a width of 5 splits the same flips into other buckets: 1-5 holds (1, 2), 16-20 S, 21-25 (11, 0)
    rows = {r["distances"]: r for r in accuracy_by_distance(greedy_policy(agent, maze), maze, 5)}
    by_hand = {}
    for d_ in free.values():
        key = f"{(d_ - 1) // 5 * 5 + 1}-{(d_ - 1) // 5 * 5 + 5}"
        by_hand[key] = by_hand.get(key, 0) + 1
    assert {k: r["states"] for k, r in rows.items()} == by_hand
    assert rows["1-5"]["accuracy"] == pytest.approx(1 - 1 / by_hand["1-5"])
    assert rows["16-20"]["accuracy"] == pytest.approx(1 - 1 / by_hand["16-20"])
    assert rows["21-25"]["accuracy"] == 0.0
    assert rows["6-10"]["accuracy"] == rows["11-15"]["accuracy"] == 1.0


class ConstantQ:
    """A fake agent whose greedy Q is the same number for every state, goal and action."""

    def __init__(self, value: float):
        self.value = value

    def greedy_q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        return torch.full((goals.numel(), states.numel(), 4), self.value)


def test_constant_q_by_hand(maze, free):
    c, gamma = 0.3, 0.5
    d = diagnose_agent(ConstantQ(c), maze, gamma, max_steps=50)
    # argmax of equal values is action 0 (right) everywhere: closer only left of G's column (the 3 cells of
    # column 0 in rows 0-2, d 1-2) and in rows 9-11 left of column 6 (18 cells: (11, 0) is d 21, 17 are 11-20).
    assert [r["accuracy"] for r in d["accuracy_by_distance"]] == pytest.approx([3 / 35, 17 / 35, 1.0])
    for lo, hi, row in zip((1, 11, 21), (10, 20, 30), d["value_error_by_distance"]):
        ds = np.array([v for v in free.values() if lo <= v <= hi])
        err = c - gamma ** (ds - 1.0)
        assert row["mean_signed_error"] == pytest.approx(err.mean(), abs=1e-6)
        assert row["mean_abs_error"] == pytest.approx(np.abs(err).mean(), abs=1e-6)
    # the path goes right along row 10 from S, (10, 1) .. (10, 8), and bumps into the grid's edge: a loop; its
    # first step away from G is (10, 6) -> (10, 7), step 5
    path = d["greedy_path"]
    assert [(s["row"], s["col"]) for s in path["steps"]] == [(10, col) for col in range(1, 9)]
    assert path["loops"] and not path["success"]
    assert path["first_off_shortest"]["step"] == 5 and path["first_off_shortest"]["distance"] == 14
    dists = np.array([19, 18, 17, 16, 15, 14, 15, 16])
    assert [s["distance"] for s in path["steps"]] == dists.tolist()
    assert path["mean_abs_error"] == pytest.approx(np.abs(c - gamma ** (dists - 1.0)).mean(), abs=1e-6)


def test_value_gamma():
    assert value_gamma(OmegaConf.create({"gamma": 0.95})) == 0.95
    assert value_gamma(OmegaConf.create({"gamma": 0.95, "step_cost": 1.0})) == 0.95
    assert value_gamma(OmegaConf.create({"gamma": 1.0, "step_cost": 1.0})) == 0.99  # the DQN's UNDISCOUNTED_SCALE


def write_csv(path, columns, rows):
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for row in rows:
            w.writerow([row.get(c, 0) for c in columns])


def test_training_data_by_hand(tmp_path):
    shares = [0.1, 0.2, 0.3, 0.5]
    write_csv(
        tmp_path / "train.csv",
        TRAIN_COLUMNS,
        [{"env_steps": 100 * (i + 1), "goal_share": g} for i, g in enumerate(shares)],
    )
    success = [0, 0, 1, 0, 1, 1, 0, 1]
    smart = [1, 0, 1, 1, 0, 0, 1, 1]
    write_csv(
        tmp_path / "episodes.csv",
        EPISODE_COLUMNS,
        [
            {"episode": i + 1, "env_steps": 50 * (i + 1), "success": s, "smart_start": m}
            for i, (s, m) in enumerate(zip(success, smart))
        ],
    )
    t = training_data(tmp_path)  # total: the largest env steps seen, 400; the last quarter is env steps > 300
    assert t["total_env_steps"] == 400 and t["last_quarter_after_env_steps"] == 300
    assert t["goal_share_mean"] == pytest.approx(0.275)
    assert t["goal_share_last_quarter"] == pytest.approx(0.5)
    assert t["episodes"] == 8 and t["first_success_episode"] == 3 and t["episodes_after_first_success"] == 5
    assert t["success_after_first_success"] == pytest.approx(3 / 5)
    assert t["success_last_quarter"] == pytest.approx(1 / 2)  # episodes at 350 and 400
    assert t["smart_start_share"] == pytest.approx(5 / 8)
    assert t["smart_start_share_last_quarter"] == 1.0
    assert "train_note" not in t and "episodes_note" not in t

    t = training_data(tmp_path, total_env_steps=320)  # the last quarter: > 240
    assert t["goal_share_last_quarter"] == pytest.approx(0.4)
    assert t["success_last_quarter"] == pytest.approx(3 / 4)  # 250, 300, 350, 400
    t = training_data(tmp_path, total_env_steps=1000)  # nothing in the last quarter
    assert t["goal_share_last_quarter"] is None and t["success_last_quarter"] is None


def test_training_data_of_old_and_unlucky_runs(tmp_path):
    write_csv(tmp_path / "episodes.csv", EPISODE_COLUMNS, [{"episode": i, "env_steps": 10 * i} for i in (1, 2)])
    t = training_data(tmp_path)
    assert t["goal_share_mean"] is None and "no train.csv" in t["train_note"]
    assert t["first_success_episode"] is None and t["success_after_first_success"] is None
    assert t["success_last_quarter"] == 0.0  # the episode at 20 > 15
    old = [c for c in TRAIN_COLUMNS if c not in ("her_share", "goal_share")]
    write_csv(tmp_path / "train.csv", old, [{"env_steps": 20}])
    t = training_data(tmp_path)
    assert t["goal_share_mean"] is None and "no goal_share column" in t["train_note"]
    (tmp_path / "episodes.csv").unlink()
    assert "no episodes.csv" in training_data(tmp_path)["episodes_note"]


def test_exploration_before_the_first_goal_by_hand(tmp_path, maze):
    """Three episodes end before the first success (episode 4); episode 5's row comes after it and is left out.
    Distances to G = (1, 1) by hand_distance: (10, 0) 20 (Manhattan 10), (9, 5) 14 (12), (2, 8) 8 (8); the smart
    start states (11, 8) 17 and (2, 2) 2 (episode 1 has no guided phase)."""
    rows = [
        {"episode": 1, "env_steps": 100, "end_state": "10:0", "ss_target": "", "states_visited": 12},
        {"episode": 2, "env_steps": 200, "end_state": "9:5", "ss_target": "11:8", "states_visited": 20},
        {"episode": 3, "env_steps": 300, "end_state": "2:8", "ss_target": "2:2", "states_visited": 25},
        {"episode": 4, "env_steps": 340, "end_state": "1:1", "ss_target": "2:2", "states_visited": 26, "success": 1},
        {"episode": 5, "env_steps": 440, "end_state": "0:0", "ss_target": "11:0", "states_visited": 30},
    ]
    write_csv(tmp_path / "episodes.csv", EPISODE_COLUMNS, rows)
    x = exploration_before_first_goal(tmp_path, maze)
    assert x == {
        "first_goal_env_step": 340,
        "episodes": 3,
        "env_steps": 300,
        "states_visited": 25,
        "free_states": 72,
        "end_true_distance_median": 14.0,
        "end_manhattan_distance_median": 10.0,
        "ss_target_true_distance_median": 9.5,
    }
    write_csv(tmp_path / "episodes.csv", EPISODE_COLUMNS, rows[:2])  # G never reached: every episode counts
    x = exploration_before_first_goal(tmp_path, maze)
    assert x["first_goal_env_step"] is None and x["episodes"] == 2 and x["end_true_distance_median"] == 17.0
    rows[1]["end_state"] = "12:0"  # row 12 lies outside the 12 x 9 maze
    write_csv(tmp_path / "episodes.csv", EPISODE_COLUMNS, rows)
    with pytest.raises(DiagnoseError, match=r"episodes.csv line 3: end_state 12:0 lies outside the 12x9 maze"):
        exploration_before_first_goal(tmp_path, maze)
    old = [c for c in EPISODE_COLUMNS if c not in ("end_state", "states_visited")]
    write_csv(tmp_path / "episodes.csv", old, rows)
    assert "no end_state/states_visited columns" in exploration_before_first_goal(tmp_path, maze)["note"]


def test_exploration_report_reads_right_when_g_is_never_reached_or_reached_at_once(tmp_path, maze):
    """The report's sentence for each case (a bug, fixed: "G never reached env steps", and "the 0 training episodes
    before it (0 env steps) visited 0 of the 72 free cells" when the first episode reached G)."""
    rows = [
        {"episode": 1, "env_steps": 100, "end_state": "10:0", "ss_target": "", "states_visited": 12},
        {"episode": 2, "env_steps": 200, "end_state": "9:5", "ss_target": "11:8", "states_visited": 20},
        {"episode": 3, "env_steps": 240, "end_state": "1:1", "ss_target": "2:2", "states_visited": 26, "success": 1},
    ]

    def report(rows) -> list[str]:
        write_csv(tmp_path / "episodes.csv", EPISODE_COLUMNS, rows)
        return exploration_lines(exploration_before_first_goal(tmp_path, maze), task=False)

    assert report(rows)[0] == (
        "- G first reached at 240 env steps: the 2 training episodes before it (200 env steps) visited 20 of the 72 "
        "free cells."
    )
    assert report(rows[:2])[0] == (
        "- G never reached: the 2 training episodes (200 env steps) visited 20 of the 72 free cells."
    )
    lines = report([{**rows[2], "episode": 1, "env_steps": 40}])
    assert lines == ["- G first reached at 40 env steps, in the first training episode: no episode before it."]


def test_a_damaged_episodes_csv_is_named_with_its_line(tmp_path, maze):
    """Bytes that are not text, a missing column, a cut row, an extra field or a count that is not a number: one
    DiagnoseError naming the file (and the line), where each was a traceback (UnicodeDecodeError, KeyError,
    AttributeError, ValueError)."""
    path = tmp_path / "episodes.csv"
    rows = [
        {"episode": 1, "env_steps": 100, "end_state": "10:0", "ss_target": "", "states_visited": 12},
        {"episode": 2, "env_steps": 200, "end_state": "9:5", "ss_target": "11:8", "states_visited": 20},
    ]

    def refused() -> str:
        with pytest.raises(DiagnoseError) as info:
            exploration_before_first_goal(tmp_path, maze)
        assert "\n" not in str(info.value)
        return str(info.value)

    path.write_bytes(b"\xa5\x00\xff" * 10)
    assert refused().startswith(f"{path}: cannot read it (UnicodeDecodeError: ")
    write_csv(path, [c for c in EPISODE_COLUMNS if c != "success"], rows)
    assert refused() == f"{path}: lacks the columns success"
    write_csv(path, EPISODE_COLUMNS, rows)
    text = path.read_text().splitlines()
    path.write_text("\n".join([*text[:2], ",".join(text[2].split(",")[:9])]) + "\n")  # the last row cut
    assert refused() == f"{path} line 3: fewer fields than the header's {len(EPISODE_COLUMNS)} (a cut file?)"
    path.write_text("\n".join([*text[:2], text[2] + ",extra"]) + "\n")
    assert refused() == f"{path} line 3: more fields than the header's {len(EPISODE_COLUMNS)}"
    write_csv(path, EPISODE_COLUMNS, [rows[0], {**rows[1], "env_steps": "abc"}])
    assert refused() == f"{path} line 3: bad env_steps value 'abc' (expected a count)"


def test_diagnose_run_errors(tmp_path):
    with pytest.raises(DiagnoseError, match="no checkpoint.pt"):
        diagnose_run(tmp_path)
    with pytest.raises(DiagnoseError, match="bucket width must be >= 1"):
        diagnose_run(tmp_path, width=0)
    (tmp_path / "checkpoint.pt").write_text("not a checkpoint")
    with pytest.raises(DiagnoseError) as unreadable:
        diagnose_run(tmp_path)
    unreadable_line = f"{tmp_path / 'checkpoint.pt'} cannot be read (UnpicklingError: invalid load key, 'n'.)"
    assert str(unreadable.value) == unreadable_line
    # A checkpoint from before the learners were renamed (no format marker): one line saying so, not a schema error.
    torch.save({"config": {"method": "ss_her", "agent": {"name": "dqn", "lr_end": None}}}, tmp_path / "checkpoint.pt")
    with pytest.raises(DiagnoseError) as old:
        diagnose_run(tmp_path)
    assert str(old.value) == (
        f"{tmp_path / 'checkpoint.pt'} was written before the learners were renamed (docs/migration.md): read it "
        "with a checkout of 7ac5009"
    )


def run_script(*args):
    return subprocess.run(
        [sys.executable, "scripts/diagnose.py", *map(str, args)], cwd=ROOT, capture_output=True, text=True, timeout=300
    )


def test_script_without_checkpoint_is_a_clear_error(tmp_path):
    result = run_script(tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == f"diagnose.py: error: no checkpoint.pt in {tmp_path}"


@pytest.mark.slow
def test_a_run_with_slips_is_diagnosed_without_them_and_says_so(tmp_path):
    """diagnose.py measures the greedy policy on the deterministic maze; on a run whose moves slip it says so."""
    from ss_drl.training.trainer import Trainer

    run = tmp_path / "run"
    Trainer(
        compose_cfg("+experiment=easy_small_tabular_ss", "env.slip=0.2", "trainer.total_env_steps=300"), run
    ).train()
    result = run_script(run)
    assert result.returncode == 0, result.stderr
    assert json.loads((run / DIAGNOSIS_FILE).read_text())["slip"] == 0.2
    assert "The run's moves slip (env.slip 0.2); what follows measures its greedy policy on the maze without slips" in (
        result.stdout
    )


@pytest.mark.slow
def test_script_on_a_tabular_smart_start_run(tmp_path):
    from ss_drl.training.trainer import Trainer

    run = tmp_path / "run"
    cfg = compose_cfg("+experiment=easy_small_tabular_ss", "trainer.total_env_steps=3000")
    summary = Trainer(cfg, run).train()
    result = run_script(run)
    assert result.returncode == 0, result.stderr
    d = json.loads((run / DIAGNOSIS_FILE).read_text())
    assert set(d) >= {
        "run_dir",
        "experiment",
        "agent",
        "value_gamma",
        "bucket_width",
        "greedy_accuracy",
        "accuracy_by_distance",
        "greedy_path",
        "value_error",
        "value_error_by_distance",
        "training",
    }
    assert d["agent"] == "tabular" and d["value_gamma"] == 0.99 and d["bucket_width"] == 10
    assert [r["distances"] for r in d["accuracy_by_distance"]] == ["1-10", "11-20", "21-30"]
    assert round(d["greedy_accuracy"], 4) == summary["final_greedy_accuracy"]
    path = d["greedy_path"]
    assert path["length"] == summary["final_eval_length"] and path["optimal_length"] == 19
    if path["success"]:
        assert len(path["steps"]) == path["length"]
    training = d["training"]
    assert training["goal_share_mean"] == 1.0 and training["goal_share_last_quarter"] == 1.0  # tabular: only G
    assert training["total_env_steps"] == summary["env_steps"] == 3000
    assert training["episodes"] == summary["episodes"]
    assert 0 < training["smart_start_share"] <= 1
    # the markdown: the section on stdout, the same in diagnosis.md
    out = result.stdout
    assert out.startswith("## easy_small_tabular_ss seed 0 (tabular_ss, agent tabular)")
    for heading in ("### Greedy accuracy and value error by distance to G", "### Q along the greedy path from S"):
        assert heading in out
    assert "| 1-10 | 35 |" in out and "| 21-30 | 1 |" in out and "- Mean goal_share" in out
    assert (run / DIAGNOSIS_MD).read_text() == out

    # --out: one list for all the runs, nothing new in the run directories
    (run / DIAGNOSIS_FILE).unlink()
    result = run_script(run, run, "--bucket-width", "5", "--out", tmp_path / "report")
    assert result.returncode == 0, result.stderr
    both = json.loads((tmp_path / "report" / DIAGNOSIS_FILE).read_text())
    assert len(both) == 2 and both[0] == both[1] and both[0]["bucket_width"] == 5
    assert not (run / DIAGNOSIS_FILE).exists()
    assert result.stdout.count("## easy_small_tabular_ss") == 2
    assert format_markdown(diagnose_run(run, 5)) in result.stdout


# --- a MiniGrid task ----------------------------------------------------------------------------------------------
DOORKEY = "MiniGrid-DoorKey-5x5-v0"


@pytest.fixture(scope="module")
def doorkey():
    """DoorKey-5x5 layout 0: S (3, 1) facing west, the key at (2, 1) north of it, the locked door at (1, 2), G at
    (3, 3); 62 reachable states, 11 actions on a shortest path."""
    pytest.importorskip("minigrid")
    from ss_drl.envs.minigrid import MiniGridTask

    return MiniGridTask(DOORKEY, 0)


def test_exploration_before_the_first_goal_of_a_minigrid_task_by_hand(tmp_path, doorkey):
    """episodes.csv writes a task's states as row:col:direction (0 east, 1 south, 2 west, 3 north), without the door
    and the key, so a state's true distance is the fewest steps from any state with that label. By hand: 1:1:3 (the
    key carried, as it must be to pass (2, 1)) 6 with the door open (right, forward twice to (1, 3), right, forward
    twice; 7 from the state of that label whose door is locked); 3:1:2 9 (the key carried and the door open: right,
    forward twice, right, forward twice, right, forward twice); 2:3:1 1; 1:3:1 2. Manhattan distances to G of the
    cells: (1, 1) 4, (3, 1) 2, (2, 3) 1."""
    rows = [
        {"episode": 1, "env_steps": 30, "end_state": "1:1:3", "ss_target": "", "states_visited": 7},
        {"episode": 2, "env_steps": 60, "end_state": "3:1:2", "ss_target": "1:3:1", "states_visited": 16},
        {"episode": 3, "env_steps": 90, "end_state": "2:3:1", "ss_target": "1:1:3", "states_visited": 20},
        {
            "episode": 4,
            "env_steps": 101,
            "end_state": "3:3:1",
            "ss_target": "2:3:1",
            "states_visited": 24,
            "success": 1,
        },
    ]
    write_csv(tmp_path / "episodes.csv", EPISODE_COLUMNS, rows)
    x = exploration_before_first_goal(tmp_path, doorkey)
    assert x == {
        "first_goal_env_step": 101,
        "episodes": 3,
        "env_steps": 90,
        "states_visited": 20,
        "free_states": 62,  # the task's reachable states, what states_visited counts
        "end_true_distance_median": 6.0,  # of 6, 9, 1
        "end_manhattan_distance_median": 2.0,  # of 4, 2, 1
        "ss_target_true_distance_median": 4.0,  # of 2, 6
    }
    for bad, message in [
        ("1:1", r"line 2: bad end_state value '1:1' \(expected row:col:direction\)"),
        ("5:1:0", r"line 2: end_state 5:1:0 lies outside the 5x5 grid"),
        ("2:2:0", r"line 2: end_state 2:2:0 is not a state of MiniGrid-DoorKey-5x5-v0"),  # a wall
    ]:
        write_csv(tmp_path / "episodes.csv", EPISODE_COLUMNS, [{**rows[0], "end_state": bad}, *rows[1:]])
        with pytest.raises(DiagnoseError, match=message):
            exploration_before_first_goal(tmp_path, doorkey)


@pytest.mark.slow
def test_script_on_a_minigrid_doorkey_run(tmp_path, doorkey):
    """A short SS+HER run on DoorKey-5x5 (episodes cut at 30 steps, so that some end before the first success) is
    diagnosed over the task's states: the buckets cover the 60 states that can reach G (the 2 states on G aside), the
    greedy path names its states, and the exploration statistics read episodes.csv's row:col:direction."""
    from ss_drl.training.trainer import Trainer

    run = tmp_path / "run"
    cfg = compose_cfg(
        "+experiment=minigrid_ss_her", f"env.id={DOORKEY}", "trainer.total_env_steps=1000", "env.max_steps=30"
    )
    summary = Trainer(cfg, run).train()
    result = run_script(run)
    assert result.returncode == 0, result.stderr
    d = json.loads((run / DIAGNOSIS_FILE).read_text())
    assert d["maze"] == DOORKEY and d["world"] == "minigrid" and d["states"] == 62 and d["optimal_length"] == 11
    dist = doorkey.distances_to_goal()
    assert (dist > 0).sum() == 60 and (dist >= 11).sum() == 5
    buckets = [(r["distances"], r["states"]) for r in d["accuracy_by_distance"]]
    assert buckets == [("1-10", 55), ("11-20", 5)]
    assert [(r["distances"], r["states"]) for r in d["value_error_by_distance"]] == buckets
    assert d["value_error"]["states"] == 60
    assert round(d["greedy_accuracy"], 4) == summary["final_greedy_accuracy"]
    path = d["greedy_path"]
    assert path["optimal_length"] == 11 and path["length"] == summary["final_eval_length"]
    assert path["steps"][0]["label"] == "3:1:2" and path["steps"][0]["state"] == 0  # S, facing west
    for s in path["steps"]:
        row, col, _ = map(int, s["label"].split(":"))
        assert (row, col) == (s["row"], s["col"]) and s["cell"] == row * 5 + col
        assert s["distance"] == dist[s["state"]]

    # The exploration statistics, worked out here from episodes.csv: the label's fewest steps to G over its states.
    with (run / "episodes.csv").open(newline="") as f:
        episodes = list(csv.DictReader(f))
    first = next(i for i, e in enumerate(episodes) if e["success"] == "1")
    before = episodes[:first]
    fewest: dict[tuple[int, int, int], int] = {}
    for key, d_ in zip(doorkey.keys, dist.tolist()):
        label = (key.y, key.x, key.direction)
        fewest[label] = min(fewest.get(label, d_), d_)
    ends = [tuple(map(int, e["end_state"].split(":"))) for e in before]
    targets = [tuple(map(int, e["ss_target"].split(":"))) for e in before if e["ss_target"]]
    x = d["exploration"]
    assert before and x["episodes"] == len(before) == d["training"]["first_success_episode"] - 1
    assert x["first_goal_env_step"] == int(episodes[first]["env_steps"]) and x["env_steps"] == 30 * len(before)
    assert x["free_states"] == 62 and 0 < x["states_visited"] <= 62
    assert x["end_true_distance_median"] == np.median([fewest[e] for e in ends])
    assert x["end_manhattan_distance_median"] == np.median([abs(r - 3) + abs(c - 3) for r, c, _ in ends])
    assert x["ss_target_true_distance_median"] == (np.median([fewest[t] for t in targets]) if targets else None)

    out = result.stdout
    assert f"MiniGrid task {DOORKEY} (62 states; shortest path 11)" in out
    assert "| 1-10 | 55 |" in out and "| 11-20 | 5 |" in out and "| step | state | cell |" in out
    assert f"visited {x['states_visited']} of the 62 states" in out
    assert (run / DIAGNOSIS_MD).read_text() == out


def test_out_under_a_file_is_refused_before_the_diagnosis(tmp_path, capsys):
    """--out names a folder to make: under a file it cannot be made (it was a NotADirectoryError traceback after
    the whole diagnosis had run)."""
    from ss_drl.analysis.diagnose import main

    afile = tmp_path / "afile"
    afile.write_text("")
    assert main([str(tmp_path), "--out", str(afile / "sub")]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"diagnose.py: error: --out {afile / 'sub'}: {afile} is not a directory"
    ]
