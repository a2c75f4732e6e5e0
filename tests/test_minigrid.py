"""MiniGrid tasks with a fixed layout (issue 50): the state graph and its ids, the optimum checked in MiniGrid itself,
HER's achieved goal (the agent's cell), the bounds that hold, refusals in one line, resume, and a learning test."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch
from helpers import TINY, assert_resume_equals_uninterrupted, compose_cfg
from tensordict import TensorDict

pytest.importorskip("minigrid")

from ss_drl.agents.network import GoalQNetwork  # noqa: E402
from ss_drl.agents.targets import DistanceFloor, ModelTargets, Scale, TurnDistanceCeiling  # noqa: E402
from ss_drl.envs.batched import BatchedMazeEnv  # noqa: E402
from ss_drl.envs.minigrid import ACTIONS, MiniGridError, MiniGridTask, StateKey, minigrid_task  # noqa: E402
from ss_drl.evaluate import main as evaluate_main  # noqa: E402
from ss_drl.her import HindsightReplayBuffer  # noqa: E402
from ss_drl.smart_start.counts import CountModel  # noqa: E402
from ss_drl.training.config import ConfigError, validate_config  # noqa: E402
from ss_drl.training.outputs import EPISODES_FILE, EVAL_FILE, SUMMARY_FILE  # noqa: E402
from ss_drl.training.trainer import Trainer, dqn_settings, make_agent, make_maze  # noqa: E402

DOORKEY = "MiniGrid-DoorKey-5x5-v0"
FOURROOMS = "MiniGrid-FourRooms-v0"


def shortest_actions(task: MiniGridTask) -> list[int]:
    """One shortest action sequence from the start to the goal, read off the task's BFS distances."""
    dist, table = task.distances_to_goal(), task.transition_table()
    state, actions = task.start_state, []
    while dist[state] > 0:
        a = next(a for a in range(task.n_actions) if dist[table[state, a]] == dist[state] - 1)
        actions.append(a)
        state = int(table[state, a])
    return actions


def _minigrid_state(env) -> tuple:
    """What MiniGrid itself holds of the agent's situation: cell, direction, each door (open, locked), the carried
    object's type; read from the env, not from the adapter."""
    doors = tuple((bool(o.is_open), bool(o.is_locked)) for o in env.grid.grid if o is not None and o.type == "door")
    carrying = None if env.carrying is None else env.carrying.type
    return int(env.agent_pos[0]), int(env.agent_pos[1]), int(env.agent_dir), doors, carrying


def replay_shortest_path(task: MiniGridTask, env_id: str, layout_seed: int = 0):
    """The task's shortest path replayed in a fresh MiniGrid env (its own reset with the layout seed, its own step
    and reward): per action, ``(the adapter's next state, MiniGrid's own state after the step (:func:`_minigrid_state`),
    reward, terminated, truncated)``."""
    env = gym.make(env_id, max_steps=1000).unwrapped
    env.reset(seed=layout_seed)
    table, state = task.transition_table(), task.start_state
    for a in shortest_actions(task):
        _, reward, terminated, truncated, _ = env.step(ACTIONS[a])
        state = int(table[state, a])
        yield state, _minigrid_state(env), reward, terminated, truncated


# --- the state graph -------------------------------------------------------------------------------------------------
def test_the_bfs_optimum_on_fourrooms_layout_0_is_a_path_replayed_in_minigrid():
    """The optimum is the fewest actions from the start to the goal square on the true state graph. Replayed in a
    fresh MiniGrid env (its own reset with the layout seed, its own step and reward), the path ends on the goal, with
    MiniGrid's own reward, after exactly that many steps; and every state on it is the one the table predicts."""
    task = MiniGridTask(FOURROOMS, 0)
    actions = shortest_actions(task)
    assert len(actions) == task.shortest_path_length == 15
    table = task.transition_table()
    steps = list(replay_shortest_path(task, FOURROOMS))
    for i, (state, in_minigrid, _, terminated, truncated) in enumerate(steps):
        key = task.keys[state]
        assert in_minigrid[:3] == (key.x, key.y, key.direction)
        assert terminated == (i == len(actions) - 1) and not truncated
    state, _, reward, _, _ = steps[-1]
    assert reward == pytest.approx(1 - 0.9 * 15 / 1000) == task.minigrid_return(True, 15, 1000)
    assert task.cells(torch.tensor([state])).item() == task.goal_cell
    # No shorter path: every state one step from the start is at least 14 steps from the goal.
    assert all(task.distances_to_goal()[s] >= 14 for s in table[task.start_state])


