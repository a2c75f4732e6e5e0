"""The TD target's named parts (ss_drl/agents/targets.py): each bound as a pure function against a hand computation,
and the composed target against the hand-composed clamp."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers import compose_cfg
from tensordict import TensorDict

from ss_drl.agents.network import GoalQNetwork
from ss_drl.agents.settings import DQNSettings
from ss_drl.agents.targets import (
    MAZE,
    DistanceCeiling,
    DistanceFloor,
    HindsightBound,
    ModelTargets,
    NStepMax,
    Scale,
    TDTarget,
    resolve_bounds,
)
from ss_drl.envs.maze import parse_maze
from ss_drl.her import HindsightReplayBuffer
from ss_drl.smart_start import CountModel

#: The shortest-path form (-1 per step, 0 on entering the goal, gamma 1): the value of k steps is -(k - 1).
PATH = Scale(gamma=1.0, step_cost=1.0)

#: cells 0 1 2 3 / 4 5 6 7; S = 0, G = 3, one wall (2)
CORRIDOR = parse_maze("S.#G\n....")
RIGHT, DOWN, LEFT, UP = range(4)


def observe(counts: CountModel, maze, pairs) -> None:
    """Count one transition per (s, a), with the maze's real successor."""
    table = maze.transition_table()
    s = torch.tensor([p[0] for p in pairs])
    a = torch.tensor([p[1] for p in pairs])
    s2 = torch.from_numpy(table[s.numpy(), a.numpy()])
    counts.update(s, a, s2, (s2 == maze.goal_cell).float())


# --- the distance ceiling steps ---------------------------------------------------------------------------------
def test_ceiling_by_hand_before_and_after_a_wall_is_seen():
    counts = CountModel(CORRIDOR.n_cells)
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, CORRIDOR.goal_cell, PATH)
    steps = ceiling.steps().view(8, 4)
    # No wall known: cell 2 taken as free, d_opt = 3 2 1 0 / 4 3 2 1 (Manhattan distance to G).
    assert steps[1, RIGHT] == 2  # 1 -> 2 (d 1), then G
    assert steps[0, RIGHT] == 3  # 0 -> 1 (d 2)
    assert steps[0, UP] == 4  # off the grid: stays at 0 (d 3)
    assert steps[6, UP] == 2  # 6 -> 2 (d 1) or a bump (d 2): the nearer
    assert steps[7, UP] == 1  # enters G
    # A move from 1 to the right bumps: cell 2 is a wall. Now d_opt = 5 4 - 0 / 4 3 2 1 (the true distances).
    observe(counts, CORRIDOR, [(1, RIGHT), (0, DOWN)])
    assert ceiling.known_walls().tolist() == [False, False, True, False, False, False, False, False]
    steps = ceiling.steps().view(8, 4)
    assert steps[1, RIGHT] == 5  # tried: stayed at 1 (d 4)
    assert steps[0, DOWN] == 5  # tried: 0 -> 4 (d 4)
    assert steps[0, RIGHT] == 5  # untried: 1 (d 4) or a bump (0, d 5)
    assert steps[6, UP] == 3  # untried, into a known wall: a bump (d 2)
    assert steps[5, UP] == 4  # untried: 1 (d 4) or a bump (5, d 3): the nearer, 3, plus 1


def test_an_off_grid_bump_is_no_wall():
    counts = CountModel(CORRIDOR.n_cells)
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, CORRIDOR.goal_cell, PATH)
    observe(counts, CORRIDOR, [(0, UP), (0, LEFT), (7, RIGHT)])
    assert not ceiling.known_walls().any()


