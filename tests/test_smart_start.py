"""Behavioural tests of Smart Start: the count model, the value-iteration planner, the UCB selection of S_ss and the
guided-phase controller. Every expected value is computed independently in the test (Counters, BFS, hand algebra)."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import torch

from ss_drl.envs.maze import load_maze, random_maze
from ss_drl.smart_start import CountModel, Planner, SmartStart, select_smart_start, ucb_scores
from ss_drl.smart_start.counts import fully_explored_model

GAMMA = 0.99


# --- helpers ---------------------------------------------------------------------------------------------------------
def free_cells(maze) -> np.ndarray:
    return np.flatnonzero(~maze.walls.reshape(-1))


def bfs_to(maze, cell: int) -> np.ndarray:
    """Flat BFS distance of every cell to ``cell`` (moves are reversible, so from == to)."""
    return maze.distances_from(maze.pos(cell)).reshape(-1)


def walk_hits(table: np.ndarray, policy: np.ndarray, starts: np.ndarray, terminal: np.ndarray, max_steps: int):
    """Follow ``policy`` from every start cell; the step at which each first stands on a terminal cell (-1: never)."""
    cur = starts.copy()
    hit = np.full(starts.shape, -1, dtype=np.int64)
    for t in range(max_steps + 1):
        newly = (hit < 0) & terminal[cur]
        hit[newly] = t
        if (hit >= 0).all():
            break
        cur = table[cur, policy[cur]]
    return hit


# --- 1. count model --------------------------------------------------------------------------------------------------
def _trajectory(maze, n: int, seed: int):
    table = maze.transition_table()
    rng = np.random.default_rng(seed)
    # A hand-made opening (right, right, up, up, left, bump down into the wall row...) then random actions.
    actions = [0, 0, 3, 3, 2, 1, 1, 1] + list(rng.integers(0, 4, size=n))
    cell = maze.start_cell
    steps = []
    for a in actions:
        nxt = int(table[cell, a])
        steps.append((cell, int(a), nxt, round(float(rng.normal()) * 4) / 4))  # exact in float32
        cell = nxt
    return steps


def test_counts_match_independent_counters():
    maze = load_maze("easy_small")
    steps = _trajectory(maze, 300, seed=1)
    model = CountModel(maze.n_cells, 4)
    # Feed in uneven chunks (single steps, a 2-D batch, the rest) to exercise incremental insertion of keys.
    chunks = [steps[:1], steps[1:2], steps[2:10], steps[10:150], steps[150:]]
    for i, chunk in enumerate(chunks):
        s, a, s2, r = (torch.tensor(x) for x in zip(*chunk))
        if i == 2:
            s, a, s2, r = (t.reshape(2, -1) for t in (s, a, s2, r))
        model.update(s, a, s2, r)
    model.update(*(torch.zeros(0, dtype=torch.int64) for _ in range(3)), torch.zeros(0))  # empty batch: no-op

    n_s = Counter(s for s, _, _, _ in steps)
    c_sa = Counter((s, a) for s, a, _, _ in steps)
    c_sas = Counter((s, a, s2) for s, a, s2, _ in steps)
    r_sum = Counter()
    for s, a, _, r in steps:
        r_sum[(s, a)] += r

    assert model.total_visits == len(steps)
    for cell in range(maze.n_cells):
        assert model.count(cell) == n_s.get(cell, 0)
        assert int(model.state_counts[cell]) == n_s.get(cell, 0)
        for a in range(4):
            assert model.count(cell, a) == c_sa.get((cell, a), 0)
            assert float(model.reward_sums[cell * 4 + a]) == pytest.approx(r_sum.get((cell, a), 0.0), abs=1e-9)
    for (s, a, s2), c in c_sas.items():
        assert model.count(s, a, s2) == c
    # Unobserved successors count 0 (including keys beyond the largest stored key).
    assert model.count(0, 0, maze.n_cells - 1) == 0
    assert model.count(maze.n_cells - 1, 3, maze.n_cells - 1) == 0

    s, a, s2, p = model.transitions()
    got = {(int(x), int(y), int(z)): float(q) for x, y, z, q in zip(s, a, s2, p)}
    assert set(got) == set(c_sas)
    for key, q in got.items():
        assert q == pytest.approx(c_sas[key] / c_sa[key[:2]])
    assert model.visited_states().tolist() == sorted(n_s)


def test_fully_explored_model_counts_every_move_once():
    maze = load_maze("easy_small")
    model = fully_explored_model(maze)
    walls = maze.walls
    free = [(r, c) for r in range(maze.height) for c in range(maze.width) if not walls[r, c]]
    assert model.total_visits == 4 * len(free)
    assert model.visited_states().tolist() == [r * maze.width + c for r, c in free]
    for r, c in free:
        cell = r * maze.width + c
        assert model.count(cell) == 4
        for a, (dr, dc) in enumerate([(0, 1), (1, 0), (0, -1), (-1, 0)]):  # right, down, left, up
            nr, nc = r + dr, c + dc
            blocked = not (0 <= nr < maze.height and 0 <= nc < maze.width) or walls[nr, nc]
            nxt = cell if blocked else nr * maze.width + nc
            assert model.count(cell, a) == 1 and model.count(cell, a, nxt) == 1
            assert float(model.reward_sums[cell * 4 + a]) == (1.0 if nxt == maze.goal_cell else 0.0)
    assert int(model.state_counts[walls.reshape(-1)].sum()) == 0  # walls are never departed from


def test_stochastic_transition_probabilities():
    model = CountModel(10, 4)
    # (3, 1) -> 4 three times and -> 7 once; (5, 0) -> 6 twice.
    s = torch.tensor([3, 3, 5, 3, 3, 5])
    a = torch.tensor([1, 1, 0, 1, 1, 0])
    s2 = torch.tensor([4, 7, 6, 4, 4, 6])
    model.update(s, a, s2, torch.zeros(6))
    got = {(int(x), int(y), int(z)): float(q) for x, y, z, q in zip(*model.transitions())}
    assert got == pytest.approx({(3, 1, 4): 0.75, (3, 1, 7): 0.25, (5, 0, 6): 1.0})
    assert model.count(3) == 4 and model.count(3, 1) == 4 and model.count(3, 1, 7) == 1
    assert model.visited_states().tolist() == [3, 5]


def test_state_dict_round_trip():
    maze = load_maze("easy_small")
    steps = _trajectory(maze, 100, seed=2)
    s, a, s2, r = (torch.tensor(x) for x in zip(*steps))
    model = CountModel(maze.n_cells, 4)
    model.update(s[:60], a[:60], s2[:60], r[:60])
    copy = CountModel(maze.n_cells, 4)
    copy.load_state_dict(model.state_dict())
    for m in (model, copy):
        m.update(s[60:], a[60:], s2[60:], r[60:])
    for name in ("state_counts", "sa_counts", "reward_sums", "keys", "sas_counts"):
        assert torch.equal(getattr(model, name), getattr(copy, name)), name
    # The loaded model holds its own tensors.
    model.update(s[:1], a[:1], s2[:1], r[:1])
    assert copy.total_visits == model.total_visits - 1
    with pytest.raises(ValueError):
        CountModel(maze.n_cells + 1, 4).load_state_dict(model.state_dict())


@pytest.mark.parametrize(
    "make, limit",
    [
        (lambda: load_maze("extreme"), 1_000_000),
        (lambda: random_maze(100, 100, seed=0), 4_000_000),
        (lambda: random_maze(50, 50, scale=2, seed=0), 4_000_000),
    ],
    ids=["extreme", "random_100x100", "random_50x50_scale2"],
)
def test_count_model_memory_is_sparse(make, limit):
    maze = make()
    model = fully_explored_model(maze)
    assert model.total_visits == 4 * maze.n_free
    assert model.keys.numel() == 4 * maze.n_free  # one successor per (s, a) in a deterministic maze
    assert model.nbytes() < limit
    assert model.nbytes() < maze.n_cells**2 * 4 * 8 / 100  # far from any dense |S| x |S| x |A| array


# --- 2. planner --------------------------------------------------------------------------------------------------
def _targets(maze, seed: int) -> list[int]:
    rng = np.random.default_rng(seed)
    free = free_cells(maze)
    return [maze.goal_cell, maze.start_cell, *(int(c) for c in rng.choice(free, size=2, replace=False))]


@pytest.mark.parametrize("name", ["easy", "medium", "hard", "easy_small"])
def test_planner_routes_are_shortest_paths(name):
    maze = load_maze(name)
    table = maze.transition_table()
    model = fully_explored_model(maze)
    planner = Planner(maze.width, gamma=GAMMA)
    gen = torch.Generator().manual_seed(0)
    free = free_cells(maze)
    for target in _targets(maze, seed=3):
        plan = planner.plan(model, target, gen)
        assert plan.policy.shape == (1, maze.n_cells)
        assert plan.converged and plan.sweeps <= planner.max_sweeps
        dist = bfs_to(maze, target)
        # Deterministic VI from V = 0 fills distance d at sweep d, then one more sweep changes nothing.
        assert plan.sweeps == dist.max() + 1
        near = free[(dist[free] >= 0) & (dist[free] <= 600)]
        terminal = np.zeros(maze.n_cells, dtype=bool)
        terminal[target] = True
        hits = walk_hits(table, plan.policy[0].numpy(), near, terminal, 600)
        np.testing.assert_array_equal(hits, dist[near])
        values = plan.values[:, 0].numpy().astype(np.float64)
        moving = near[dist[near] >= 1]
        np.testing.assert_allclose(values[moving], GAMMA ** (dist[moving] - 1.0), rtol=1e-4)
        assert values[target] == 0.0
        # Walls are never departed from: value 0.
        assert (values[maze.walls.reshape(-1)] == 0).all()


def test_planner_from_random_start_cells_and_extreme():
    maze = load_maze("extreme")
    table = maze.transition_table()
    model = fully_explored_model(maze)
    rng = np.random.default_rng(4)
    target = int(rng.choice(free_cells(maze)))
    plan = Planner(maze.width, gamma=GAMMA).plan(model, target, torch.Generator().manual_seed(1))
    dist = bfs_to(maze, target)
    starts = rng.choice(free_cells(maze), size=20, replace=False)
    terminal = np.arange(maze.n_cells) == target
    hits = walk_hits(table, plan.policy[0].numpy(), starts, terminal, 600)
    np.testing.assert_array_equal(hits, dist[starts])


@pytest.mark.parametrize("name", ["easy", "hard"])
def test_batched_planning_matches_single(name):
    maze = load_maze(name)
    table = maze.transition_table()
    model = fully_explored_model(maze)
    planner = Planner(maze.width, gamma=GAMMA)
    gen = torch.Generator().manual_seed(5)
    targets = _targets(maze, seed=6)[:3]
    batch = planner.plan(model, torch.tensor(targets), gen)
    assert batch.policy.shape == (3, maze.n_cells) and batch.values.shape == (maze.n_cells, 3)
    assert batch.q_values.shape == (maze.n_cells, 4, 3)
    free = free_cells(maze)
    for j, target in enumerate(targets):
        alone = planner.plan(model, target, gen)
        terminal = np.arange(maze.n_cells) == target
        hits_batch = walk_hits(table, batch.policy[j].numpy(), free, terminal, 600)
        hits_alone = walk_hits(table, alone.policy[0].numpy(), free, terminal, 600)
        np.testing.assert_array_equal(hits_batch, hits_alone)
        np.testing.assert_array_equal(hits_batch, bfs_to(maze, target)[free])
        torch.testing.assert_close(batch.values[:, j], alone.values[:, 0])


def test_untried_actions_are_valued_zero():
    maze = load_maze("easy_small")
    table = maze.transition_table()
    # Explore only "right" along row 10 (from S) and "up" along column 7 to the target at (1, 7).
    s_list, a_list = [], []
    for col in range(1, 7):
        s_list.append(maze.cell((10, col)))
        a_list.append(0)
    for row in range(10, 1, -1):
        s_list.append(maze.cell((row, 7)))
        a_list.append(3)
    s = torch.tensor(s_list)
    a = torch.tensor(a_list)
    s2 = torch.from_numpy(table[s.numpy(), a.numpy()])
    model = CountModel(maze.n_cells, 4)
    model.update(s, a, s2, torch.zeros(len(s_list)))
    target = maze.cell((1, 7))
    plan = Planner(maze.width, gamma=GAMMA).plan(model, target)
    tried = torch.zeros(maze.n_cells, 4, dtype=torch.bool)
    tried[s, a] = True
    q = plan.q_values[:, :, 0]
    assert (q[~tried] == 0).all()
    # Tried actions on the route are valued gamma^(steps left - 1) along the explored L-shaped route.
    steps_left = {maze.cell((row, 7)): row - 1 for row in range(2, 11)}
    steps_left.update({maze.cell((10, col)): (7 - col) + 9 for col in range(1, 7)})
    for cell, left in steps_left.items():
        assert float(plan.values[cell, 0]) == pytest.approx(GAMMA ** (left - 1), rel=1e-4)
    # Unvisited free cells (e.g. next to the target, but never departed from) are worth 0.
    assert float(plan.values[maze.cell((1, 6)), 0]) == 0.0
    # Following the route from S reaches the target in the explored route's length.
    terminal = np.arange(maze.n_cells) == target
    hits = walk_hits(table, plan.policy[0].numpy(), np.array([maze.cell((10, 1))]), terminal, 100)
    assert hits.tolist() == [15]


@pytest.mark.parametrize("theta", [1, 2, 3])
def test_theta_stops_within_manhattan_distance(theta):
    maze = load_maze("medium")
    table = maze.transition_table()
    model = fully_explored_model(maze)
    target = maze.goal_cell
    planner = Planner(maze.width, gamma=GAMMA, theta=theta)
    plan = planner.plan(model, target, torch.Generator().manual_seed(7))
    rows, cols = np.divmod(np.arange(maze.n_cells), maze.width)
    tr, tc = maze.pos(target)
    terminal = (np.abs(rows - tr) + np.abs(cols - tc)) <= theta
    free = free_cells(maze)
    region = free[terminal[free]]
    assert region.size > 1
    # Distance to the region: min over its free cells of the BFS distance.
    dist = np.min(np.stack([bfs_to(maze, int(c)) for c in region]), axis=0)
    hits = walk_hits(table, plan.policy[0].numpy(), free, terminal, 600)
    np.testing.assert_array_equal(hits, dist[free])
    values = plan.values[:, 0].numpy().astype(np.float64)
    outside = free[dist[free] >= 1]
    np.testing.assert_allclose(values[outside], GAMMA ** (dist[outside] - 1.0), rtol=1e-4)
    assert (values[region] == 0).all()


def test_max_sweeps_caps_value_iteration():
    maze = load_maze("hard")
    model = fully_explored_model(maze)
    plan = Planner(maze.width, gamma=GAMMA, max_sweeps=5).plan(model, maze.goal_cell)
    assert plan.sweeps == 5 and not plan.converged
    dist = bfs_to(maze, maze.goal_cell)
    values = plan.values[:, 0].numpy()
    # After 5 sweeps only cells within 5 steps carry value.
    free = free_cells(maze)
    assert (values[free[dist[free] > 5]] == 0).all()
    assert (values[free[(dist[free] >= 1) & (dist[free] <= 5)]] > 0).all()


def test_stochastic_model_values_by_hand():
    # A 1 x 4 corridor: target 3. (2, right) -> 3; (2, down) -> 3 or 2 (1:1);
    # (1, right) -> 2 three times, -> 0 once; (0, right) -> 1.
    model = CountModel(4, 4)
    s = torch.tensor([2, 2, 2, 1, 1, 1, 1, 0, 0])
    a = torch.tensor([0, 1, 1, 0, 0, 0, 0, 0, 0])
    s2 = torch.tensor([3, 3, 2, 2, 2, 2, 0, 1, 1])
    model.update(s, a, s2, torch.zeros(9))
    plan = Planner(4, gamma=GAMMA, tol=1e-7, max_sweeps=10_000).plan(model, 3)
    assert plan.converged
    g = GAMMA
    v2 = 1.0  # max(Q(2, right) = 1, Q(2, down) = 0.5 * 1 + 0.5 * g * V(2))
    # V1 = 0.75 g V2 + 0.25 g V0,  V0 = g V1
    v1 = 0.75 * g * v2 / (1 - 0.25 * g * g)
    v0 = g * v1
    q = plan.q_values[:, :, 0].double()
    assert float(q[2, 0]) == pytest.approx(1.0, abs=1e-5)
    assert float(q[2, 1]) == pytest.approx(0.5 + 0.5 * g * v2, abs=1e-5)
    assert float(q[1, 0]) == pytest.approx(v1, abs=1e-5)
    assert float(q[0, 0]) == pytest.approx(v0, abs=1e-5)
    assert plan.values[:, 0].double().tolist() == pytest.approx([v0, v1, v2, 0.0], abs=1e-5)
    assert int(plan.policy[0, 2]) == 0 and int(plan.policy[0, 1]) == 0


def test_route_length_from_planner_values():
    # V = gamma^(steps - 1): 1 step for V = 1, 4 steps for gamma^3, -1 (no route) for V = 0.
    lengths = Planner.route_length(torch.tensor([1.0, GAMMA**3, 0.0]), GAMMA)
    assert lengths.dtype == torch.float64
    assert torch.allclose(lengths, torch.tensor([1.0, 4.0, -1.0], dtype=torch.float64))
    # A 1 x 5 corridor walked right once, planned towards cell 4: cells 0..3 lie 4..1 steps away; the target is
    # terminal (value 0: no route from it).
    model = CountModel(5, 4)
    model.update(torch.arange(4), torch.zeros(4, dtype=torch.int64), torch.arange(1, 5), torch.zeros(4))
    plan = Planner(5, gamma=GAMMA).plan(model, 4)
    lengths = Planner.route_length(plan.values[:, 0], GAMMA)
    assert torch.allclose(lengths, torch.tensor([4.0, 3.0, 2.0, 1.0, -1.0], dtype=torch.float64))


def _random_model(maze, n: int, seed: int, slip: float = 0.0) -> CountModel:
    """A partly explored model: n random (free cell, action) tries; with ``slip`` some lead to a random neighbour."""
    table = maze.transition_table()
    rng = np.random.default_rng(seed)
    s = rng.choice(free_cells(maze), size=n)
    a = rng.integers(0, 4, size=n)
    s2 = np.where(rng.random(n) < slip, table[s, rng.integers(0, 4, size=n)], table[s, a])
    model = CountModel(maze.n_cells, 4)
    model.update(torch.from_numpy(s), torch.from_numpy(a), torch.from_numpy(s2), torch.zeros(n))
    return model


@pytest.mark.parametrize(
    "kwargs", [{}, {"theta": 2}, {"max_sweeps": 5}, {"max_sweeps": 1}, {"max_sweeps": 0}, {"tol": 0.5}]
)
@pytest.mark.parametrize("explored", [0.2, 1.0])
def test_deterministic_shortcut_equals_sweeps(kwargs, explored):
    # On a deterministic model the planner computes the sweeps' result from breadth-first distances; it must equal
    # the sweeps themselves bit for bit: q, V, the number of sweeps and whether they converged.
    maze = load_maze("medium")
    model = _random_model(maze, int(explored * 4 * maze.n_free), seed=11)
    st = model.structure()
    assert st.deterministic
    planner = Planner(maze.width, gamma=GAMMA, **kwargs)
    rng = np.random.default_rng(12)
    visited = model.visited_states().numpy()
    unvisited = np.setdiff1d(free_cells(maze), visited)
    for targets in ([int(rng.choice(visited))], rng.choice(visited, 3), [int(unvisited[0]), int(visited[0])]):
        terminal = planner.terminal_mask(model.n_states, torch.as_tensor(targets)).T
        fast = planner._deterministic_sweeps(st, 4, terminal)
        slow = planner._sweeps(st, model, terminal)
        assert fast[2:] == slow[2:]
        torch.testing.assert_close(fast[0], slow[0], rtol=0, atol=0)
        torch.testing.assert_close(fast[1], slow[1], rtol=0, atol=0)


def test_structure_cache_follows_new_transitions():
    # The planner's layout is cached in the count model and rebuilt only when a new (s, a, s') key appears: a plan
    # after more transitions (new keys, only more counts, a first stochastic outcome, a loaded checkpoint) must
    # equal the plan of a model built from scratch on the same transitions.
    maze = load_maze("easy")
    table = maze.transition_table()
    planner = Planner(maze.width, gamma=GAMMA)
    rng = np.random.default_rng(13)
    free = free_cells(maze)
    model = CountModel(maze.n_cells, 4)
    seen = []

    def add(s, a, s2):
        batch = [torch.as_tensor(x, dtype=torch.int64) for x in (s, a, s2)]
        model.update(*batch, torch.zeros(len(s)))
        seen.append(batch)

    def check():
        fresh = CountModel(maze.n_cells, 4)
        for s, a, s2 in seen:
            fresh.update(s, a, s2, torch.zeros(s.numel()))
        target = torch.tensor([maze.goal_cell, int(model.visited_states()[0])])
        got = planner.plan(model, target, torch.Generator().manual_seed(0))
        want = planner.plan(fresh, target, torch.Generator().manual_seed(0))
        assert (got.sweeps, got.converged) == (want.sweeps, want.converged)
        for name in ("values", "q_values", "policy"):
            torch.testing.assert_close(getattr(got, name), getattr(want, name), rtol=0, atol=0)
        return got

    for _ in range(4):  # new keys each time
        s, a = rng.choice(free, 150), rng.integers(0, 4, 150)
        add(s, a, table[s, a])
        first = model.structure()
        check()
    assert model.structure() is first  # planning reuses the cached layout
    add(seen[0][0][:5].numpy(), seen[0][1][:5].numpy(), seen[0][2][:5].numpy())  # known keys: counts only
    assert model.structure() is first
    check()
    s, a = seen[0][0][:1].numpy(), (seen[0][1][:1].numpy() + 1) % 4
    add(s, seen[0][1][:1].numpy(), table[s, a])  # a second outcome of a tried (s, a): now stochastic
    assert model.structure() is not first and not model.structure().deterministic
    plan = check()
    restored = CountModel(maze.n_cells, 4)
    restored.structure()
    restored.load_state_dict(model.state_dict())
    got = planner.plan(restored, plan.targets, torch.Generator().manual_seed(0))
    torch.testing.assert_close(got.values, plan.values, rtol=0, atol=0)


# --- 3. selection ----------------------------------------------------------------------------------------------------
def _zero_q(states, goals):
    return torch.zeros(goals.numel(), states.numel())


def _random_counts(n_states: int, seed: int, n: int = 400) -> tuple[CountModel, Counter]:
    rng = np.random.default_rng(seed)
    # Visit only the even states.
    s = rng.choice(np.arange(0, n_states, 2), size=n)
    model = CountModel(n_states, 4)
    model.update(torch.from_numpy(s), torch.zeros(n, dtype=torch.int64), torch.from_numpy(s), torch.zeros(n))
    return model, Counter(s.tolist())


def test_selection_with_zero_q_picks_least_visited_with_random_ties():
    model, counter = _random_counts(40, seed=8)
    # Force a tie at the minimum: two more states visited exactly once each (one is odd, so never visited before).
    k = min(counter.values())
    for cell in (1, 3):
        model.update(torch.full((k,), cell), torch.zeros(k, dtype=torch.int64), torch.full((k,), cell), torch.zeros(k))
        counter[cell] = k
    least = min(counter.values())
    tied = {s for s, c in counter.items() if c == least}
    assert len(tied) >= 3
    gen = torch.Generator().manual_seed(9)
    goals = torch.zeros(3000, dtype=torch.int64)
    chosen = select_smart_start(model, _zero_q, goals, c_ss=2.0, w_q=1.0, generator=gen)
    assert set(chosen.tolist()) == tied


def test_selection_c_ss_zero_picks_argmax_q_and_never_unvisited():
    model, counter = _random_counts(40, seed=10)
    seen = []

    def max_q(states, goals):
        seen.append(states.clone())
        # Q grows with the state index and with the goal; unvisited states would score highest if they were offered.
        return (states.double().unsqueeze(0) * (goals.double().unsqueeze(1) + 1.0)) % 17

    goals = torch.arange(5)
    chosen = select_smart_start(model, max_q, goals, c_ss=0.0, generator=torch.Generator().manual_seed(0))
    assert sorted(seen[0].tolist()) == sorted(counter)  # only visited states are evaluated
    for g, pick in zip(goals.tolist(), chosen.tolist()):
        assert pick in counter  # a visited state
        scores = {s: (s * (g + 1.0)) % 17 for s in counter}
        assert scores[pick] == max(scores.values())
    # With zero Q and any c_ss, over many draws nothing unvisited comes out.
    many = select_smart_start(model, _zero_q, torch.zeros(2000, dtype=torch.int64), 1.0)
    assert set(many.tolist()) <= set(counter)


def test_selection_by_counts_alone_skips_the_network_and_matches_zero_q():
    # w_q = 0 (the paper-setup experiments): the UCB is the count bonus alone, so the network is never evaluated,
    # and the picks (random tie-breaks included) are those of a network that returns Q = 0 everywhere.
    model, _ = _random_counts(40, seed=12)
    goals = torch.zeros(500, dtype=torch.int64)

    def no_network(states, goals):
        raise AssertionError("the network was evaluated although w_q = 0")

    counts_only = select_smart_start(model, no_network, goals, 0.3, w_q=0.0, generator=torch.Generator().manual_seed(4))
    zero_q = select_smart_start(model, _zero_q, goals, 0.3, w_q=1.0, generator=torch.Generator().manual_seed(4))
    assert torch.equal(counts_only, zero_q)


def test_ucb_scores_formula_and_selection_agree():
    visits = torch.tensor([[1, 4, 9, 2, 30]])
    max_q = torch.tensor([[0.1, 0.5, 0.9, -0.2, 0.3]])
    c_ss, w_q = 1.7, 0.6
    total = 1 + 4 + 9 + 2 + 30
    expected = [w_q * q + math.sqrt(c_ss * math.log(total) / n) for q, n in zip(max_q[0].tolist(), visits[0].tolist())]
    got = ucb_scores(max_q, visits, c_ss, w_q)
    assert got.shape == (1, 5)
    assert got[0].tolist() == pytest.approx(expected, rel=1e-6)

    # The selection maximizes the same score over the visited states.
    states = [2, 5, 11, 17, 23]
    model = CountModel(30, 4)
    for cell, n in zip(states, visits[0].tolist()):
        model.update(torch.full((n,), cell), torch.zeros(n, dtype=torch.int64), torch.full((n,), cell), torch.zeros(n))
    q_of = dict(zip(states, max_q[0].tolist()))

    def max_q_fn(st, goals):
        return torch.tensor([[q_of[int(x)] for x in st]]).expand(goals.numel(), -1)

    pick = select_smart_start(model, max_q_fn, torch.zeros(1, dtype=torch.int64), c_ss, w_q)
    assert int(pick[0]) == states[int(np.argmax(expected))]


@pytest.mark.parametrize(
    "encoder,dueling", [("embedding", True), ("embedding", False), ("coords", True), ("hybrid", True)]
)
@pytest.mark.parametrize("n_goals", [1, 3])
def test_goal_q_values_match_the_network(encoder, dueling, n_goals, monkeypatch):
    # GoalQNetwork.goal_q_values splits the first layer into state and goal halves, folds the dueling head and works
    # in blocks of rows: the same Q as the network's own forward pass up to float rounding, and the same smart start
    # states.
    from ss_drl.agents.network import GoalQNetwork

    maze = load_maze("medium")
    torch.manual_seed(14)
    net = GoalQNetwork(maze, encoder, 16, (32, 24), dueling)
    model = _random_model(maze, 600, seed=15)
    states = model.visited_states()
    goals = torch.from_numpy(np.random.default_rng(16).choice(free_cells(maze), n_goals))
    monkeypatch.setattr("ss_drl.agents.network.BLOCK_ROWS", 64)  # several blocks, the last one partial
    with torch.no_grad():
        want = net(states.repeat(n_goals), goals.repeat_interleave(states.numel())).view(n_goals, -1, 4)
    got = net.goal_q_values(states, goals)
    assert got.shape == want.shape and not got.requires_grad
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)

    def plain(s, g):
        return net(s.repeat(g.numel()), g.repeat_interleave(s.numel())).view(g.numel(), -1, 4).amax(-1).detach()

    def fast(s, g):
        return net.goal_q_values(s, g).amax(-1)

    expected = select_smart_start(model, plain, goals, 0.1, 1.0, torch.Generator().manual_seed(17))
    got = select_smart_start(model, fast, goals, 0.1, 1.0, torch.Generator().manual_seed(17))
    torch.testing.assert_close(got, expected)


def test_selection_needs_a_visited_state():
    with pytest.raises(ValueError):
        select_smart_start(CountModel(5, 4), _zero_q, torch.zeros(1, dtype=torch.int64), 1.0)


# --- 4. SmartStart controller ----------------------------------------------------------------------------------------
def _zero_q_values(states, goals):
    return torch.zeros(goals.numel(), states.numel(), 4)


def _controller(maze, model, num_envs, eta, theta=0, seed=0):
    planner = Planner(maze.width, gamma=GAMMA, theta=theta)
    return SmartStart(
        maze, model, num_envs, eta=eta, c_ss=2.0, w_q=1.0, theta=theta, planner=planner,
        generator=torch.Generator().manual_seed(seed),
    )  # fmt: skip


def _model_with_least_visited(maze, target: int) -> CountModel:
    """Fully explored, then every free cell but ``target`` departed from once more: ``target`` is the unique S_ss."""
    model = fully_explored_model(maze)
    table = maze.transition_table()
    others = free_cells(maze)[free_cells(maze) != target]
    a = np.zeros_like(others)
    model.update(torch.from_numpy(others), torch.from_numpy(a), torch.from_numpy(table[others, a]), torch.zeros(len(a)))
    return model


def test_no_guided_phase_in_first_episode_and_eta_bounds():
    maze = load_maze("easy_small")
    model = fully_explored_model(maze)
    n = 4
    cells = torch.full((n,), maze.start_cell)
    goals = torch.full((n,), maze.goal_cell)
    all_copies = torch.ones(n, dtype=torch.bool)

    ss = _controller(maze, model, n, eta=1.0)
    ss.start_episodes(all_copies, cells, goals, _zero_q_values)
    assert not ss.used.any() and not ss.active.any()  # episodes == 0 everywhere
    ss.end_episodes(torch.tensor([True, True, False, False]))
    ss.start_episodes(all_copies, cells, goals, _zero_q_values)
    assert ss.used.tolist() == [True, True, False, False]
    assert ss.decisions == 2
    assert (ss.target[:2] >= 0).all() and (ss.target[2:] == -1).all()
    assert all(model.count(int(t)) > 0 for t in ss.target[:2])

    never = _controller(maze, model, n, eta=0.0)
    state_before = never.generator.get_state().clone()
    for _ in range(5):
        never.end_episodes(all_copies)
        never.start_episodes(all_copies, cells, goals, _zero_q_values)
        assert not never.used.any() and not never.active.any()
    assert torch.equal(never.generator.get_state(), state_before)  # eta = 0 draws nothing
    assert never.decisions == 0


def test_eta_half_guides_about_half_the_episodes():
    maze = load_maze("easy_small")
    n = 2000
    ss = _controller(maze, fully_explored_model(maze), n, eta=0.5, seed=3)
    ss.end_episodes(torch.ones(n, dtype=torch.bool))
    cells = torch.full((n,), maze.start_cell)
    ss.start_episodes(torch.ones(n, dtype=torch.bool), cells, torch.full((n,), maze.goal_cell), _zero_q_values)
    assert 0.45 < ss.used.double().mean() < 0.55


@pytest.mark.parametrize("target_pos", [(1, 1), (0, 8), (3, 7), (11, 0)])
def test_guided_phase_reaches_smart_start_in_planned_steps(target_pos):
    maze = load_maze("easy_small")
    table = torch.from_numpy(maze.transition_table())
    target = maze.cell(target_pos)
    model = _model_with_least_visited(maze, target)
    n = 3
    ss = _controller(maze, model, n, eta=1.0, seed=11)
    starts = torch.tensor([maze.start_cell, maze.cell((11, 8)), maze.cell((9, 4))])
    goals = torch.full((n,), maze.goal_cell)
    ss.end_episodes(torch.ones(n, dtype=torch.bool))
    ss.start_episodes(torch.ones(n, dtype=torch.bool), starts, goals, _zero_q_values)
    assert ss.target.tolist() == [target] * n
    dist = bfs_to(maze, target)
    expected = [int(dist[c]) for c in starts.tolist()]
    assert ss.planned_steps.tolist() == expected
    assert ss.active.all() and not ss.reached.any()

    cells = starts.clone()
    sentinel = torch.full((n,), -7)
    for _ in range(max(expected) + 5):
        was_active = ss.active.clone()
        act = ss.guide(cells, sentinel)
        assert (act[~was_active] == -7).all()  # copies out of the guided phase keep their own action
        act = torch.where(was_active, act, torch.zeros_like(act))
        cells = torch.where(was_active, table[cells, act], cells)
        ss.after_step(was_active, cells, torch.zeros(n, dtype=torch.bool))
    assert ss.steps.tolist() == expected
    assert ss.reached.all() and not ss.active.any()
    assert cells.tolist() == [target] * n


def test_guided_phase_stops_when_episode_ends():
    maze = load_maze("easy_small")
    table = torch.from_numpy(maze.transition_table())
    target = maze.cell((0, 0))
    ss = _controller(maze, _model_with_least_visited(maze, target), 2, eta=1.0)
    starts = torch.tensor([maze.start_cell, maze.start_cell])
    ss.end_episodes(torch.ones(2, dtype=torch.bool))
    ss.start_episodes(torch.ones(2, dtype=torch.bool), starts, torch.full((2,), maze.goal_cell), _zero_q_values)
    assert ss.active.all() and ss.planned_steps.tolist() == [int(bfs_to(maze, target)[maze.start_cell])] * 2
    cells = starts.clone()
    for step in range(3):
        was_active = ss.active.clone()
        act = ss.guide(cells, torch.zeros(2, dtype=torch.int64))
        cells = table[cells, act]
        done = torch.tensor([step == 2, False])  # copy 0's episode ends (budget / goal) after its third step
        ss.after_step(was_active, cells, done)
    assert ss.active.tolist() == [False, True]
    assert ss.reached.tolist() == [False, False]
    assert ss.steps.tolist() == [3, 3]
    ss.end_episodes(torch.tensor([False, True]))
    assert not ss.active.any()


def test_guided_phase_with_theta_stops_within_theta():
    maze = load_maze("easy_small")
    table = torch.from_numpy(maze.transition_table())
    target = maze.cell((1, 1))
    theta = 2
    ss = _controller(maze, _model_with_least_visited(maze, target), 1, eta=1.0, theta=theta)
    start = torch.tensor([maze.start_cell])
    ss.end_episodes(torch.ones(1, dtype=torch.bool))
    ss.start_episodes(torch.ones(1, dtype=torch.bool), start, torch.tensor([maze.goal_cell]), _zero_q_values)
    cells = start.clone()
    while bool(ss.active[0]):
        was_active = ss.active.clone()
        cells = table[cells, ss.guide(cells, torch.zeros(1, dtype=torch.int64))]
        ss.after_step(was_active, cells, torch.zeros(1, dtype=torch.bool))
        assert int(ss.steps[0]) <= 100
    r, c = maze.pos(int(cells[0]))
    assert abs(r - 1) + abs(c - 1) <= theta
    assert ss.reached.all()
    # Steps taken = BFS distance from S to the nearest free cell within theta of the target = the planned steps.
    rows, cols = np.divmod(free_cells(maze), maze.width)
    region = free_cells(maze)[(np.abs(rows - 1) + np.abs(cols - 1)) <= theta]
    d = min(int(bfs_to(maze, int(x))[maze.start_cell]) for x in region)
    assert ss.steps.tolist() == [d] and ss.planned_steps.tolist() == [d]


def test_guided_epsilon_deviates_at_its_rate_and_still_reaches_smart_start():
    maze = load_maze("easy_small")
    table = torch.from_numpy(maze.transition_table())
    target = maze.cell((1, 1))
    n = 400
    planner = Planner(maze.width, gamma=GAMMA)
    ss = SmartStart(
        maze, _model_with_least_visited(maze, target), n, eta=1.0, c_ss=2.0, w_q=1.0, theta=0, planner=planner,
        generator=torch.Generator().manual_seed(5), guided_epsilon=0.4,
    )  # fmt: skip
    starts = torch.full((n,), maze.start_cell)
    ss.end_episodes(torch.ones(n, dtype=torch.bool))
    ss.start_episodes(torch.ones(n, dtype=torch.bool), starts, torch.full((n,), maze.goal_cell), _zero_q_values)
    cells, off_route, guided = starts.clone(), 0, 0
    for _ in range(500):
        was_active = ss.active.clone()
        if not was_active.any():
            break
        act = ss.guide(cells, torch.zeros(n, dtype=torch.int64))
        planned = ss.route.gather(1, cells.unsqueeze(1)).squeeze(1)
        off_route += int((was_active & (act != planned)).sum())
        guided += int(was_active.sum())
        cells = torch.where(was_active, table[cells, act], cells)
        ss.after_step(was_active, cells, torch.zeros(n, dtype=torch.bool))
    # A random action is the planned one a quarter of the time: 0.4 * 3/4 = 0.3 of the guided steps leave the route.
    assert 0.27 < off_route / guided < 0.33
    assert ss.reached.all() and (cells == target).all()  # the route is taken up again after every deviation
    assert (ss.steps >= ss.planned_steps).all() and (ss.steps > ss.planned_steps).float().mean() > 0.9