def test_doorkey_states_hold_the_door_and_the_key():
    """DoorKey-5x5: the door starts locked and the key on the floor; the shortest path picks up the key (carried from
    then on) and unlocks the door (open from then on), which only a state with both can express."""
    task = MiniGridTask(DOORKEY, 0)
    assert task.n_doors == 1 and task.n_pickables == 1
    start = task.keys[task.start_state]
    assert start.doors == (2,) and start.carrying == 0  # locked, nothing carried
    table, state, seen = task.transition_table(), task.start_state, []
    for a in shortest_actions(task):
        state = int(table[state, a])
        seen.append(task.keys[state])
    assert seen[-1].carrying == 1 and seen[-1].doors == (0,)
    pickup = next(i for i, k in enumerate(seen) if k.carrying == 1)
    unlock = next(i for i, k in enumerate(seen) if k.doors == (0,))
    assert pickup < unlock


def test_the_doorkey_optimum_is_minigrids_own_fewest_actions():
    """DoorKey-5x5 layout 0, checked in MiniGrid alone: a breadth-first search over deep copies of a fresh env (its
    own step, the five actions the adapter keeps) finds the goal in exactly as many actions as the adapter's
    optimum, 11; and the adapter's shortest path, replayed in a fresh env, picks up the key and unlocks the door
    where the adapter's states say it does, and ends on the goal at its last step."""
    import copy
    from collections import deque

    task = MiniGridTask(DOORKEY, 0)
    assert task.shortest_path_length == 11
    env = gym.make(DOORKEY, max_steps=1000).unwrapped
    env.reset(seed=0)
    frontier, seen, depth = deque([(env, 0)]), {_minigrid_state(env)}, None
    while frontier and depth is None:
        node, d = frontier.popleft()
        for a in ACTIONS:
            child = copy.deepcopy(node)
            _, _, terminated, _, _ = child.step(a)
            if terminated:  # on the goal square, or an episode ended elsewhere (not a state to search on)
                if child.grid.get(*child.agent_pos).type == "goal":
                    depth = d + 1
                    break
                continue
            key = _minigrid_state(child)
            if key not in seen:
                seen.add(key)
                frontier.append((child, d + 1))
    assert depth == 11
    for i, (state, in_minigrid, _, terminated, _) in enumerate(replay_shortest_path(task, DOORKEY)):
        x, y, direction, doors, carrying = in_minigrid
        key = task.keys[state]
        assert (x, y, direction) == (key.x, key.y, key.direction)
        assert (carrying == "key") == (key.carrying == 1)
        assert doors == ((key.doors[0] == 0, key.doors[0] == 2),)  # code 0 open, 2 locked
        assert terminated == (i == task.shortest_path_length - 1)


def test_state_ids_are_the_same_in_every_build_and_after_reset():
    """Ids come from the search from the start, so two builds of a layout number every state alike; each reset of
    the batched env puts every copy in the start state, id 0."""
    a, b = MiniGridTask(DOORKEY, 3), MiniGridTask(DOORKEY, 3)
    assert a.keys == b.keys and np.array_equal(a.transition_table(), b.transition_table())
    assert a.start_state == 0 and a.keys[0] == a._key()  # the env is left in the start state
    env = BatchedMazeEnv(a, num_envs=3, max_steps=5)
    td = env.reset()
    assert td["observation"].tolist() == [0, 0, 0] and td["desired_goal"].tolist() == [a.goal_cell] * 3
    for _ in range(5):
        td = env.step_and_maybe_reset(td.set("action", torch.tensor([2, 0, 4])))[1]
    assert td["observation"].tolist() == [0, 0, 0]  # truncated at 5 steps and reset