def test_the_ceiling_never_exceeds_the_true_steps_on_any_partial_model():
    """On Hard, for count models that have seen random subsets of the transitions, every (s, a) of a free cell has
    ceiling steps <= 1 + d(s') (s' its real successor), and with every transition seen they are equal."""
    from ss_drl.envs.maze import load_maze

    maze = load_maze("hard")
    table = maze.transition_table()
    free = np.flatnonzero(~maze.walls.reshape(-1))
    true_dist = maze.distances_from(maze.goal).reshape(-1)
    true_steps = 1 + true_dist[table[free]]  # (free, A)
    rng = np.random.default_rng(0)
    pairs = [(int(s), a) for s in free for a in range(4)]
    for share in (0.0, 0.1, 0.5, 1.0):
        counts = CountModel(maze.n_cells)
        chosen = [pairs[i] for i in np.flatnonzero(rng.random(len(pairs)) < share)]
        if chosen:
            observe(counts, maze, chosen)
        steps = DistanceCeiling(counts, maze.height, maze.width, maze.goal_cell, PATH).steps().view(-1, 4)[free].numpy()
        assert (steps <= true_steps).all()
        if share == 1.0:
            np.testing.assert_array_equal(steps, true_steps)
        elif share == 0.0:
            assert (steps < true_steps).any()  # the empty model sees through walls


def test_the_steps_follow_the_count_model_as_it_grows():
    """The cached steps are recomputed when the count model's keys change (and only then)."""
    counts = CountModel(CORRIDOR.n_cells)
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, CORRIDOR.goal_cell, PATH)
    first = ceiling.steps()
    assert ceiling.steps() is first
    observe(counts, CORRIDOR, [(1, RIGHT)])
    assert ceiling.steps()[1 * 4 + RIGHT] == 5


# --- the distance floor steps -----------------------------------------------------------------------------------
def test_floor_by_hand_on_a_built_route():
    """Nothing is known before G has been entered; after the route 0 -> 4 -> 5 -> 6 -> 7 -> G (and a bump at 1),
    each tried (s, a) on it is 1 + its successor's distance along the route, the rest have no bound (0)."""
    counts = CountModel(CORRIDOR.n_cells)
    floor = DistanceFloor(counts, CORRIDOR.goal_cell, PATH)
    assert not floor.steps().any()
    observe(counts, CORRIDOR, [(0, DOWN), (4, RIGHT), (5, RIGHT), (1, RIGHT)])
    assert not floor.steps().any()  # no observed transition into G yet
    observe(counts, CORRIDOR, [(6, RIGHT), (7, UP)])
    steps = floor.steps().view(8, 4)
    expected = torch.zeros(8, 4)
    expected[0, DOWN], expected[4, RIGHT], expected[5, RIGHT], expected[6, RIGHT], expected[7, UP] = 5, 4, 3, 2, 1
    torch.testing.assert_close(steps, expected)  # (1, RIGHT) bumps: cell 1 has no observed route to G
    assert floor.distances().tolist() == [5, -1, -1, 0, 4, 3, 2, 1]
    observe(counts, CORRIDOR, [(1, DOWN), (5, UP)])  # 1 -> 5 joins the route; 5 -> 1 leads back to it
    steps = floor.steps().view(8, 4)
    assert steps[1, DOWN] == 4 and steps[5, UP] == 5  # 1 + d(5) = 4; 1 + d(1) = 1 + 4


def test_the_floor_is_never_below_the_true_steps_nor_the_ceiling():
    """On Hard, for count models that have seen random subsets of the transitions (G's entries always among
    them), every bounded (s, a) has floor steps >= 1 + d(s') >= ceiling steps, and with every transition seen the
    floor is exact on every (s, a) of a free cell."""
    from ss_drl.envs.maze import load_maze

    maze = load_maze("hard")
    table = maze.transition_table()
    free = np.flatnonzero(~maze.walls.reshape(-1) & (np.arange(maze.n_cells) != maze.goal_cell))
    true_dist = maze.distances_from(maze.goal).reshape(-1)
    true_steps = torch.from_numpy(1 + true_dist[table[free]]).float()  # (free, A)
    rng = np.random.default_rng(1)
    pairs = [(int(s), a) for s in free for a in range(4)]
    into_g = [(s, a) for s, a in pairs if table[s, a] == maze.goal_cell]
    for share in (0.3, 0.7, 0.9, 1.0):
        counts = CountModel(maze.n_cells)
        observe(counts, maze, into_g + [pairs[i] for i in np.flatnonzero(rng.random(len(pairs)) < share)])
        steps = DistanceFloor(counts, maze.goal_cell, PATH).steps().view(-1, 4)[free]
        ceiling = DistanceCeiling(counts, maze.height, maze.width, maze.goal_cell, PATH).steps().view(-1, 4)[free]
        bounded = steps > 0
        assert bounded.any()
        assert bool((steps[bounded] >= true_steps[bounded]).all())
        assert bool((true_steps >= ceiling).all())
        if share == 1.0:
            torch.testing.assert_close(steps, true_steps)


