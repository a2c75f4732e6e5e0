"""Tests of the benchmarks (``scripts/benchmark.py``, the top-level ``benchmarks`` package) at their ``--quick`` sizes.

Timings depend on the machine, so no speed is asserted. What is asserted: every section reports the sizes ``--quick``
asked for, its numbers are positive and finite, each derived figure (ratios, sums, the bare update's env-step rate)
agrees with the printed numbers it is derived from, and the HER section timed as many ``sample()`` calls as it says.
The Stable-Baselines3 checks are skipped when it is missing (it is in the ``bench`` extra, not ``dev``).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
# The benchmarks are not installed with ss-drl; they run from the checkout, as scripts/benchmark.py does.
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import cli, her, train, update  # noqa: E402
from benchmarks.common import compose_config  # noqa: E402

needs_sb3 = pytest.mark.skipif(not train.sb3_available(), reason="stable-baselines3 is not installed (bench extra)")


# --- parsing the printed markdown -------------------------------------------------------------------------------------
def tables(text: str) -> list[list[dict[str, str]]]:
    """Every markdown table in ``text``, as a list of rows keyed by the header's cells."""
    found, block = [], []
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            block.append([cell.strip() for cell in re.split(r"(?<!\\)\|", line.strip()[1:-1])])
            continue
        if block:
            header, separator, *rows = block
            assert set("".join(separator)) <= {"-"}, separator
            assert all(len(row) == len(header) for row in rows), block
            found.append([dict(zip(header, row)) for row in rows])
            block = []
    return found


def number(cell: str) -> float:
    """A printed number ("1,234", "0.513", "12.5x", "100.0%")."""
    value = float(cell.replace(",", "").rstrip("x%"))
    assert math.isfinite(value), cell
    return value


def half_ulp(cell: str) -> float:
    """Half a unit in the last printed digit: how far rounding may have moved the number."""
    digits = cell.replace(",", "").rstrip("x%")
    return 0.5 * 10.0 ** -(len(digits.split(".")[1]) if "." in digits else 0)


def assert_quotient(printed: str, numerator: str, denominator: str) -> None:
    """``printed`` is numerator / denominator, each as printed (rounded): the quotient of some values within their
    rounding, itself rounded."""
    n, d = number(numerator), number(denominator)
    dn, dd = half_ulp(numerator), half_ulp(denominator)
    low, high = (n - dn) / (d + dd), (n + dn) / (d - dd)
    assert low - half_ulp(printed) <= number(printed) <= high + half_ulp(printed), (printed, numerator, denominator)


def bullet(text: str, pattern: str) -> re.Match:
    match = re.search(pattern, text, re.MULTILINE)
    assert match, f"no line matches {pattern!r} in:\n{text}"
    return match


def run_main(argv: list[str]) -> str:
    """``benchmarks.cli.main(argv)``'s standard output (torch's thread count restored after)."""
    threads = torch.get_num_threads()
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            assert cli.main(argv) == 0
    finally:
        torch.set_num_threads(threads)
    return out.getvalue()


# --- sections at --quick ----------------------------------------------------------------------------------------------
def test_env_section_quick():
    text = run_main(["--section", "env", "--quick", "--repeats", "1"])
    sizes = cli.QUICK_SIZES["env"]
    (rows,) = tables(text)
    by_env = {row["env"]: row for row in rows}
    raw = by_env["raw gymnasium `gymnasium.make('SSDRL/Easy-v0').unwrapped`"]
    gym = by_env["TorchRL `GymEnv('SSDRL/Easy-v0')`, step_and_maybe_reset"]
    assert (raw["copies"], raw["steps per repeat"]) == ("1", str(sizes["raw_steps"]))
    assert (gym["copies"], gym["steps per repeat"]) == ("1", str(sizes["gym_steps"]))
    native = {int(row["copies"]): row for row in rows if row["env"].startswith("native `BatchedMazeEnv`")}
    assert sorted(native) == [1, 16, 256]
    for n, row in native.items():
        assert row["env"] == f"native `BatchedMazeEnv`, N={n}, step_and_maybe_reset"
        assert int(row["steps per repeat"]) == sizes["batched_iters"] * n  # every copy's steps count
    assert all(number(row["env steps/s"]) > 0 for row in rows)
    one = native[1]["env steps/s"]
    assert_quotient(bullet(text, r"^- native N=1 / TorchRL GymEnv: (\S+)x$")[1], one, gym["env steps/s"])
    assert_quotient(bullet(text, r"^- native N=1 / raw gymnasium: (\S+)x$")[1], one, raw["env steps/s"])
    verdict = bullet(text, r"^- native N=256: (\S+) steps/s; exceeds 1,000,000 steps/s: (yes|no)$")
    assert verdict[1] == native[256]["env steps/s"]
    assert verdict[2] == ("yes" if number(verdict[1]) > 1_000_000 else "no")


