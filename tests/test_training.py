"""The training loop with Smart Start: no guided phase, no change; counts, guided phases, collected batches."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
import torch
from helpers import compose_cfg

from ss_drl.training.collector import MazeCollector
from ss_drl.training.outputs import EPISODE_COLUMNS, EPISODES_FILE
from ss_drl.training.trainer import Trainer

SMALL = ["agent.learning_starts=100", "agent.batch_size=32", "agent.hidden=[32,32]", "agent.embed_dim=8"]


def episode_rows(run_dir: Path) -> list[list[str]]:
    lines = (run_dir / EPISODES_FILE).read_text().splitlines()
    return [line.rsplit(",", 1)[0] for line in lines]  # wall_s is the last column


@pytest.mark.slow
def test_smart_start_without_guided_phases_leaves_the_run_unchanged(tmp_path):
    """Smart Start draws from its own generator, so until it takes a guided phase a run is the run without it.

    A tiny eta builds the controller, wires it into the collector and draws at every episode start, yet (on this
    seed) never takes a guided phase: its episodes.csv equals the one of the run without Smart Start. With eta = 1
    the same seed takes guided phases and the run changes. (eta = 0 builds no controller at all.)
    """
    common = ["trainer.total_env_steps=2500", "env.max_steps=200", *SMALL]
    runs = {
        "off": compose_cfg("+experiment=easy_small_dqn_her", *common),
        "idle": compose_cfg("+experiment=easy_small_ss_her", "smart_start.eta=1e-9", *common),
        "on": compose_cfg("+experiment=easy_small_ss_her", *common),
    }
    eta0 = compose_cfg("+experiment=easy_small_ss_her", "smart_start.eta=0", *common)
    assert Trainer(eta0, tmp_path / "eta0").smart_start is None
    trainers, summaries = {}, {}
    for name, cfg in runs.items():
        trainers[name] = Trainer(cfg, tmp_path / name)
        generator_before = None
        if trainers[name].smart_start is not None:
            generator_before = trainers[name].smart_start.generator.get_state().clone()
        summaries[name] = trainers[name].train()
        if generator_before is not None:  # the controller did draw
            assert not torch.equal(trainers[name].smart_start.generator.get_state(), generator_before), name
    off, idle, on = (episode_rows(tmp_path / name) for name in runs)
    guided = EPISODE_COLUMNS.index("smart_start")
    assert len(off) > 5

    idle_ss = trainers["idle"].smart_start
    assert idle_ss is not None
    assert int(idle_ss.episodes.sum()) == summaries["idle"]["episodes"] == len(idle) - 1  # it saw every episode
    assert summaries["idle"]["smart_start_decisions"] == 0
    assert all(row.split(",")[guided] == "0" for row in idle[1:])
    assert idle == off

    assert summaries["on"]["smart_start_decisions"] > 0
    first_guided = next(i for i, row in enumerate(on) if i > 0 and row.split(",")[guided] == "1")
    assert on[:first_guided] == off[:first_guided]  # identical up to the first guided phase (one env copy) ...
    assert on != off  # ... which changes the run


def _run_collector(
    run_dir: Path, maze: str, steps: int, num_envs: int = 1, eta: float = 1.0, guided_epsilon: float = 0.0
):
    cfg = compose_cfg(
        f"+experiment={maze}_ss_her",
        f"smart_start.eta={eta}",
        f"smart_start.guided_epsilon={guided_epsilon}",  # 0: the route is followed exactly
        f"env.num_envs={num_envs}",
        "env.max_steps=60",
        f"trainer.frames_per_batch={num_envs}",
        *SMALL,
    )
    trainer = Trainer(cfg, run_dir)  # writes the CSV headers only; the collector runs without train()
    collector: MazeCollector = trainer.collector
    batches, episodes = [], []
    while collector.env_steps < steps:
        batch, finished = collector.rollout()
        nxt = batch["next"]
        trainer.counts.update(batch["observation"], batch["action"], nxt["observation"], nxt["reward"])  # as the loop
        batches.append(batch)
        episodes += finished
    return trainer, torch.cat(batches), episodes


def test_counts_equal_the_transitions_taken(tmp_path):
    trainer, batch, episodes = _run_collector(tmp_path, "easy_small", 900, num_envs=3)
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


def test_guided_phase_reaches_smart_start_state_in_planned_steps(tmp_path):
    trainer, batch, episodes = _run_collector(tmp_path, "easy_small", 3000)
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


def test_network_acts_only_on_steps_outside_the_guided_phase(tmp_path, monkeypatch):
    from ss_drl.agents.dqn import DQNAgent

    calls = []
    act = DQNAgent.act
    monkeypatch.setattr(DQNAgent, "act", lambda self, obs, goal: calls.append(obs.numel()) or act(self, obs, goal))
    _, batch, episodes = _run_collector(tmp_path, "easy_small", 3000)
    guided_steps = sum(e.ss_steps for e in episodes)
    assert guided_steps > 100
    running = batch.numel() - sum(e.length for e in episodes)  # steps of the unfinished last episode
    assert running >= 0 and len(calls) >= batch.numel() - guided_steps - running
    assert len(calls) <= batch.numel() - guided_steps


def test_smart_start_without_guided_phases_collects_the_same_transitions(tmp_path):
    """In three env copies: a controller that draws at every episode start but takes no guided phase (tiny eta)
    leaves the collected transitions exactly those of eta = 0 (no controller); eta = 1 changes them."""
    keys = ["observation", "desired_goal", "action", ("next", "observation"), ("next", "reward"), ("next", "done")]
    none, batch_none, episodes_none = _run_collector(tmp_path / "none", "easy_small", 600, num_envs=3, eta=0.0)
    idle, batch_idle, episodes_idle = _run_collector(tmp_path / "idle", "easy_small", 600, num_envs=3, eta=1e-9)
    assert none.smart_start is None and idle.smart_start is not None
    assert len(episodes_idle) > 5 and not any(e.smart_start for e in episodes_idle)
    assert idle.smart_start.decisions == 0
    assert int(idle.smart_start.episodes.sum()) == len(episodes_idle)  # the controller saw every episode end
    for key in keys:
        assert torch.equal(batch_idle[key], batch_none[key]), key

    def ends(episodes):
        return [(e.env_id, e.env_steps, e.length, e.success) for e in episodes]

    assert ends(episodes_idle) == ends(episodes_none)

    _, batch_on, episodes_on = _run_collector(tmp_path / "on", "easy_small", 600, num_envs=3, eta=1.0)
    assert any(e.smart_start for e in episodes_on)
    assert not torch.equal(batch_on["action"], batch_none["action"])


@pytest.mark.slow  # a training run
def test_train_csv_rows_every_log_interval_updates(tmp_path):
    from ss_drl.agents import UPDATE_METRICS
    from ss_drl.ops import linear_schedule
    from ss_drl.training.outputs import TRAIN_COLUMNS, TRAIN_FILE

    cfg = compose_cfg(
        "+experiment=easy_small_ss_her", "trainer.total_env_steps=1500", "trainer.log_interval=50", *SMALL
    )
    summary = Trainer(cfg, tmp_path).train()
    lines = (tmp_path / TRAIN_FILE).read_text().splitlines()
    assert tuple(lines[0].split(",")) == TRAIN_COLUMNS
    rows = [dict(zip(TRAIN_COLUMNS, map(float, line.split(",")))) for line in lines[1:]]
    updates = [int(r["updates"]) for r in rows]
    # One update per env step of every batch that ends at or after learning_starts (100; a batch holds at most 16
    # steps): a row every 50 updates, plus one for the end of the run's remainder.
    total_updates = updates[-1]
    assert 1500 - 100 <= total_updates <= 1500 - 100 + 16
    assert updates[:-1] == list(range(50, total_updates, 50))
    assert rows[-1]["env_steps"] == 1500
    assert summary["env_steps"] == 1500
    for r in rows:
        assert 100 <= r["env_steps"] <= 1500
        assert r["loss"] > 0 and r["td_abs"] > 0 and r["updates_per_s"] > 0  # no regression fits to 0 by 100 updates
        assert r["her_share"] == pytest.approx(round(32 * 4 / 5) / 32)  # k = 4: 26 of 32 items relabeled
        # The items HER did not relabel keep the real goal G (relabeled ones may draw G too).
        assert 1 - r["her_share"] - 1e-6 <= r["goal_share"] <= 1
        assert r["epsilon"] == pytest.approx(linear_schedule(int(r["env_steps"]) - 16, 1.0, 0.05, 5000), abs=0.01)
    assert set(UPDATE_METRICS) <= set(TRAIN_COLUMNS)
    # Without HER no goal is relabeled, and every batch's goal is G.
    no_her = compose_cfg(
        "+experiment=easy_small_ss_her", "her.k=0", "trainer.total_env_steps=600", "trainer.log_interval=50", *SMALL
    )
    Trainer(no_her, tmp_path / "no_her").train()
    lines = (tmp_path / "no_her" / TRAIN_FILE).read_text().splitlines()[1:]
    column = {name: i for i, name in enumerate(TRAIN_COLUMNS)}
    assert lines and all(float(line.split(",")[column["her_share"]]) == 0 for line in lines)
    assert all(float(line.split(",")[column["goal_share"]]) == 1 for line in lines)


@pytest.mark.slow  # a training run
def test_the_evaluated_network_changes_only_the_evaluations(tmp_path):
    """``agent.eval_network=target`` reads another network at evaluation and nothing else: the run's episodes and
    updates are the online run's, row for row, and each eval.csv holds its network's greedy rollouts."""
    from ss_drl.training.greedy import greedy_rollout
    from ss_drl.training.outputs import EVAL_FILE, TRAIN_FILE

    def without_timing(name: str, run: str) -> list[list[str]]:
        rows = [line.split(",") for line in (tmp_path / run / name).read_text().splitlines()]
        timing = [i for i, column in enumerate(rows[0]) if column in ("wall_s", "updates_per_s")]
        return [[c for i, c in enumerate(row) if i not in timing] for row in rows]

    common = ["+experiment=easy_small_ss_her", "trainer.total_env_steps=1500", "env.max_steps=200", *SMALL]
    for network in ("online", "target"):
        trainer = Trainer(compose_cfg(*common, f"agent.eval_network={network}"), tmp_path / network)
        trainer.train()
        assert episode_rows(tmp_path / network) == episode_rows(tmp_path / "online")
        assert without_timing(TRAIN_FILE, network) == without_timing(TRAIN_FILE, "online")
        final = without_timing(EVAL_FILE, network)[-1]
        assert int(final[0]) == 1500  # the last evaluation is at the end of the run
        assert int(final[2]) == greedy_rollout(trainer.agent, trainer.maze, 200).length


def test_episode_rows_record_the_end_cell_and_the_cells_visited_so_far(tmp_path):
    """``end_state`` is the cell each episode ended in (G when it succeeded) and ``states_visited`` the distinct
    cells departed from up to the end of the episode: checked against the transitions, replayed by hand."""
    cfg = compose_cfg(
        "+experiment=easy_small_ss_her",
        "trainer.total_env_steps=1500",
        "env.max_steps=60",
        "trainer.eval_interval=1500",
        *SMALL,
    )
    trainer = Trainer(cfg, tmp_path)
    trainer.start_time = 0.0  # set by train(), which this test replaces with its own loop
    collector, episodes, cells = trainer.collector, [], []
    departed: set[int] = set()
    while collector.env_steps < 1500:
        batch, finished = collector.rollout()
        s, s2 = batch["observation"][:, 0].tolist(), batch["next", "observation"][:, 0].tolist()
        trainer.counts.update(
            batch["observation"], batch["action"], batch["next", "observation"], batch["next", "reward"]
        )
        departed.update(s)
        for episode in finished:  # an episode ends a batch, so its last transition is the batch's last
            assert episode.end_state == s2[-1]
            trainer._log_episode(episode)
            episodes.append(episode)
            cells.append(len(departed))
    trainer.logger.close()
    rows = (tmp_path / EPISODES_FILE).read_text().splitlines()
    header = rows[0].split(",")
    end, visited, success = (header.index(c) for c in ("end_state", "states_visited", "success"))
    rows = [row.split(",") for row in rows[1:]]
    assert len(rows) == len(episodes) >= 20
    goal = "{}:{}".format(*trainer.maze.goal)
    assert any(row[success] == "1" for row in rows) and any(row[success] == "0" for row in rows)
    for row, episode, n in zip(rows, episodes, cells):
        assert row[end] == "{}:{}".format(*trainer.maze.pos(episode.end_state))
        assert (row[end] == goal) == (row[success] == "1")
        assert int(row[visited]) == n
    assert cells == sorted(cells) and cells[0] < cells[-1]


#: The bounds of the model-bounded learner's TD target, in the order ``bounds_in_force`` lists them.
TD_BOUNDS = ["hindsight_bound", "distance_floor", "distance_ceiling", "model_targets"]


@pytest.mark.parametrize(
    ("experiment", "bounds"),
    [
        ("easy_small_ss_her", ["hindsight_bound", "n_step_max"]),
        ("easy_small_ss_her_bounded", [*TD_BOUNDS, "optimistic_floor", "bound_all_actions", "bounded_policy"]),
        ("easy_small_ss_her_bounded agent.bounded_policy=false", [*TD_BOUNDS, "optimistic_floor", "bound_all_actions"]),
        (
            "easy_small_ss_her_bounded agent.optimistic_floor=false agent.bound_all_actions=false "
            "agent.bounded_policy=false",
            TD_BOUNDS,
        ),
        ("easy_small_tabular_ss", []),
    ],
)
def test_summary_lists_the_bounds_in_force(tmp_path, experiment, bounds):
    """``bounds_in_force``: the TD target's bounds the run built, by their switches, then the switches that shape
    the floor and ceiling (optimistic_floor, bound_all_actions) and the policy that reads them (bounded_policy)
    where they are on."""
    name, *overrides = experiment.split()
    trainer = Trainer(compose_cfg(f"+experiment={name}", *overrides), tmp_path)
    assert trainer.summary(completed=False, wall=1.0)["bounds_in_force"] == bounds