def test_the_floor_follows_the_count_model_and_refuses_a_stochastic_one():
    counts = CountModel(CORRIDOR.n_cells)
    floor = DistanceFloor(counts, CORRIDOR.goal_cell, PATH)
    observe(counts, CORRIDOR, [(7, UP)])
    first = floor.steps()
    assert floor.steps() is first  # cached while no new transition is seen
    observe(counts, CORRIDOR, [(6, RIGHT)])
    assert floor.steps()[6 * 4 + RIGHT] == 2
    counts.update(torch.tensor([6]), torch.tensor([RIGHT]), torch.tensor([2]), torch.tensor([0.0]))
    with pytest.raises(ValueError, match="deterministic"):
        floor.steps()


# --- each bound as a pure function on a built sample -----------------------------------------------------------------
def test_hindsight_bound_on_a_relabeled_transition_whose_episode_ends_inside_the_n_step_window():
    """One episode 0 -> 1 -> 2 -> 3 cut after its third step (truncated), stored in a 5-step HER buffer that relabels
    every sample with the episode's final achieved goal (cell 3). From step t the stored episode reaches that goal
    k = 3 - t steps on, inside the 5-step window, which therefore stops there: m = k, the goal entered (terminal),
    and the hindsight bound is the value of k steps, -(k - 1): -2, -1, 0 for t = 0, 1, 2."""
    buffer = HindsightReplayBuffer(100, 1, batch_size=30, strategy="final", k=1_000_000, n_step=5, goal_steps=True)
    obs, nxt = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 3])
    done = torch.tensor([False, False, True])
    batch = TensorDict(
        {
            "observation": obs,
            "desired_goal": torch.full((3,), 7),
            "action": torch.zeros(3, dtype=torch.int64),
            "next": {
                "observation": nxt,
                "desired_goal": torch.full((3,), 7),
                "reward": torch.zeros(3, 1),
                "terminated": torch.zeros(3, 1, dtype=torch.bool),
                "truncated": done.unsqueeze(-1),
                "done": done.unsqueeze(-1),
            },
        },
        batch_size=[3],
    ).unsqueeze(1)
    buffer.extend(batch)
    torch.manual_seed(0)
    sample = buffer.sample()
    assert bool(sample["relabeled"].all())
    t = sample["observation"]
    assert set(t.tolist()) == {0, 1, 2}
    k = 3 - t
    assert sample["desired_goal"].tolist() == [3] * 30
    assert sample["goal_steps"].squeeze(-1).tolist() == k.tolist()
    assert sample["n_steps"].squeeze(-1).tolist() == k.tolist()  # the window stops where the goal is entered
    assert bool(sample["next", "terminated"].all())
    bound = HindsightBound(PATH).lower(sample, None)
    torch.testing.assert_close(bound.squeeze(-1), -(k - 1).float())
    # With 0/1 rewards and gamma 0.9 the same path is worth gamma^(k - 1).
    torch.testing.assert_close(HindsightBound(Scale(0.9, 0.0)).lower(sample, None).squeeze(-1), 0.9 ** (k - 1.0))


def test_hindsight_bound_is_none_where_the_goal_is_not_known_to_be_reached():
    sample = TensorDict({"goal_steps": torch.tensor([[0], [4]])}, batch_size=[2])
    assert HindsightBound(PATH).lower(sample, None).squeeze(-1).tolist() == [-float("inf"), -3.0]