def test_planner_section_quick():
    from ss_drl.envs.maze import load_maze, random_maze

    text = run_main(["--section", "planner", "--quick", "--repeats", "1"])
    assert cli.QUICK_SIZES["planner"]["mazes"] == ("easy_small", "random29")  # no 100x100 maze, no Extreme
    (rows,) = tables(text)
    assert [row["maze"] for row in rows] == ["easy_small"] * 2 + ["random29"] * 2
    for name, maze in (("easy_small", load_maze("easy_small")), ("random29", random_maze(29, 29, seed=0))):
        mine = [row for row in rows if row["maze"] == name]
        assert all(row["size"] == f"{maze.height}x{maze.width}" for row in mine)
        assert all(int(row["visited states"]) == int((~maze.walls).sum()) for row in mine)  # fully explored
        assert mine[0]["target S_ss"] == f"start ({maze.start[0]},{maze.start[1]})"
        assert mine[1]["target S_ss"].startswith("random visited (")
    for row in rows:
        times = {key: number(row[key]) for key in row if key.endswith(" ms") or key.endswith("ms, w_q 0")}
        assert len(times) == 5 and all(t > 0 for t in times.values()), row
        # A decision is the selection plus the planning; "w_q 0" selects by counts alone and plans the same way.
        slack = half_ulp(row["selection ms"]) + half_ulp(row["planning ms"]) + half_ulp(row["decision ms"])
        assert abs(times["decision ms"] - times["selection ms"] - times["planning ms"]) <= slack
        assert times["decision ms, w_q 0"] > times["planning ms"] - half_ulp(row["planning ms"])
        assert int(row["VI sweeps"]) > 0
        # A perfect maze, fully explored: value iteration converges and every state has a route to the target.
        assert (row["converged"], row["states with V>0"]) == ("yes", "100.0%")
    assert "Extreme" not in text  # the Extreme verdicts come only with the Extreme maze


def test_her_section_quick_times_the_stated_samples(monkeypatch):
    from ss_drl.her import HindsightReplayBuffer

    calls = []
    sample = HindsightReplayBuffer.sample

    def counted(self, *args, **kwargs):
        calls.append(len(self))
        return sample(self, *args, **kwargs)

    monkeypatch.setattr(HindsightReplayBuffer, "sample", counted)
    repeats = 2
    text = run_main(["--section", "her", "--quick", "--repeats", str(repeats)])
    sizes, samples = cli.QUICK_SIZES["her"]["sizes"], cli.QUICK_SIZES["her"]["samples"]
    assert max(sizes) < 1_000_000
    (rows,) = tables(text)
    assert [number(row["stored transitions"]) for row in rows] == list(sizes)
    for size, row in zip(sizes, rows):
        assert number(row["len(buffer)"]) == size
        assert number(row["samples timed"]) == repeats * samples
        assert number(row["transitions drawn"]) == repeats * samples * 128  # batch 128
        median, p90 = number(row["sample ms (median)"]), number(row["sample ms (p90)"])
        # A quarter of the samples at least lie at or above the median of the repeats' medians.
        # "fill s" is printed to 0.01 s, so a small buffer's fill reads 0.00: only that it is a number is checked.
        assert 0 < median <= p90 + half_ulp(row["sample ms (p90)"]) and number(row["fill s"]) >= 0
        # 10 warm-up samples, then the timed ones, all from the buffer of this size.
        assert calls.count(size) == 10 + repeats * samples
    assert len(calls) == len(sizes) * (10 + repeats * samples)
    ratio = bullet(text, rf"^- ratio {max(sizes):,} / {min(sizes):,}: (\S+) ")[1]
    assert_quotient(ratio, rows[-1]["sample ms (median)"], rows[0]["sample ms (median)"])
    assert f"median of {samples} samples, median of {repeats} repeats" in text


#: The TD target's switches (bounds and their modifiers) of ``DQNSettings``, and the policy that reads them.
SWITCHES = (
    "hindsight_bound",
    "n_step_max",
    "distance_floor",
    "distance_ceiling",
    "bound_all_actions",
    "model_targets",
    "optimistic_floor",
    "bounded_policy",
)