def test_layouts_differ_by_seed_and_a_state_cap_refuses_in_one_line():
    assert MiniGridTask(DOORKEY, 0).goal_cell == MiniGridTask(DOORKEY, 1).goal_cell  # the goal sits in the corner
    assert MiniGridTask(DOORKEY, 0).shortest_path_length != MiniGridTask(DOORKEY, 1).shortest_path_length
    with pytest.raises(MiniGridError, match=r"^env\.max_states: .* more than 10 reachable states") as info:
        MiniGridTask(DOORKEY, 0, max_states=10)
    assert "\n" not in str(info.value)


def test_the_config_check_and_the_trainer_share_one_state_graph_search(monkeypatch):
    """The config check builds the task (to refuse an unsupported one before the run) and the trainer builds it
    again: one search of the state graph between them, not one each (on LockedRoom, 111,872 states, a run of 300
    env steps spent most of its 40 s in three searches). A refused task is searched again, not kept."""
    searches = []
    enumerate_states = MiniGridTask._enumerate
    monkeypatch.setattr(
        MiniGridTask, "_enumerate", lambda self, start: searches.append(1) or enumerate_states(self, start)
    )
    minigrid_task.cache_clear()
    cfg = compose_cfg("+experiment=minigrid_ss_her", f"env.id={DOORKEY}", "env.layout_seed=2")
    validate_config(cfg)
    task = make_maze(cfg.env)
    assert len(searches) == 1
    assert make_maze(cfg.env) is task and task.layout_seed == 2
    assert (
        make_maze(compose_cfg("+experiment=minigrid_ss_her", f"env.id={DOORKEY}", "env.layout_seed=3").env) is not task
    )
    assert len(searches) == 2
    for _ in range(2):
        with pytest.raises(MiniGridError, match=r"^env\.max_states"):
            minigrid_task(DOORKEY, 2, 10)
    assert len(searches) == 4


@pytest.mark.parametrize(
    ("override", "key", "words"),
    [
        ("env.id=MiniGrid-LavaGapS5-v0", "env.id", "lava"),
        ("env.id=MiniGrid-NoSuchTask-v0", "env.id", "unknown environment"),
        ("env.id=CartPole-v1", "env.id", "not a MiniGrid task"),
        ("env.max_states=20", "env.max_states", "more than 20 reachable states"),
        ("env.slip=0.1", "env.slip", "MiniGrid"),
        ("env.slip=abc", "env.slip", "expected a number"),  # was a traceback: read as a float before it was checked
        ("env.layout_seed=-1", "env.layout_seed", "out of range"),
    ],
)
def test_a_task_the_adapter_cannot_run_is_refused_in_one_line(override, key, words):
    cfg = compose_cfg("+experiment=minigrid_ss_her", f"env.id={DOORKEY}", override)
    with pytest.raises(ConfigError) as info:
        validate_config(cfg)
    message = str(info.value)
    assert message.startswith(f"{key}: ") and words in message and "\n" not in message


@pytest.mark.parametrize("when", ["make", "reset"])
def test_a_task_whose_package_is_missing_is_refused_in_one_line(when):
    """MiniGrid's WFC tasks need imageio, which the minigrid extra does not install: gymnasium's
    DependencyNotInstalled (raised when the grid is generated, or by a task's constructor) reached the user as a
    traceback through Hydra."""
    import gymnasium as gym
    from minigrid.envs import EmptyEnv

    missing = gym.error.DependencyNotInstalled('imageio is missing, please run `pip install "minigrid[wfc]"`')

    class NeedsAPackage(EmptyEnv):
        def __init__(self, **kwargs):
            if when == "make":
                raise missing
            super().__init__(**kwargs)

        def _gen_grid(self, width, height):
            raise missing

    env_id = "MiniGrid-NeedsAPackage-v0"
    gym.register(id=env_id, entry_point=NeedsAPackage)
    try:
        with pytest.raises(ConfigError) as info:
            validate_config(compose_cfg("+experiment=minigrid_ss_her", f"env.id={env_id}"))
    finally:
        del gym.registry[env_id]
    message = str(info.value)
    assert message.startswith(f"env.id: {env_id} needs a package that is not installed: imageio is missing")
    assert "\n" not in message