#: The count model of the tests below, on CORRIDOR (cells 0 1 2 3 / 4 5 6 7, S 0, G 3, a wall at 2): the route
#: 0 -> 4 -> 5 -> 6 -> 7 -> G, and 0 -> 1 -> 5. The wall at 2 has never been bumped into: it is unseen.
SEEN = [(0, DOWN), (4, RIGHT), (5, RIGHT), (6, RIGHT), (7, UP), (0, RIGHT), (1, DOWN)]


def corridor_counts() -> CountModel:
    counts = CountModel(CORRIDOR.n_cells)
    observe(counts, CORRIDOR, SEEN)
    return counts


def samples(obs, action, goal, **extra) -> TensorDict:
    data = {"observation": torch.tensor(obs), "action": torch.tensor(action), "desired_goal": torch.tensor(goal)}
    return TensorDict({**data, **extra}, batch_size=[len(obs)])


def test_distance_floor_and_ceiling_on_a_hand_drawn_count_model_with_one_unseen_wall():
    """Floor: the observed routes, d_known = 5 4 - 0 / 4 3 2 1 (0 and 1 go down; 1 -> 5 was seen). Ceiling: with the
    wall at 2 unseen every cell is free, d_opt = |s - G|_1 = 3 2 1 0 / 4 3 2 1. Per action of cell 0 (right, down,
    left, up) for G, in the shortest-path form (k steps are worth -(k - 1)):
    floor: right 1 + d_known(1) = 5 -> -4, down 1 + d_known(4) = 5 -> -4, left and up untried -> none;
    ceiling: right (tried, to 1) 1 + 2 = 3 -> -2, down (tried, to 4) 1 + 4 = 5 -> -4, left and up (off the grid:
    a bump) 1 + d_opt(0) = 4 -> -3. Cell 1 up (untried, off the grid): 1 + d_opt(1) = 3 -> -2, and cell 1 right
    (untried, into the unseen wall): 1 + min(d_opt(2), d_opt(1)) = 2 -> -1. A sample for another goal has no bound."""
    counts = corridor_counts()
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, CORRIDOR.goal_cell, PATH, all_actions=True)
    floor = DistanceFloor(counts, CORRIDOR.goal_cell, PATH, all_actions=True)
    g = CORRIDOR.goal_cell
    batch = samples([0, 1, 0], [RIGHT, RIGHT, RIGHT], [g, g, 5])
    inf = float("inf")
    assert floor.lower_all(batch).tolist() == [[-4, -4, -inf, -inf], [-inf, -3, -inf, -inf], [-inf] * 4]
    assert ceiling.upper_all(batch).tolist() == [[-2, -4, -3, -3], [-1, -3, -2, -2], [inf] * 4]
    assert floor.lower(batch, None).squeeze(-1).tolist() == [-4, -inf, -inf]
    assert ceiling.upper(batch).squeeze(-1).tolist() == [-2, -1, inf]
    assert floor.upper(batch) is None and ceiling.lower(batch, None) is None
    # Without bound_all_actions the bounds hold the taken action only.
    assert DistanceFloor(counts, g, PATH).lower_all(batch) is None
    assert DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, g, PATH).upper_all(batch) is None


def test_optimistic_floor_substitutes_the_ceiling_where_no_route_is_known():
    """With ``optimistic``, an (s, a) with no observed route into G takes the ceiling's value as its floor (cell 0
    left and up: -3; cell 1 right: -1, up: -2); one with a route keeps the route's (cell 0 right: -4, not the
    ceiling's -2)."""
    counts = corridor_counts()
    g = CORRIDOR.goal_cell
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, g, PATH, all_actions=True)
    floor = DistanceFloor(counts, g, PATH, all_actions=True, optimistic=ceiling)
    batch = samples([0, 1], [LEFT, RIGHT], [g, g])
    assert floor.lower_all(batch).tolist() == [[-4, -4, -3, -3], [-1, -3, -2, -2]]
    assert floor.lower(batch, None).squeeze(-1).tolist() == [-3, -1]
    assert floor.assumes == DistanceFloor.assumes | DistanceCeiling.assumes  # it leans on the grid geometry too