def _learner_settings(maze: str, group: str):
    from ss_drl.agents.settings import DQNSettings

    return DQNSettings.from_config(compose_config([f"+experiment={maze}_ss_her", f"agent={group}"]).agent)


def test_update_section_quick_times_the_stated_updates(monkeypatch):
    """The rows are J, each learner of ``update.LEARNERS`` as its ``agent`` group composes it, and the model-bounded
    one again with TorchRL's SoftUpdate stepping its target network in place of ss-drl's PolyakUpdate, and once with
    its model targets' successors in passes of their own (``TDTarget(fused=False)``). Each row is an agent built
    with those settings and timed for the same number of updates (5 warm-up ones first); "bounds on"
    lists the switches on in its settings; the ratios are the printed medians' quotients."""
    import dataclasses

    from ss_drl.agents.dqn import DQNAgent
    from ss_drl.agents.settings import COUNT_MODEL_KEYS
    from ss_drl.agents.targets import assumptions

    calls = []
    real_update = DQNAgent.update

    def counted(self):
        calls.append(
            (self.settings, tuple(self.td_target.names), type(self.target_updater).__name__, self.td_target.fused)
        )
        return real_update(self)

    monkeypatch.setattr(DQNAgent, "update", counted)
    repeats, sizes = 2, cli.QUICK_SIZES["update"]
    text = run_main(["--section", "update", "--quick", "--repeats", str(repeats)])
    rows, passes = tables(text)
    groups = {name: group for name, group, _ in update.LEARNERS}
    assert set(groups.values()) == {"dqn", "dqn_bounded"}  # the two learners, each from its agent group
    assert [row["setting"] for row in rows] == ["J", *groups, update.SOFT_UPDATE, update.SEPARATE, update.PER_ROW]
    learners = {name: _learner_settings(sizes["maze"], group) for name, group in groups.items()}
    replay_only = next(learners[n] for n, g in groups.items() if g == "dqn")
    bounded_name = next(n for n, g in groups.items() if g == "dqn_bounded")
    assert set(assumptions(dataclasses.replace(replay_only, **dict.fromkeys(SWITCHES, True)))) == set(SWITCHES)
    reference = dataclasses.replace(replay_only, **dict.fromkeys(SWITCHES, False))  # J: no switch on
    expected = {
        "J": (reference, "PolyakUpdate", True),
        **{name: (settings, "PolyakUpdate", True) for name, settings in learners.items()},
        update.SOFT_UPDATE: (learners[bounded_name], "SoftUpdate", True),
        update.SEPARATE: (learners[bounded_name], "PolyakUpdate", False),
        update.PER_ROW: (
            dataclasses.replace(
                learners[bounded_name], factored_bootstrap=True, successor_double_dqn=False, sparse_tables=True
            ),
            "PolyakUpdate",
            True,
        ),
    }
    assert len(set(expected.values())) == len(rows)  # every row a distinct agent
    stages = {"J": update.REFERENCE[1], **{name: stage for name, _, stage in update.LEARNERS}}
    stages[update.SOFT_UPDATE] = stages[update.SEPARATE] = stages[update.PER_ROW] = stages[bounded_name]
    names = {}
    for row in rows:
        settings, updater, fused = expected[row["setting"]]
        mine = [call for call in calls if call[0] == settings and call[2] == updater and call[3] == fused]
        assert len(mine) == 5 + repeats * sizes["updates"], row
        names[row["setting"]] = mine[0][1]
        on = {key for key in SWITCHES if getattr(settings, key)}
        if row["setting"] == update.PER_ROW:
            assert row["bounds on"] == f"as {bounded_name}, " + " ".join(update.PER_ROW_OPTIONS)
        elif row["setting"] in update.VARIANTS:
            assert row["bounds on"] == f"as {bounded_name}"
        else:
            assert (set() if row["bounds on"] == "none" else set(row["bounds on"].split(", "))) == on
        assert set(mine[0][1]) <= on  # the TD target's bounds are switches that are on
        assert row["stage"] == stages[row["setting"]]
        assert number(row["ms per update"]) > 0
        assert_quotient(row["vs J"], row["ms per update"], rows[0]["ms per update"])
    assert len(calls) == len(rows) * (5 + repeats * sizes["updates"])
    # J has no bound; the replay-only learner reads no count model; the model-bounded one does.
    assert names["J"] == ()
    replay_name = next(n for n, g in groups.items() if g == "dqn")
    assert names[replay_name] and not set(names[replay_name]) & set(COUNT_MODEL_KEYS)
    assert set(names[bounded_name]) & set(COUNT_MODEL_KEYS)
    assert f"on {sizes['maze']} ({sizes['transitions']:,} random-walk transitions stored" in text
    assert f"batch {replay_only.batch_size};" in text
    # The second table: the online network's two passes against one, over the bounded update's own row counts.
    batch = learners[bounded_name].batch_size
    extra = batch * (1 + 3)  # the next states and, with model targets, the successors of the three actions not taken
    assert f"({batch} batch rows, {extra:,} bootstrap rows;" in text
    assert [row["online passes"].split(":")[0] for row in passes] == ["two (the update's)", "one"]
    for row in passes:
        assert number(row["rows forward"]) == batch + extra
        assert number(row["ms"]) > 0
        assert_quotient(row["vs two"], row["ms"], passes[0]["ms"])