def test_the_state_encoder_tells_apart_what_the_cell_does_not():
    """States in one cell that differ in direction, door or carried object get different codes; the per-id rows of
    the hybrid encoder start at zero (the code is the features' at first) and there is one per reachable state; the
    goal encoder stays over cells."""
    task = MiniGridTask(DOORKEY, 0)
    net = GoalQNetwork(task, "hybrid", 8, (16,))
    states = torch.arange(task.n_states)
    codes = net.state_encoder(states)
    cell = task.cells(states)
    same_cell = [(a, b) for a in range(task.n_states) for b in range(a) if cell[a] == cell[b]]
    assert same_cell and all(not torch.allclose(codes[a], codes[b]) for a, b in same_cell)
    assert net.state_encoder.cells.weight.shape[0] == task.n_states and not net.state_encoder.cells.weight.any()
    assert net.goal_encoder.cells.weight.shape[0] == task.height * task.width
    assert net(states, torch.full_like(states, task.goal_cell)).shape == (task.n_states, 5)


# --- goals, HER and the bounds ---------------------------------------------------------------------------------------
def test_her_relabels_with_the_agents_cell_not_its_state_id():
    """An episode of DoorKey-5x5 stored in the HER buffer: every relabeled goal is the cell of a next state of a later
    step of the episode (never a state id), and its reward is 1 exactly where the sample's own next state is in that
    cell."""
    task = MiniGridTask(DOORKEY, 0)
    table = task.transition_table()
    states = [task.start_state]
    for a in shortest_actions(task):
        states.append(int(table[states[-1], a]))
    s, s2 = torch.tensor(states[:-1]), torch.tensor(states[1:])
    n = s.numel()
    assert not torch.equal(task.cells(s2), s2)  # ids and cells differ on this path
    done = torch.zeros(n, 1, dtype=torch.bool)
    done[-1] = True
    batch = TensorDict(
        {
            "observation": s, "desired_goal": torch.full((n,), task.goal_cell),
            "action": torch.zeros(n, dtype=torch.long),
            "next": {"observation": s2, "desired_goal": torch.full((n,), task.goal_cell), "reward": done.float(),
                     "terminated": done, "truncated": torch.zeros_like(done), "done": done},
        },
        batch_size=[n],
    ).unsqueeze(1)  # fmt: skip
    buffer = HindsightReplayBuffer(64, 1, 256, "future", k=10**6, generator=torch.Generator().manual_seed(0),
                                   cells=task.cells)  # fmt: skip
    buffer.extend(batch)
    sample = buffer.sample(256)
    cells_after = {t: set(task.cells(s2[t:]).tolist()) for t in range(n)}
    position = {int(x): t for t, x in enumerate(s.tolist())}  # the path visits each state once
    for obs, goal, nxt, reward in zip(
        sample["observation"].tolist(), sample["desired_goal"].tolist(), sample["next", "observation"].tolist(),
        sample["next", "reward"].squeeze(-1).tolist(),
    ):  # fmt: skip
        assert goal in cells_after[position[obs]]
        assert reward == float(task.cells(torch.tensor(nxt)).item() == goal)
    assert sample["next", "reward"].sum() > 0