def test_k_step_max_takes_the_largest_shorter_target_inside_the_window():
    """Windows of 3 steps (shortest-path form: k steps return -k before the bootstrap), bootstrapped values V after
    steps 1 and 2: m = 3 gives max(-1 + V1, -2 + V2); m = 2 only -1 + V1; m = 1 nothing."""
    bound = NStepMax(PATH, n_step=3)
    batch = TensorDict(
        {"window_observation": torch.tensor([[1, 2, 3]] * 3), "n_steps": torch.tensor([[3], [2], [1]])},
        batch_size=[3],
    )
    assert bound.bootstrap_states(batch).tolist() == [[1, 2]] * 3
    values = torch.tensor([[-10.0, -4.0], [-10.0, -4.0], [-10.0, -4.0]])
    assert bound.lower(batch, values).squeeze(-1).tolist() == [-6.0, -11.0, -float("inf")]


# --- the composed target --------------------------------------------------------------------------------------------
#: Bootstrapped values V(s) per cell for the composed target (every goal alike).
V = torch.tensor([-30.0, -9.0, 0.0, 0.0, -2.0, -8.0, -9.0, 5.0])


def every_bound_binds(fused: bool = True) -> tuple[TDTarget, TensorDict]:
    """The TD target with every bound and the model targets on CORRIDOR's count model above, and the six samples of
    :func:`test_the_composed_target_equals_the_hand_composed_clamp_where_every_bound_binds`."""
    counts = corridor_counts()
    g = CORRIDOR.goal_cell
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, g, PATH, all_actions=True)
    bounds = [HindsightBound(PATH), NStepMax(PATH, 3), DistanceFloor(counts, g, PATH, all_actions=True), ceiling]
    target = TDTarget(PATH, bounds, ModelTargets(counts, PATH), value_range=(-20.0, 0.0), fused=fused)
    goals = torch.tensor([6, 7, g, g, 5, 1])
    m = torch.tensor([[1], [3], [1], [1], [1], [1]])
    after = torch.tensor([5, 6, 1, 7, 7, 0])
    window = torch.stack((after, after, after), dim=1)
    window[1] = torch.tensor([4, 5, 6])
    batch = samples(
        [4, 0, 0, 6, 4, 5],
        [RIGHT, DOWN, RIGHT, UP, LEFT, LEFT],
        goals.tolist(),
        goal_steps=torch.tensor([[2], [0], [0], [0], [0], [0]]),
        n_steps=m,
        window_observation=window,
        next=TensorDict(
            {
                "observation": after,
                "desired_goal": goals,
                "reward": torch.zeros(6, 1),
                "terminated": torch.zeros(6, 1, dtype=torch.bool),
            },
            batch_size=[6],
        ),
    )

    return target, batch