@pytest.mark.parametrize("successor_double", [True, False])
def test_bootstrap_rows_counts_the_online_networks_bootstrap_rows(successor_double):
    """One loss computation of the model-bounded learner sends the next states and the model targets' successors of
    the three actions not taken through the online network (double DQN), or only the next states when the
    successors take the target network's own max; the count makes no gradient step."""
    from ss_drl.envs.maze import load_maze
    from ss_drl.smart_start import CountModel
    from ss_drl.training.trainer import make_agent

    layout = load_maze("easy_small")
    data = update.random_walk_batch(layout, 500, 100)
    cfg = compose_config(
        ["+experiment=easy_small_ss_her", "agent=dqn_bounded", f"agent.successor_double_dqn={successor_double}"]
    )
    counts = CountModel(layout.n_cells)
    counts.update(data["observation"], data["action"], data["next", "observation"], data["next", "reward"])
    torch.manual_seed(0)
    agent = make_agent(cfg, layout, 0, counts)
    agent.store(data)
    before = [p.detach().clone() for p in agent.loss.parameters()]
    batch = agent.settings.batch_size
    assert update.bootstrap_rows(agent) == (batch * 4 if successor_double else batch)
    assert all(torch.equal(a, b) for a, b in zip(before, agent.loss.parameters()))
    assert agent.updates == 0 and "_online" not in vars(agent.loss)


def test_random_walk_batch_moves_as_the_maze_does():
    from ss_drl.envs.maze import load_maze

    maze = load_maze("easy_small")
    table = maze.transition_table()
    batch = update.random_walk_batch(maze, 3_000, episode_len=100, seed=1)  # reaches G once, cut 29 times
    obs, act, nxt = batch["observation"].view(-1), batch["action"].view(-1), batch["next", "observation"].view(-1)
    term, trunc = batch["next", "terminated"].view(-1), batch["next", "truncated"].view(-1)
    torch.testing.assert_close(nxt, torch.from_numpy(table[obs.numpy(), act.numpy()]))
    assert torch.equal(term, nxt == maze.goal_cell)
    assert torch.equal(batch["next", "reward"].view(-1), term.float())
    assert torch.equal(batch["next", "done"].view(-1), term | trunc)
    done = (term | trunc).tolist()
    assert obs[0] == maze.start_cell
    length = 0
    for i in range(len(done)):
        length += 1
        assert length <= 100 and (trunc[i] == (length == 100 and not term[i]))
        if i + 1 < len(done):
            assert obs[i + 1] == (maze.start_cell if done[i] else nxt[i])
        if done[i]:
            length = 0
    assert term.any() and trunc.any()


@pytest.fixture(scope="module")
def train_quick() -> str:
    return run_main(["--section", "train", "--quick", "--repeats", "1"])


SB3_FORM_RUN = "`easy_dqn_her` in SB3's form"
BARE_RUN = train.BARE_SB3
BARE_OWN_RUN = train.BARE_OWN


def _train_rows(text: str) -> tuple[dict[str, dict[str, str]], list[dict[str, str]]]:
    results, parity = tables(text)
    return {row["run"]: row for row in results}, parity