def test_on_a_fully_explored_model_the_distance_floor_is_the_true_distance():
    """The distance floor searches back from every state in the goal's cell (one per direction, door state and carried
    object): on a count model that has seen every transition it equals the BFS distance on the true graph."""
    task = MiniGridTask(DOORKEY, 0)
    table = task.transition_table()
    live = np.flatnonzero(task.state_cell != task.goal_cell)
    s = np.repeat(live, task.n_actions)
    a = np.tile(np.arange(task.n_actions), live.size)
    s2 = table[s, a]
    counts = CountModel(task.n_states, task.n_actions)
    reward = torch.from_numpy(task.state_cell[s2] == task.goal_cell).float()
    counts.update(torch.from_numpy(s), torch.from_numpy(a), torch.from_numpy(s2), reward)
    goal_states = np.flatnonzero(task.state_cell == task.goal_cell)
    floor = DistanceFloor(counts, task.goal_cell, Scale(0.99, 0.0), goal_states=goal_states)
    assert np.array_equal(floor.distances(), task.distances_to_goal())
    # The model targets see the goal through the successor's cell too.
    targets = ModelTargets(counts, Scale(0.99, 0.0), task.cells)
    state = int(live[np.argmax(task.distances_to_goal()[live] == 1)])  # one step from the goal
    sample = TensorDict(
        {"observation": torch.tensor([state]), "desired_goal": torch.tensor([task.goal_cell])}, batch_size=[1]
    )
    succ = targets.successors(sample)
    held = targets(sample, torch.zeros(1, task.n_actions), succ, torch.zeros(1, task.n_actions))
    into_goal = task.cells(succ.clamp(min=0)) == task.goal_cell
    assert into_goal.any() and torch.equal(held[into_goal], torch.ones(int(into_goal.sum())))


def observe_in(task: MiniGridTask, counts: CountModel, pairs) -> None:
    """Count one transition per (state, action) of ``pairs``, with the task's real successor."""
    s = np.array([p[0] for p in pairs])
    a = np.array([p[1] for p in pairs])
    s2 = task.transition_table()[s, a]
    reward = torch.from_numpy(task.state_cell[s2] == task.goal_cell).float()
    counts.update(torch.from_numpy(s), torch.from_numpy(a), torch.from_numpy(s2), reward)


LEFT, RIGHT, FORWARD, PICKUP, TOGGLE = range(5)


def test_the_turning_ceiling_by_hand_on_an_empty_room():
    """MiniGrid-Empty-5x5: a 3 x 3 room inside the outer wall, the agent at (1, 1) facing right, the goal at (3, 3).
    From the start the fewest actions are forward, forward, right, forward, forward (5); a turn costs an action."""
    task = MiniGridTask("MiniGrid-Empty-5x5-v0", 0)
    assert task.start == (1, 1) and task.goal_cell == 3 * 5 + 3 and task.features[0, 1] == 0
    counts = CountModel(task.n_states, task.n_actions)
    ceiling = TurnDistanceCeiling(counts, task, Scale(1.0, 1.0))
    steps = ceiling.steps().view(task.n_states, 5)
    # untried: left faces up (then right, then 5: 7), right faces down (then 5 the other way round: 6), forward
    # reaches (2, 1) facing right (4 more: 5), pickup and toggle stay (1 + 5)
    assert steps[0].tolist() == [7, 6, 5, 6, 6]
    # The outer wall is not known yet: from (3, 1) facing up, a forward may reach (3, 0), which is no nearer.
    corner_up = task.ids[StateKey(3, 1, 3, (), 0)]  # (column 3, row 1) facing up
    assert steps[corner_up, FORWARD] == 1 + 4  # staying (up: right, then 3) beats the cell ahead (5)
    observe_in(task, counts, [(corner_up, FORWARD)])  # it bumps: (3, 0) is a wall
    walls = ceiling.known_walls()
    assert walls.sum() == 1 and walls[0 * 5 + 3]
    assert ceiling.steps().view(task.n_states, 5)[corner_up, FORWARD] == 1 + 4  # tried: it stayed


def test_a_closed_door_or_a_key_that_blocks_a_forward_is_no_wall():
    """DoorKey-5x5: a forward into the locked door or onto the key stays, but neither cell becomes a wall."""
    task = MiniGridTask(DOORKEY, 0)
    table = task.transition_table()
    blocked = [
        (s, FORWARD) for s in range(task.n_states) if table[s, FORWARD] == s and task.state_cell[s] != task.goal_cell
    ]
    counts = CountModel(task.n_states, task.n_actions)
    observe_in(task, counts, blocked)
    walls = TurnDistanceCeiling(counts, task, Scale(1.0, 1.0)).known_walls()
    openable = [y * task.width + x for _, (x, y) in (*task.doors, *task.pickables)]
    assert not walls[openable].any()
    assert walls.any() and np.array_equal(walls, task.walls.reshape(-1) & walls)  # every wall it knows is one