def test_the_composed_target_equals_the_hand_composed_clamp_where_every_bound_binds():
    """Six samples on CORRIDOR with the count model above, each with a different bound deciding its target (value
    range [-20, 0], shortest-path form, m-step windows of width 3, base target -m + V(s_{t+m}), +1 if entered):

    0. goal 6, (4, right) -> 5, goal_steps 2: base -1 + V5 = -9; the hindsight bound -1 binds -> -1.
    1. goal 7, (0, down), window 4 5 6 (m 3): base -3 + V6 = -12; k-step max: max(-1 + V4, -2 + V5) = -3 -> -3.
    2. goal G, (0, right) -> 1: base -1 + V1 = -10; distance floor -4 (ceiling -2) -> -4.
    3. goal G, (6, up) -> 7: base -1 + V7 = 4; distance ceiling -1 (no floor: untried) -> -1.
    4. goal 5, (4, left) -> 7: base 4 -> the value range's 0.
    5. goal 1, (5, left) -> 0: base -31 -> the value range's -20.

    The other actions hold their prediction (-5 everywhere here) or, where the count model saw the action, its
    one-step model target ``-1 + V(s')`` (0 on entering the goal), clamped into the all-action bounds for G. The
    taken action holds its prediction clamped the same way, its model target left uncomputed (the loss does not
    read it): in samples 0 and 1 it would have been -9 and -3.
    0. (4): right taken: -5.                   3. (6): right -> 7 gives 4, floor and ceiling -1 -> -1; down
    1. (0): right -> 1: -10; down taken: -5.      (off the grid) ceiling -2, left ceiling -2, up ceiling -1.
    2. (0) for G: right (taken) -5 into         4. (4), goal 5: right enters it: 0.
       [-4, -2] -> -4; down -3 into [-4, -4]    5. (5): right -> 6: -10.
       -> -4; left and up ceiling -3 over -5."""
    target, batch = every_bound_binds()

    def bootstrap(states, goals):
        return V[states].unsqueeze(-1)

    assert target.taken(batch, bootstrap).squeeze(-1).tolist() == [-1.0, -3.0, -4.0, -1.0, 0.0, -20.0]
    held = target.others(batch, torch.full((6, 4), -5.0), bootstrap)
    expected = [
        [-5, -5, -5, -5],
        [-10, -5, -5, -5],
        [-4, -4, -5, -5],
        [-1, -5, -5, -5],
        [0, -5, -5, -5],
        [-10, -5, -5, -5],
    ]
    assert held.tolist() == expected
    assert target.names == ["hindsight_bound", "n_step_max", "distance_floor", "distance_ceiling", "model_targets"]


@pytest.mark.parametrize("fused", [True, False])
def test_fused_passes_give_the_separate_passes_targets(fused):
    """One bootstrap call for every state (the window's end, the k-step maximum's states, the model targets'
    successors of the actions not taken) against two (the successors on their own, as at 7ac5009): the same targets
    and held values, to float tolerance, on the samples where every bound binds; and the fused target makes one call
    where the separate one makes two. The bootstrap is a real network's double-DQN value, scaled down and added to
    the hand values ``V``, so that the floats differ from the hand test's while every bound still decides the target
    it decides there."""
    torch.manual_seed(0)
    online, target_net = GoalQNetwork(CORRIDOR, "hybrid", 8, (16, 16)), GoalQNetwork(CORRIDOR, "hybrid", 8, (16, 16))
    calls = []

    def bootstrap(states, goals):
        calls.append(states.numel())
        with torch.no_grad():
            q = target_net(states, goals).gather(-1, online(states, goals).argmax(-1, keepdim=True))
        return V[states].unsqueeze(-1) + 1e-3 * q

    q_all = -5.0 + 1e-3 * torch.randn(6, 4)
    one, batch = every_bound_binds(fused)
    other, _ = every_bound_binds(not fused)
    calls.clear()
    got = one(batch, q_all, bootstrap)
    assert calls == ([6 * 3 + 6 * 3] if fused else [6 * 3, 6 * 3])  # no successor of a taken action
    want = other(batch, q_all, bootstrap)
    torch.testing.assert_close(got[0], want[0])
    torch.testing.assert_close(got[1], want[1])
    # Every bound binds, as in the hand-composed test: the taken actions' targets are the hand values up to the noise.
    hand = torch.tensor([-1.0, -3.0, -4.0, -1.0, 0.0, -20.0])
    torch.testing.assert_close(got[0].squeeze(-1), hand, atol=0.01, rtol=0)


def one_step_from_0_to_1() -> TensorDict:
    """One sample: RIGHT from cell 0 to cell 1 for goal 5, a one-step window, no reward, not terminal."""
    batch = samples([0], [RIGHT], [5], n_steps=torch.tensor([[1]]))
    batch["next"] = TensorDict(
        {
            "observation": torch.tensor([1]),
            "desired_goal": torch.tensor([5]),
            "reward": torch.zeros(1, 1),
            "terminated": torch.zeros(1, 1, dtype=torch.bool),
        },
        batch_size=[1],
    )
    return batch