@pytest.mark.slow  # training runs (scripts/train.py subprocesses)
def test_train_section_quick(train_quick):
    sizes = cli.QUICK_SIZES["train"]
    steps, learning_starts, max_steps = sizes["steps"], sizes["learning_starts"], sizes["max_steps"]
    assert f"{steps} timed env steps after learning_starts={learning_starts}" in train_quick
    rows, parity = _train_rows(train_quick)
    ours = [rows["`easy_dqn_her`"], rows[SB3_FORM_RUN], rows["`easy_ss_her` (Smart Start on; for information)"]]
    cfg = compose_config(["+experiment=easy_dqn_her"])
    fpb, per_step = int(cfg.trainer.frames_per_batch), int(cfg.agent.gradient_steps) / int(cfg.agent.train_freq)
    for row in ours:
        assert row["framework"] == "ss-drl (TorchRL)"
        # The window runs from train.csv's first row to the end of the run. The first row comes LOG_INTERVAL updates
        # (a batch at most later) after the first update, which waits for learning_starts and a full batch stored.
        timed = int(row["timed env steps"])
        wait = max(0, int(cfg.agent.batch_size) - learning_starts)
        assert steps - wait - train.LOG_INTERVAL - fpb <= timed < steps
        # A row is written mid-batch, once its update count is reached: the window may hold a batch's updates more.
        assert 0 < int(row["updates"]) <= (timed + fpb) * per_step
        for key in ("train-phase env steps/s", "updates/s", "whole-run env steps/s"):
            assert number(row[key]) > 0
    for name in (BARE_RUN, BARE_OWN_RUN):
        bare = rows[name]
        assert bare["updates"] == str(steps)
        # At train_freq env steps per gradient_steps updates, the ceiling's env steps/s is its updates/s / per_step.
        assert_quotient(bare["train-phase env steps/s"], bare["updates/s"], str(per_step))
    # The trainer's own network costs more per update than SB3's small MLP over 6 numbers.
    assert number(rows[BARE_OWN_RUN]["updates/s"]) < number(rows[BARE_RUN]["updates/s"])
    ratio = bullet(train_quick, r"^- ours/own ceiling \(.*\): \*\*([0-9.]+)\*\*$")[1]
    assert 0 < float(ratio) < 1
    settings = {row[""]: row for row in parity}
    assert settings["env"]["ss-drl"] == f"`BatchedMazeEnv('easy', 1, max_steps={max_steps})`"
    assert settings["learning_starts"]["ss-drl"] == str(learning_starts)
    # The run compared with SB3 is the replay-only learner: SB3 has no count-model bounds.
    from ss_drl.methods import method_label

    assert method_label(cfg) == "dqn_her"
    assert settings["learner"]["ss-drl"].startswith("dqn_her (`easy_dqn_her`; bounds on: ")
    form = bullet(train_quick, r"^- SB3's form \(.*\): `easy_dqn_her` (.*)$")[1].split()
    assert form == list(train.sb3_form(cfg.agent))
    decisions = bullet(train_quick, r"^- `easy_ss_her`: (\d+) Smart Start decisions per run")
    assert int(decisions[1]) >= 1  # episodes of 100 steps: several episode starts after the first
    if not train.sb3_available():
        assert "stable-baselines3 is not installed" in train_quick
        assert not any(row["framework"].startswith("stable-baselines3") for row in rows.values())


@pytest.mark.slow
@needs_sb3
def test_train_section_quick_against_sb3(train_quick):
    steps = cli.QUICK_SIZES["train"]["steps"]
    rows, parity = _train_rows(train_quick)
    sb3 = rows["SB3 `DQN` + `HerReplayBuffer`"]
    assert sb3["framework"] == f"stable-baselines3 {train.sb3_version()}"
    assert int(sb3["timed env steps"]) == steps and int(sb3["updates"]) == steps  # one update per env step
    assert all(number(sb3[key]) > 0 for key in ("train-phase env steps/s", "updates/s", "whole-run env steps/s"))
    theirs = sb3["train-phase env steps/s"]
    ours = rows["`easy_dqn_her`"]["train-phase env steps/s"]
    same_form = rows[SB3_FORM_RUN]["train-phase env steps/s"]
    ceiling = rows[BARE_RUN]["train-phase env steps/s"]
    assert_quotient(bullet(train_quick, r"^- ratio ours/SB3 \(train-phase .*: \*\*(\S+)\*\*$")[1], ours, theirs)
    assert_quotient(bullet(train_quick, r"^- ratio ours/SB3 with SB3's form .*: \*\*(\S+)\*\*$")[1], same_form, theirs)
    assert_quotient(bullet(train_quick, r"^- ceiling/SB3: \*\*(\S+)\*\*")[1], ceiling, theirs)
    settings = {row[""]: row for row in parity}
    assert settings["learning_starts"]["SB3"] == str(cli.QUICK_SIZES["train"]["learning_starts"])
    assert settings["HER"]["SB3"] == "future, n_sampled_goal=4"


