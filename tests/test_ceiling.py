"""The distance ceiling: the fewest steps to G that the count model cannot rule out, by hand and as a bound."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ss_drl.envs.maze import parse_maze
from ss_drl.smart_start import CountModel
from ss_drl.smart_start.ceiling import DistanceCeiling, DistanceFloor

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


def test_ceiling_by_hand_before_and_after_a_wall_is_seen():
    counts = CountModel(CORRIDOR.n_cells)
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, CORRIDOR.goal_cell)
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
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, CORRIDOR.goal_cell)
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
        steps = DistanceCeiling(counts, maze.height, maze.width, maze.goal_cell).steps().view(-1, 4)[free].numpy()
        assert (steps <= true_steps).all()
        if share == 1.0:
            np.testing.assert_array_equal(steps, true_steps)
        elif share == 0.0:
            assert (steps < true_steps).any()  # the empty model sees through walls


def test_the_steps_follow_the_count_model_as_it_grows():
    """The cached steps are recomputed when the count model's keys change (and only then)."""
    counts = CountModel(CORRIDOR.n_cells)
    ceiling = DistanceCeiling(counts, CORRIDOR.height, CORRIDOR.width, CORRIDOR.goal_cell)
    first = ceiling.steps()
    assert ceiling.steps() is first
    observe(counts, CORRIDOR, [(1, RIGHT)])
    assert ceiling.steps()[1 * 4 + RIGHT] == 5


# --- the distance floor ---------------------------------------------------------------------------------------------
def test_floor_by_hand_on_a_built_route():
    """Nothing is known before G has been entered; after the route 0 -> 4 -> 5 -> 6 -> 7 -> G (and a bump at 1),
    each tried (s, a) on it is 1 + its successor's distance along the route, the rest have no bound (0)."""
    counts = CountModel(CORRIDOR.n_cells)
    floor = DistanceFloor(counts, CORRIDOR.goal_cell)
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
        steps = DistanceFloor(counts, maze.goal_cell).steps().view(-1, 4)[free]
        ceiling = DistanceCeiling(counts, maze.height, maze.width, maze.goal_cell).steps().view(-1, 4)[free]
        bounded = steps > 0
        assert bounded.any()
        assert bool((steps[bounded] >= true_steps[bounded]).all())
        assert bool((true_steps >= ceiling).all())
        if share == 1.0:
            torch.testing.assert_close(steps, true_steps)


def test_the_floor_follows_the_count_model_and_refuses_a_stochastic_one():
    counts = CountModel(CORRIDOR.n_cells)
    floor = DistanceFloor(counts, CORRIDOR.goal_cell)
    observe(counts, CORRIDOR, [(7, UP)])
    first = floor.steps()
    assert floor.steps() is first  # cached while no new transition is seen
    observe(counts, CORRIDOR, [(6, RIGHT)])
    assert floor.steps()[6 * 4 + RIGHT] == 2
    counts.update(torch.tensor([6]), torch.tensor([RIGHT]), torch.tensor([2]), torch.tensor([0.0]))
    with pytest.raises(ValueError, match="deterministic"):
        floor.steps()