def test_a_lower_and_an_upper_bound_that_cross_give_the_upper():
    """``clamp(y, low, high)`` with low > high is high, as ``min(max(y, low), high)``."""

    class Fixed(HindsightBound):
        def __init__(self, low, high):
            self.low, self.high = torch.tensor([[low]]), torch.tensor([[high]])

        def lower(self, sample, values):
            return self.low

        def upper(self, sample):
            return self.high

    batch = one_step_from_0_to_1()
    target = TDTarget(PATH, [Fixed(-2.0, -6.0)])
    assert target.taken(batch, lambda s, g: V[s].unsqueeze(-1)).item() == -6.0
    assert target.others(batch, torch.zeros(1, 4), lambda s, g: V[s].unsqueeze(-1)) is None


def test_the_taken_target_alone_does_not_depend_on_the_number_of_actions():
    """``TDTarget.taken`` built a (B, 4) stand-in for the predictions, the maze's four moves: with an all-action bound
    and no model targets on a task of five actions (MiniGrid), the stand-in met the bound's (B, 5) and raised."""

    class AllActions(HindsightBound):
        all_actions = True

        def __init__(self):
            pass

        def lower(self, sample, values):
            return torch.tensor([[-3.0]])

        def lower_all(self, sample):
            return torch.full((1, 5), -4.0)

    batch = one_step_from_0_to_1()
    target = TDTarget(PATH, [AllActions()])
    bootstrap = lambda s, g: torch.full((s.numel(), 1), -9.0)  # noqa: E731
    assert target.taken(batch, bootstrap).item() == -3.0  # -1 - 9 = -10, raised to the bound
    held = target.others(batch, torch.full((1, 5), -6.0), bootstrap)
    assert held.tolist() == [[-4.0] * 5]


# --- what each bound assumes ----------------------------------------------------------------------------------------
def bounded_settings() -> DQNSettings:
    return DQNSettings.from_config(compose_cfg("+experiment=easy_ss_her_bounded").agent)


def test_every_bound_holds_on_a_keulen_maze():
    settings = bounded_settings()
    resolved, lines = resolve_bounds(settings, MAZE)
    assert resolved == settings and lines == []


def _turned_off(line: str) -> set[str]:
    """The switches one line of :func:`resolve_bounds` names: ``turned off, since ... (why): agent.a, agent.b``."""
    assert line.startswith("turned off, since this environment breaks what they assume (")
    return set(line.rsplit("): ", 1)[1].split(", "))


def test_bounds_whose_assumption_breaks_are_turned_off_in_one_line():
    """Without deterministic moves every bound of the model-bounded learner goes (each assumes them); without the
    grid's four moves only the ceiling and what leans on it. One line names them all, and why."""
    settings = bounded_settings()
    stochastic, lines = resolve_bounds(settings, MAZE - {"deterministic"})
    on = ("hindsight_bound", "distance_floor", "distance_ceiling", "bound_all_actions", "model_targets")
    assert not any(getattr(stochastic, key) for key in (*on, "optimistic_floor", "bounded_policy"))
    assert len(lines) == 1 and len(lines[0].splitlines()) == 1 and "deterministic moves" in lines[0]
    assert _turned_off(lines[0]) == {f"agent.{key}" for key in (*on, "optimistic_floor", "bounded_policy")}
    gridless, lines = resolve_bounds(settings, MAZE - {"grid_four_moves"})
    assert (gridless.distance_ceiling, gridless.optimistic_floor) == (False, False)
    assert gridless.distance_floor and gridless.model_targets and gridless.hindsight_bound
    assert len(lines) == 1 and _turned_off(lines[0]) == {"agent.distance_ceiling", "agent.optimistic_floor"}
    assert resolve_bounds(settings, MAZE) == (settings, [])
    replay_only = DQNSettings.from_config(compose_cfg("+experiment=easy_ss_her").agent)
    off, lines = resolve_bounds(replay_only, MAZE - {"deterministic"})
    assert (off.hindsight_bound, off.n_step_max) == (False, False)
    assert _turned_off(lines[0]) == {"agent.hindsight_bound", "agent.n_step_max"}
    assert dataclasses.replace(off, hindsight_bound=True, n_step_max=True) == replay_only