@pytest.mark.slow
def test_train_section_without_sb3_notes_it(monkeypatch):
    monkeypatch.setattr(train, "sb3_available", lambda: False)
    threads = torch.get_num_threads()
    try:
        text = train.bench_train(1, steps=8, max_steps=20, learning_starts=20, experiments=("easy_dqn_her",))
    finally:
        torch.set_num_threads(threads)
    rows, _ = _train_rows(text)
    assert "stable-baselines3 is not installed, so the SB3 rows are skipped" in text
    assert len(rows) == 4 and not any("SB3 `DQN`" in run for run in rows)  # ours, its SB3 form, two bare updates
    assert "ratio ours/SB3" not in text


def test_the_own_ceiling_runs_on_the_experiments_own_world_and_tables():
    """The bare update of the experiment's network is built on the world the experiment trains on (a maze file given
    by ``env.layout``, a MiniGrid task), with its sparse tables stepped by the lazy Adam when it uses them."""
    from ss_drl.agents.tables import LazyAdam
    from ss_drl.training.trainer import make_maze

    cfg = compose_config(["+experiment=extreme_ss_her_bounded", "env.layout=docs/mazes/misleading0.txt"])
    world = make_maze(cfg.env)
    assert train.world_name(cfg.env) == "docs/mazes/misleading0.txt" and world.n_cells == 23 * 23
    built = []
    real_lazy_adam = LazyAdam

    class Recording(real_lazy_adam):
        def __init__(self, params, **kwargs):
            built.append([tuple(p.shape) for p in params])
            super().__init__(params, **kwargs)

    import ss_drl.agents.tables as tables

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(tables, "LazyAdam", Recording)
        dense = train.run_bare_update(cfg.agent, 3, world=world)
        assert built == []  # dense tables: one Adam over every parameter
        sparse = compose_config(["+experiment=extreme_ss_her_bounded", "env.layout=docs/mazes/misleading0.txt",
                                 "agent.sparse_tables=true"])  # fmt: skip
        lazy = train.run_bare_update(sparse.agent, 3, world=world)
    dim = int(cfg.agent.embed_dim)
    assert built == [[(23 * 23, dim), (23 * 23, dim)]]  # the hybrid encoders' two tables, over the maze file's cells
    assert dense["updates_per_s"] > 0 and lazy["updates_per_s"] > 0
    pytest.importorskip("minigrid")
    task_cfg = compose_config(["+experiment=minigrid_ss_her", "env.id=MiniGrid-DoorKey-5x5-v0", "seed=1"])
    task = make_maze(task_cfg.env)
    assert train.world_name(task_cfg.env) == "MiniGrid-DoorKey-5x5-v0 (layout 1)"
    assert task.n_actions == 5 and train.run_bare_update(task_cfg.agent, 3, world=task)["updates_per_s"] > 0


@pytest.mark.parametrize("experiment", ["easy_dqn_her", "easy_dqn_her_bounded"])
def test_sb3_form_is_the_plain_one_step_target_without_bounds(experiment):
    """In SB3's form a learner keeps its network width, batch and schedule but loses every bound, the double-DQN
    target, the dueling head, n-step returns and clipping: the arithmetic of SB3's DQN update."""
    import dataclasses

    from ss_drl.agents.settings import DQNSettings

    ours = DQNSettings.from_config(compose_config([f"+experiment={experiment}"]).agent)
    form = train.sb3_form(compose_config([f"+experiment={experiment}"]).agent)
    theirs = DQNSettings.from_config(compose_config([f"+experiment={experiment}", *form]).agent)
    assert not any(getattr(theirs, key) for key in SWITCHES)
    assert (theirs.double_dqn, theirs.dueling, theirs.n_step, theirs.clip_targets) == (False, False, 1, False)
    assert theirs.loss == "smooth_l1"
    changed = {f.name for f in dataclasses.fields(ours) if getattr(ours, f.name) != getattr(theirs, f.name)}
    assert changed <= {*SWITCHES, "double_dqn", "dueling", "n_step", "clip_targets", "loss"}