@pytest.mark.parametrize("env_id, layout", [(DOORKEY, 0), (FOURROOMS, 0), ("MiniGrid-MultiRoom-N4-S5-v0", 2)])
def test_the_turning_ceiling_never_exceeds_the_true_steps_on_any_partial_model(env_id, layout):
    """For count models that have seen random subsets of a task's transitions, every (s, a) off the goal has
    ceiling steps <= 1 + d(s') (s' its real successor, d the BFS distance on the true state graph); on FourRooms,
    which has no doors, they are equal once every transition is seen."""
    task = minigrid_task(env_id, layout)
    dist, table = task.distances_to_goal(), task.transition_table()
    live = task.state_cell != task.goal_cell
    true_steps = np.where(dist[table] >= 0, 1 + dist[table], np.iinfo(np.int64).max)[live]
    rng = np.random.default_rng(0)
    for share in (0.0, 0.1, 0.5, 1.0):
        counts = CountModel(task.n_states, task.n_actions)
        s, a = np.nonzero((rng.random(table.shape) < share) & live[:, None])
        if s.size:
            observe_in(task, counts, list(zip(s.tolist(), a.tolist())))
        steps = TurnDistanceCeiling(counts, task, Scale(1.0, 1.0)).steps().view(task.n_states, -1)[live].numpy()
        assert (steps <= true_steps).all()
        if share == 1.0 and env_id == FOURROOMS:
            np.testing.assert_array_equal(steps, true_steps)
        if share == 0.0:
            assert (steps < true_steps).any()  # the empty model sees through walls


def test_on_minigrid_the_model_bounded_learner_keeps_every_bound(capsys):
    """Every bound of the model-bounded learner holds on MiniGrid (deterministic moves, the count model, a grid
    whose agent turns and moves forward): the ceiling is the turning one, so the optimistic floor stays on too;
    the replay-only learner loses nothing either."""
    settings = dqn_settings(compose_cfg("+experiment=minigrid_ss_her_bounded", f"env.id={DOORKEY}"))
    assert capsys.readouterr().err == ""
    assert settings.distance_floor and settings.model_targets and settings.hindsight_bound
    assert settings.distance_ceiling and settings.optimistic_floor
    dqn_settings(compose_cfg("+experiment=minigrid_ss_her", f"env.id={DOORKEY}"))
    assert capsys.readouterr().err == ""
    # The trainer's agent takes the turning ceiling, picked by the assumptions the config's environment meets.
    cfg = compose_cfg("+experiment=minigrid_ss_her_bounded", f"env.id={DOORKEY}")
    task = minigrid_task(DOORKEY, 0)
    agent = make_agent(cfg, task, seed=0, counts=CountModel(task.n_states, task.n_actions))
    assert any(isinstance(b, TurnDistanceCeiling) for b in agent.td_target.bounds)
    assert capsys.readouterr().err == ""


# --- runs ------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_minigrid_run_resumes_as_if_uninterrupted(tmp_path, capsys):
    """SS+HER (model-bounded) on DoorKey-5x5, cut after its second checkpoint and resumed: the same CSVs as an
    uninterrupted run (the state ids, the count model over them and the env's states come back alike). Its run
    directory then has the per-cell visit counts, and evaluate.py reads it."""
    run = [
        "+experiment=minigrid_ss_her_bounded", f"env.id={DOORKEY}", "env.max_steps=100",
        *(o for o in TINY if not o.startswith("trainer.total_env_steps=")),
        "trainer.total_env_steps=900", "trainer.checkpoint_interval=300",
    ]  # fmt: skip
    full = assert_resume_equals_uninterrupted(run, tmp_path)
    summary = json.loads((full / SUMMARY_FILE).read_text())
    assert summary["maze"] == DOORKEY and summary["optimal_length"] == 11
    bounds = ["hindsight_bound", "distance_floor", "distance_ceiling", "model_targets", "optimistic_floor"]
    assert summary["bounds_in_force"] == [*bounds, "bound_all_actions", "bounded_policy"]
    assert (full / "smart_start.png").is_file()  # visit counts per cell
    # evaluate.py draws the MiniGrid frame with the greedy path.
    assert evaluate_main([str(full), "--out", str(tmp_path / "greedy.png")]) == 0
    assert "(optimal 11)" in capsys.readouterr().out and (tmp_path / "greedy.png").stat().st_size > 0