def test_the_bounded_policy_goes_with_the_bounds_it_reads():
    """``bounded_policy`` assumes what the all-action bounds do: under slips it is turned off with them, in the same
    line, and set on the command line it is refused."""
    settings = dataclasses.replace(bounded_settings(), bounded_policy=True)
    assert resolve_bounds(settings, MAZE) == (settings, [])
    stochastic, lines = resolve_bounds(settings, MAZE - {"deterministic"})
    assert not stochastic.bounded_policy and not stochastic.bound_all_actions
    assert len(lines) == 1 and {"agent.bounded_policy", "agent.bound_all_actions"} <= _turned_off(lines[0])
    with pytest.raises(ValueError, match=r"^agent\.bounded_policy=true: this environment breaks"):
        resolve_bounds(settings, MAZE - {"deterministic"}, explicit=["bounded_policy"])


def test_a_bound_the_user_set_explicitly_is_refused_instead():
    with pytest.raises(ValueError, match=r"^agent\.distance_ceiling=true: this environment breaks") as err:
        resolve_bounds(bounded_settings(), MAZE - {"grid_four_moves"}, explicit=["distance_ceiling"])
    assert len(str(err.value).splitlines()) == 1


def test_successors_by_the_target_networks_max_skip_the_online_pass():
    """``successor_double=False``: the window's states (6 x 3 rows here) take the online network's action, the model
    targets' successors of the actions not taken (6 x 3) the target network's own max; the bootstrap is asked for the
    split, by hand."""
    target, batch = every_bound_binds()
    target.successor_double = False
    calls = []

    def bootstrap(states, goals, double_rows=None):
        calls.append((states.numel(), double_rows))
        return V[states].unsqueeze(-1)

    held = target.others(batch, torch.full((6, 4), -5.0), bootstrap)
    assert calls == [(6 * 3 + 6 * 3, 6 * 3)]
    assert held.tolist()[1] == [-10, -5, -5, -5]  # the successors' values as before: V is the bootstrap's


def test_loss_bootstrap_splits_double_dqn_from_the_target_max():
    """GoalDQNLoss.bootstrap with ``double_rows``: the first rows are valued at the online network's greedy action,
    the rest at the target network's max, each checked against the two networks called directly."""
    from ss_drl.agents.dqn import GoalDQNLoss

    torch.manual_seed(0)
    online = GoalQNetwork(CORRIDOR, "hybrid", 8, (16, 16))
    loss = GoalDQNLoss(online, every_bound_binds()[0])
    with torch.no_grad():
        for p in loss.target_value_network_params.values(True, True):
            p.add_(torch.randn_like(p) * 0.1)
    states, goals = torch.tensor([0, 1, 4, 5, 6, 7]), torch.tensor([7, 7, 2, 2, 5, 5])
    got = loss.bootstrap(states, goals, double_rows=2)
    with torch.no_grad():
        q_target = loss.target_value_network(states, goals)
        greedy = online(states[:2], goals[:2]).argmax(-1, keepdim=True)
    torch.testing.assert_close(got[:2], q_target[:2].gather(-1, greedy))
    torch.testing.assert_close(got[2:], q_target[2:].amax(-1, keepdim=True))


@pytest.mark.parametrize("encoder", ["hybrid", "embedding", "coords"])
def test_factored_q_equals_the_forward_pass(encoder):
    """The bootstrap's factored pass (encoders and first-layer halves once per distinct cell) gives the forward
    pass's values to float tolerance, on rows that repeat states and goals, in the rows' shape."""
    torch.manual_seed(0)
    net = GoalQNetwork(CORRIDOR, encoder, 8, (16, 16))
    with torch.no_grad():
        for p in net.parameters():
            p.add_(torch.randn_like(p) * 0.3)
    states = torch.tensor([[0, 1, 1], [4, 0, 7], [7, 7, 6]])
    goals = torch.tensor([[2, 2, 2], [5, 5, 2], [1, 1, 1]])
    with torch.no_grad():
        want = net(states, goals)
    got = net.factored_q(states, goals)
    assert got.shape == want.shape == (3, 3, 4)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