@pytest.mark.parametrize(
    ("train_freq", "gradient_steps", "soft_interval", "hard_interval"),
    [
        (1, 1, 1, 100),  # one update per env step: a Polyak step every env step, a copy every 100 env steps
        (4, 1, 4, 400),  # one update per 4 env steps: SB3 steps its target every 4 env steps; 100 updates = 400
        (1, 4, 1, 25),  # 4 updates per env step: SB3 cannot step more than once per env step; 100 updates = 25
        (2, 3, 1, 66),  # 1.5 updates per env step: 100 updates = 66.7 env steps, SB3 copies after 66 of them
    ],
)
def test_sb3_target_update_moves_the_target_at_ss_drl_rate(train_freq, gradient_steps, soft_interval, hard_interval):
    """SB3 updates its target at most once per env step, ss-drl once per update: over the same env steps both move
    the target network by the same Polyak weight, and hard copies come after the same number of updates, to within
    one env step's updates."""
    from omegaconf import OmegaConf

    tau, copies = 0.005, 100
    base = dict(train_freq=train_freq, gradient_steps=gradient_steps, tau=tau, target_update_interval=copies)
    interval, sb3_tau = train.sb3_target_update(OmegaConf.create(dict(base, target_update="soft")))
    assert interval == soft_interval
    updates = interval * gradient_steps / train_freq  # ss-drl's updates in one SB3 target-update interval
    assert math.isclose(1 - sb3_tau, (1 - tau) ** updates, rel_tol=1e-12)
    interval, sb3_tau = train.sb3_target_update(OmegaConf.create(dict(base, target_update="hard")))
    assert sb3_tau == 1.0 and interval == hard_interval
    assert abs(interval * gradient_steps / train_freq - copies) <= gradient_steps / train_freq


# --- against a baseline checkout (issue 49) ---------------------------------------------------------------------------
BASELINE = Path("/work/exp/base")  # a `git worktree add /work/exp/base 7ac5009`, where one exists


def test_baseline_invocation_maps_names_by_the_migration_table():
    lm = list(train.LM_OVERRIDES)
    assert train.baseline_invocation("hard_ss_her_bounded") == ("hard_ss_her", [])
    assert train.baseline_invocation("easy_small_dqn_bounded") == ("easy_small_dqn", [])
    assert train.baseline_invocation("easy_ss_her") == ("easy_ss_her", lm)
    assert train.baseline_invocation("medium_small_dqn_her") == ("medium_small_dqn_her", lm)
    assert train.baseline_invocation("extreme_ss") == ("extreme_ss", lm)
    assert train.baseline_invocation("easy_tabular_ss") == ("easy_tabular_ss", [])
    assert train.baseline_invocation("hard_small_tabular") == ("hard_small_tabular", [])
    # docs/migration.md's overrides, which make 7ac5009's shared setting (LCFATO) the replay-only DQN (LM).
    assert lm == [
        "agent.n_step_max=true",
        "agent.distance_ceiling=false",
        "agent.distance_floor=false",
        "agent.bound_all_actions=false",
        "agent.model_targets=false",
        "agent.optimistic_floor=false",
    ]
    for experiment in ("easy_frontier", "easy_small_frontier", "easy_nonsense"):
        with pytest.raises(ValueError, match="has no baseline"):
            train.baseline_invocation(experiment)


def test_a_baseline_checkout_with_todays_names_runs_the_experiment_as_it_is(tmp_path):
    """A checkout made after the rename (it has conf/agent/dqn_bounded.yaml, as this one does) runs the same name
    with no overrides: mapping it would run another learner (today's ``easy_ss_her`` is replay-only; 7ac5009's
    ``easy_ss_her`` was the model-bounded one). A checkout without that file is mapped as 7ac5009 is."""
    root = Path(__file__).resolve().parent.parent
    assert (root / train.RENAMED_MARKER).is_file()
    for experiment in ("easy_ss_her", "hard_ss_her_bounded", "easy_frontier"):
        assert train.baseline_invocation(experiment, root) == (experiment, [])
    assert train.baseline_invocation("hard_ss_her_bounded", tmp_path) == ("hard_ss_her", [])
    assert train.baseline_invocation("easy_ss_her", tmp_path) == ("easy_ss_her", list(train.LM_OVERRIDES))


def test_baseline_refused_in_one_line_for_an_experiment_without_one(capsys):
    code = cli.main(["--section", "train", "--experiment", "easy_frontier", "--baseline-checkout", str(ROOT)])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert captured.err.splitlines() == [
        "scripts/benchmark.py: --baseline-checkout: easy_frontier: the frontier explorer is new since 7ac5009, so it "
        "has no baseline to run"
    ]