def test_greedy_path_guided_phase_ends_in_the_very_state_not_its_cell():
    """Smart Start's guided phase ends in any state of S_ss's cell (theta 0), but one sent to an untried greedy move
    (``greedy_path``) ends only in S_ss itself: the move was untried in that direction, with those doors."""
    from ss_drl.smart_start import Planner, SmartStart

    task = minigrid_task(DOORKEY, 0)
    start = task.start_state
    same_cell = [s for s in range(task.n_states) if task.state_cell[s] == task.state_cell[start] and s != start]
    assert same_cell  # the start cell in another direction
    ss = SmartStart(
        task, CountModel(task.n_states, task.n_actions), 1, eta=1.0, c_ss=0.1, w_q=0.0, theta=0,
        planner=Planner(task.width, cells=task.cells), generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    other, target = torch.tensor([same_cell[0]]), torch.tensor([start])
    assert ss.arrived(other, target, torch.tensor([False])).tolist() == [True]
    assert ss.arrived(other, target, torch.tensor([True])).tolist() == [False]
    assert ss.arrived(target, target, torch.tensor([True])).tolist() == [True]


def test_greedy_path_guided_phase_walks_to_the_very_state_then_takes_its_untried_move():
    """DoorKey-5x5 layout 0 with every move counted but one: the shortest path's move in a state x that the path
    enters by a turn, so that the state before it lies in x's cell. The evaluated network's greedy policy is the
    shortest path, so ``greedy_path`` sends the guided phase to x. Walked along the true transitions, the phase
    passes the state before x (same cell, another direction) and ends in x itself; the next action is the untried
    move."""
    from ss_drl.smart_start import Planner, SmartStart

    task = minigrid_task(DOORKEY, 0)
    table, dist = task.transition_table(), task.distances_to_goal()
    path, states = shortest_actions(task), [task.start_state]
    for a in path:
        states.append(int(table[states[-1], a]))
    cell = task.state_cell
    i = next(i for i in range(1, len(path)) if cell[states[i]] == cell[states[i - 1]])  # entered by a turn
    x, move = states[i], path[i]
    counts = CountModel(task.n_states, task.n_actions)
    every_move = [(s, a) for s in range(task.n_states) for a in range(task.n_actions)]
    observe_in(task, counts, [pair for pair in every_move if pair != (x, move)])

    def greedy(states_, goals):  # the shortest path's action is the greedy one (the first on ties, as path's)
        q = -torch.from_numpy(dist[table[states_.numpy()]]).to(torch.float32)
        return q.unsqueeze(0).expand(goals.numel(), -1, -1)

    ss = SmartStart(
        task, counts, 1, eta=1.0, c_ss=0.1, w_q=0.0, theta=0, planner=Planner(task.width, cells=task.cells),
        generator=torch.Generator().manual_seed(0), greedy_path=True, max_steps=100,
    )  # fmt: skip
    one = torch.ones(1, dtype=torch.bool)
    ss.end_episodes(one)
    zeros = lambda states_, goals: torch.zeros(goals.numel(), states_.numel(), task.n_actions)  # noqa: E731
    ss.start_episodes(one, torch.tensor([task.start_state]), torch.tensor([task.goal_cell]), zeros, greedy)
    assert ss.target.tolist() == [x] and ss.exact.tolist() == [True] and ss.greedy_path_decisions == 1
    state, walked, none = task.start_state, [task.start_state], torch.tensor([-1])
    while bool(ss.active.any()):
        was_active = ss.active.clone()
        action = int(ss.guide(torch.tensor([state]), none)[0])
        state = int(table[state, action])
        walked.append(state)
        ss.after_step(was_active, torch.tensor([state]), torch.tensor([False]))
        assert len(walked) <= len(path) + 1
    assert states[i - 1] in walked and walked[-1] == x  # past x's cell in another direction, ended in x itself
    assert int(ss.guide(torch.tensor([x]), none)[0]) == move


@pytest.mark.slow
def test_greedy_path_runs_on_minigrid_and_resumes_as_if_uninterrupted(tmp_path):
    """``smart_start.greedy_path`` on DoorKey-5x5 (states that are not cells; the guided phase then ends in the very
    state whose greedy move is untried, not in any state of its cell): some guided phases go to an untried greedy
    move once G has been reached, and a run cut after its second checkpoint and resumed equals an uninterrupted one
    (the pending move and the exact-arrival flags are in the checkpoint)."""
    run = [
        "+experiment=minigrid_ss_her_bounded", f"env.id={DOORKEY}", "env.max_steps=100", "smart_start.greedy_path=true",
        "agent.learning_starts=100", "trainer.eval_interval=150",  # the shipped network: TINY's one loops on pickup
        "trainer.total_env_steps=1500", "trainer.checkpoint_interval=500",
    ]  # fmt: skip
    full = assert_resume_equals_uninterrupted(run, tmp_path)
    summary = json.loads((full / SUMMARY_FILE).read_text())
    assert summary["first_goal_env_step"] is not None
    assert 0 < summary["greedy_path_decisions"] < summary["smart_start_decisions"]


@pytest.mark.slow
def test_replay_only_ss_her_learns_doorkey_5x5_by_the_rule(tmp_path):
    """The seed paper's method (replay-only SS+HER, its one setting) learns DoorKey-5x5 layout 0 (a key to pick up and
    a locked door; optimum 11 actions) by the learned rule within 4,000 env steps (seed 0 learns at 2,500): the last
    quarter's evaluations all take the optimal 11 steps. MiniGrid's own return is recorded for every episode."""
    cfg = compose_cfg("+experiment=minigrid_ss_her", f"env.id={DOORKEY}", "seed=0", "trainer.total_env_steps=4000")
    summary = Trainer(cfg, tmp_path).train()
    assert summary["optimal_length"] == 11 and summary["bounds_in_force"] == ["hindsight_bound", "n_step_max"]
    evals = np.loadtxt(tmp_path / EVAL_FILE, delimiter=",", skiprows=1, usecols=(0, 2))
    assert evals[0, 1] == 1000  # the untrained greedy policy does not reach the goal
    assert summary["learned_env_step"] is not None and summary["last_quarter_within"] >= 0.9
    assert np.all(evals[evals[:, 0] >= 3000, 1] == 11)
    episodes = np.genfromtxt(tmp_path / EPISODES_FILE, delimiter=",", names=True)
    expected = np.where(episodes["success"] == 1, 1 - 0.9 * episodes["length"] / 1000, 0.0)
    assert np.allclose(episodes["minigrid_return"], expected, atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize(("method", "budget"), [("frontier", 1000), ("tabular_ss", 3000)])
def test_the_baselines_learn_doorkey_5x5(tmp_path, method, budget):
    """The frontier explorer and tabular Smart Start (Keulen's original) on DoorKey-5x5 layout 0, seed 0: both learn
    the 11-action optimum by the rule (measured: the explorer at 500 env steps, tabular SS at 2,500)."""
    cfg = compose_cfg(f"+experiment=minigrid_{method}", f"env.id={DOORKEY}", f"trainer.total_env_steps={budget}")
    summary = Trainer(cfg, tmp_path).train()
    assert summary["optimal_length"] == 11 and summary["first_goal_env_step"] is not None
    assert summary["learned_env_step"] is not None and summary["final_eval_length"] == 11