@pytest.fixture(scope="module")
def baseline_checkout(tmp_path_factory) -> Path:
    """7ac5009's worktree where this machine has one; elsewhere (CI's clean clone) a clone of this checkout's HEAD,
    which exercises the same mechanism: its own code, run under the migration table's names."""
    if (BASELINE / "scripts" / "train.py").is_file():
        return BASELINE
    clone = tmp_path_factory.mktemp("baseline") / "checkout"
    done = subprocess.run(["git", "clone", "-q", "--shared", str(ROOT), str(clone)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"no baseline checkout at {BASELINE}, and {ROOT} cannot be cloned: {done.stderr.strip()}")
    return clone


@pytest.mark.slow
def test_train_section_quick_against_a_baseline_checkout(baseline_checkout):
    argv = ["--section", "train", "--quick", "--repeats", "1", "--experiment", "easy_small_dqn_her"]
    text = run_main([*argv, "--baseline-checkout", str(baseline_checkout)])
    commit = train.checkout_commit(baseline_checkout)
    assert f"`$ python scripts/benchmark.py {' '.join(argv)} --baseline-checkout {baseline_checkout}`" in text
    rows, _ = _train_rows(text)
    ours, theirs = rows["`easy_small_dqn_her`"], rows[f"`easy_small_dqn_her` at {commit} (baseline)"]
    assert theirs["framework"] == f"ss-drl {commit}"
    steps = cli.QUICK_SIZES["train"]["steps"]
    for row in (ours, theirs):
        assert 0 < int(row["timed env steps"]) < steps
        assert all(number(row[key]) > 0 for key in ("train-phase env steps/s", "updates/s", "whole-run env steps/s"))
    ratio = bullet(text, r"^- ratio ours/baseline \(train-phase env steps/s, .*: \*\*(\S+)\*\*$")[1]
    assert_quotient(ratio, ours["train-phase env steps/s"], theirs["train-phase env steps/s"])
    # The baseline ran its own code, under the replay-only DQN's name and overrides at 7ac5009.
    line = bullet(
        text, r"^- baseline: `python scripts/train.py (.*)` \(docs/migration.md\), run in (\S+) \(its `ss_drl`: (\S+)\)"
    )
    assert line[1].split() == ["+experiment=easy_small_dqn_her", *train.LM_OVERRIDES]
    assert Path(line[3]).resolve().is_relative_to(baseline_checkout.resolve())
    assert "SB3's form" in text  # a replay-only dqn_her: SB3 can mirror it


# --- command line -----------------------------------------------------------------------------------------------------
def test_quick_shrinks_every_section():
    assert set(cli.QUICK_SIZES) == set(cli.SECTIONS)
    assert max(cli.QUICK_SIZES["her"]["sizes"]) <= 10_000  # not the 1M-transition buffer
    assert not {"random100", "extreme"} & set(cli.QUICK_SIZES["planner"]["mazes"])
    assert cli.QUICK_SIZES["train"]["steps"] < 1_500


def test_cli_threads_option_and_bad_numbers(capsys):
    text = run_main(["--section", "her", "--quick", "--repeats", "1", "--threads", "2"])
    assert "`$ python scripts/benchmark.py --section her --quick --repeats 1 --threads 2`" in text
    assert "(threads 2)" in text
    for option in ("--threads", "--repeats", "--train-steps"):
        with pytest.raises(SystemExit) as exc:
            cli.main(["--section", "her", option, "0"])
        assert exc.value.code != 0
        assert capsys.readouterr().err.splitlines()[-1].endswith(f"error: {option} must be >= 1, got 0")


def test_cli_override_is_checked_before_any_run(capsys):
    for argv, message in (
        (["--section", "train", "--override", "agent.lr"], "error: --override: 'agent.lr' is not KEY=VALUE"),
        (["--section", "her", "--override", "agent.lr=0.1"], "error: --override applies to the train section"),
    ):
        with pytest.raises(SystemExit) as exc:
            cli.main(argv)
        assert exc.value.code != 0
        assert capsys.readouterr().err.splitlines()[-1].endswith(message)


def test_script_runs_from_the_checkout(tmp_path):
    """``python scripts/benchmark.py`` finds ``benchmarks`` (not installed) from any directory, without PYTHONPATH."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "benchmark.py"), "--section", "her", "--quick", "--repeats", "1"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    (rows,) = tables(proc.stdout)
    assert [row["stored transitions"] for row in rows] == [f"{n:,}" for n in cli.QUICK_SIZES["her"]["sizes"]]
    assert np.all([number(row["sample ms (median)"]) > 0 for row in rows])


def test_synthetic_buffer_holds_the_asked_size():
    buffer = her.filled_buffer(1_500, chunk=400)
    assert len(buffer) == 1_500
    assert buffer.sample().numel() == 128
