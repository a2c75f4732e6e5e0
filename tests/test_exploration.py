"""Smart Start's exploration options (issue 49): the frontier of tried moves, S_ss chosen on the frontier, the
untried move on arrival and the exploration phase that walks to the nearest untried move. Each on a hand-built count
model whose answer is worked out by hand below."""

from __future__ import annotations

from collections import deque

import pytest
import torch
from helpers import compose_cfg

from ss_drl.envs.maze import parse_maze
from ss_drl.smart_start import CountModel, Frontier, Planner, SmartStart
from ss_drl.smart_start.counts import fully_explored_model
from ss_drl.training.trainer import Trainer

R, D, L, U = range(4)  # ss_drl.envs.maze.ACTIONS: right, down, left, up
#: Row 0 is an open corridor of six cells (0-5); S (6) lies below its left end and G (11) below its right end, with a
#: wall between them. The only way from S to G: up, right x5, down.
HOOK = "......\nS####G\n"
SENTINEL = 7  # the policy's "action" in these tests: never a real one, so the test sees who chose


def _maze():
    return parse_maze(HOOK)


def _hand_model(maze) -> CountModel:
    """S (6) and cells 0 and 1 have every move tried; cell 2 has every move but right. Visits: N(6) = 8, N(0) = 4,
    N(1) = 12, N(2) = 6, so the least visited state is 0, inside explored territory."""
    table = maze.transition_table()
    model = CountModel(maze.n_cells)
    moves = [(6, a, 2) for a in range(4)] + [(0, a, 1) for a in range(4)] + [(1, a, 3) for a in range(4)]
    moves += [(2, a, 2) for a in (D, L, U)]
    for cell, action, times in moves:
        s = torch.full((times,), cell)
        a = torch.full((times,), action)
        model.update(s, a, torch.from_numpy(table[s.numpy(), a.numpy()]), torch.zeros(times))
    return model


def _controller(maze, model, select="frontier", explore="frontier", after_goal=True, seed=0):
    return SmartStart(
        maze, model, 1, eta=1.0, c_ss=2.0, w_q=0.0, theta=0, planner=Planner(maze.width, gamma=0.99),
        generator=torch.Generator().manual_seed(seed), select=select, explore=explore, explore_after_goal=after_goal,
    )  # fmt: skip


def _start(ss, maze, cell=None):
    """Begin a copy's second episode (the first never has a guided phase) at ``cell`` (S by default)."""
    one = torch.ones(1, dtype=torch.bool)
    ss.end_episodes(one)
    cells = torch.tensor([maze.start_cell if cell is None else cell])
    ss.start_episodes(one, cells, torch.tensor([maze.goal_cell]), lambda s, g: torch.zeros(g.numel(), s.numel(), 4))


def _step(ss, maze, cell: int, update_model: bool = True) -> tuple[int, int]:
    """One env step of the controller from ``cell``: (action, next cell). The count model learns the step at once (a
    batch of one step) unless ``update_model`` is False (a step inside a longer batch: only the frontier sees it)."""
    table = maze.transition_table()
    was_active = ss.active.clone()
    action = int(ss.guide(torch.tensor([cell]), torch.tensor([SENTINEL]))[0])
    if action == SENTINEL:
        return action, cell
    nxt = int(table[cell, action])
    step = torch.tensor([cell]), torch.tensor([action]), torch.tensor([nxt])
    ss.frontier.observe(*step)
    if update_model:
        ss.counts.update(*step, torch.tensor([float(nxt == maze.goal_cell)]))
    ss.after_step(was_active, torch.tensor([nxt]), torch.tensor([nxt == maze.goal_cell]))
    return action, nxt


# --- the frontier ----------------------------------------------------------------------------------------------------
def test_frontier_is_the_known_states_with_an_untried_move_less_the_goal():
    maze = _maze()
    model = _hand_model(maze)
    frontier = Frontier(model)
    # Known: S, 0, 1, 2 (departed) and nothing else entered; only 2 has an untried move (right).
    assert torch.nonzero(frontier.states(torch.tensor([11]))[0]).flatten().tolist() == [2]
    assert frontier.untried(torch.tensor([2, 0])).tolist() == [[True, False, False, False], [False] * 4]
    # Trying right in 2 enters 3: 2 leaves the frontier and 3 (all four moves untried) joins it.
    assert frontier.observe(torch.tensor([2]), torch.tensor([R]), torch.tensor([3])).tolist() == [True]
    assert frontier.observe(torch.tensor([2]), torch.tensor([R]), torch.tensor([3])).tolist() == [False]
    assert torch.nonzero(frontier.states(torch.tensor([11]))[0]).flatten().tolist() == [3]
    # The goal is never on the frontier, though its moves are never tried.
    frontier.observe(torch.tensor([5]), torch.tensor([D]), torch.tensor([11]))
    assert 11 not in torch.nonzero(frontier.states(torch.tensor([11]))[0]).flatten().tolist()
    assert 11 in torch.nonzero(frontier.states(torch.tensor([0]))[0]).flatten().tolist()  # another goal's view


def test_frontier_rebuilt_from_the_count_model_equals_the_one_kept_step_by_step():
    maze = _maze()
    model = CountModel(maze.n_cells)
    kept = Frontier(model)
    table = maze.transition_table()
    gen = torch.Generator().manual_seed(3)
    cell = maze.start_cell
    for _ in range(40):
        a = int(torch.randint(4, (1,), generator=gen))
        nxt = int(table[cell, a])
        kept.observe(torch.tensor([cell]), torch.tensor([a]), torch.tensor([nxt]))
        model.update(torch.tensor([cell]), torch.tensor([a]), torch.tensor([nxt]), torch.zeros(1))
        cell = maze.start_cell if nxt == maze.goal_cell else nxt
    rebuilt = Frontier(model)
    assert torch.equal(rebuilt.tried, kept.tried) and torch.equal(rebuilt.known, kept.known)


# --- select = frontier -----------------------------------------------------------------------------------------------
def test_smart_start_on_the_frontier_by_hand():
    maze = _maze()
    # The paper's UCB on counts picks the least visited state, 0, whose moves are all tried.
    paper = _controller(maze, _hand_model(maze), select="visited", explore="epsilon_greedy")
    _start(paper, maze)
    assert paper.target.tolist() == [0]
    # On the frontier the only candidate is 2, the one visited state with an untried move.
    ss = _controller(maze, _hand_model(maze))
    _start(ss, maze)
    assert ss.target.tolist() == [2] and ss.active.tolist() == [True]
    assert ss.planned_steps.tolist() == [3]  # up, right, right


def _explored_but_3(maze) -> CountModel:
    """Every move of every free cell tried once, then each free cell but 3 visited once more (right again): no
    untried move is left, and 3 is the least visited state."""
    model = fully_explored_model(maze)
    table = maze.transition_table()
    again = torch.tensor([c for c in range(maze.n_cells) if not maze.walls.reshape(-1)[c] and c != 3])
    right = torch.full_like(again, R)
    model.update(again, right, torch.from_numpy(table[again.numpy(), R]), torch.zeros(again.numel()))
    return model


def test_smart_start_on_the_frontier_falls_back_to_every_visited_state():
    maze = _maze()
    ss = _controller(maze, _explored_but_3(maze))
    _start(ss, maze)  # nothing is left to try: S_ss by the paper's UCB over every visited state, the least visited
    paper = _controller(maze, _explored_but_3(maze), select="visited", explore="epsilon_greedy")
    _start(paper, maze)
    assert ss.used.tolist() == [True] and ss.target.tolist() == [3] == paper.target.tolist()


# --- explore ---------------------------------------------------------------------------------------------------------
def test_untried_move_on_arrival_then_the_policy():
    maze = _maze()
    ss = _controller(maze, _hand_model(maze), explore="untried")
    _start(ss, maze)
    trace = [_step(ss, maze, cell) for cell in (6, 0, 1)]  # the guided phase to S_ss = 2
    assert trace == [(U, 0), (R, 1), (R, 2)] and not ss.active.any() and ss.exploring.tolist() == [True]
    assert _step(ss, maze, 2) == (R, 3)  # the one untried move of S_ss
    assert _step(ss, maze, 3)[0] == SENTINEL  # then the policy, though 3 has four untried moves
    assert ss.explore_steps.tolist() == [1]


def test_exploration_walks_the_shortest_route_to_the_nearest_untried_move():
    """Over seeds, both ways out of 3 occur, and each is checked: the walk goes on from where the agent lands."""
    maze = _maze()
    ways_out = set()
    for seed in range(12):
        ss = _controller(maze, _hand_model(maze), seed=seed)
        _start(ss, maze, cell=2)  # S_ss = 2: there already, so the exploration phase begins at once
        assert ss.exploring.tolist() == [True] and ss.steps.tolist() == [0]
        assert _step(ss, maze, 2) == (R, 3)
        # In 3 every move is untried: each is tried in turn (their order is random), staying or leaving as they go.
        cell, tried_in_3 = 3, set()
        while cell == 3:
            action, cell = _step(ss, maze, 3)
            assert action not in tried_in_3
            tried_in_3.add(action)
        ways_out.add(cell)
        if cell == 4:  # every move of 4 is untried: one of them at once
            action, _ = _step(ss, maze, 4)
            assert action in (R, D, L, U)
        else:  # back in 2, whose moves are all tried: the nearest untried move is 3's right (3 was left by left)
            assert cell == 2 and R not in tried_in_3
            assert _step(ss, maze, 2) == (R, 3)
            untried = ss.frontier.untried(torch.tensor([3]))[0]
            action, _ = _step(ss, maze, 3)
            assert action != SENTINEL and bool(untried[action])
    assert ways_out == {2, 4}


def test_exploration_inside_a_batch_sees_the_moves_the_model_has_not_counted_yet():
    maze = _maze()
    ss = _controller(maze, _hand_model(maze))
    _start(ss, maze, cell=2)
    assert _step(ss, maze, 2, update_model=False) == (R, 3)
    # 2 is fully tried now, though the count model still lacks 2 -> 3 (it still counts right in 2 as untried).
    assert ss.counts.sa_counts.view(-1, 4)[2, R] == 0
    assert ss.frontier.untried(torch.tensor([2])).tolist() == [[False] * 4]
    # Back in 2 within the same batch, the controller reads the frontier: right is not tried a second time. The
    # count model knows no route out of 2 to a cell with an untried move (2 -> 3 is not in it yet), so the policy acts.
    assert _step(ss, maze, 2, update_model=False) == (SENTINEL, 2)


def test_exploration_follows_the_frontier_rule_until_the_goal():
    maze = _maze()
    ss = _controller(maze, _hand_model(maze), seed=4)
    _start(ss, maze)
    table = maze.transition_table()
    cell = maze.start_cell
    while ss.active.any():
        _, cell = _step(ss, maze, cell)
    steps = 0
    while cell != maze.goal_cell:
        untried = ss.frontier.untried(torch.tensor([cell]))[0]
        goal_frontier = ss.frontier.states(torch.tensor([maze.goal_cell]))[0]
        dist = _known_distance(ss.frontier, table, goal_frontier)
        action, nxt = _step(ss, maze, cell)
        if bool(untried.any()):
            assert untried[action]
        else:  # one step nearer the nearest frontier state along tried moves
            assert dist[nxt] == dist[cell] - 1
        cell, steps = nxt, steps + 1
        assert steps < 100
    # The episode ended in G: the phase is over.
    assert ss.exploring.tolist() == [False]


def _known_distance(frontier, table, targets) -> dict[int, int]:
    """Fewest tried moves from each known cell into ``targets`` (a BFS backwards along tried moves)."""
    into: dict[int, set[int]] = {}
    for s, a in torch.nonzero(frontier.tried).tolist():
        if int(table[s, a]) != s:
            into.setdefault(int(table[s, a]), set()).add(s)
    dist = {int(t): 0 for t in torch.nonzero(targets).flatten()}
    queue = deque(dist)
    while queue:
        x = queue.popleft()
        for y in into.get(x, ()):
            if y not in dist:
                dist[y] = dist[x] + 1
                queue.append(y)
    return dist


def test_exploration_hands_over_to_the_policy_when_nothing_is_left_to_try():
    maze = _maze()
    model = fully_explored_model(maze)
    goal = torch.tensor([maze.goal_cell])
    model.update(goal, torch.tensor([R]), goal, torch.zeros(1))  # G visited more: it is never S_ss here
    ss = _controller(maze, model)
    _start(ss, maze)
    cell = maze.start_cell
    while ss.active.any():
        _, cell = _step(ss, maze, cell)
    assert ss.exploring.tolist() == [True]
    assert _step(ss, maze, cell)[0] == SENTINEL
    assert ss.exploring.tolist() == [False]


@pytest.mark.parametrize("after_goal", [True, False])
def test_options_after_the_goal_was_reached(after_goal):
    """Once G has been reached, ``explore_after_goal: false`` turns both options off: S_ss by the paper's UCB on
    counts again (not on the frontier), and no exploration phase on arrival."""
    maze = _maze()
    model = _hand_model(maze)
    table = maze.transition_table()
    # The corridor on to 5 is known (2 -> 3, every move of 3 twice and of 4 once, 4's up twice more, 5's up ten times)
    # and G was reached once, from 5. 5's right and left are still untried.
    moves = [(2, R, 1)] + [(3, a, 2) for a in range(4)] + [(4, a, 1) for a in range(4)] + [(4, U, 2), (5, U, 10)]
    for cell, action, times in [*moves, (5, D, 1)]:
        s, a = torch.full((times,), cell), torch.full((times,), action)
        nxt = torch.from_numpy(table[s.numpy(), a.numpy()])
        model.update(s, a, nxt, (nxt == maze.goal_cell).float())
    ss = _controller(maze, model, after_goal=after_goal)
    _start(ss, maze)
    # Visits: S 8, 0 4, 1 12, 2 7, 3 8, 4 6, 5 11. The paper's UCB (w_q 0) picks the least visited state, 0, whose
    # moves are all tried; the one state with an untried move is 5, the frontier's pick.
    expected = 5 if after_goal else 0
    assert ss.target.tolist() == [expected]
    cell = maze.start_cell
    while ss.active.any():
        _, cell = _step(ss, maze, cell)
    assert cell == expected and ss.exploring.tolist() == [after_goal]


# --- the untried move on the greedy path (greedy_path) ----------------------------------------------------------------
def _goal_reached_model(maze, untried_at_4=(D, L, U)) -> CountModel:
    """Every move of S and of cells 0-3 tried (S 4 times each, the others twice), 4's right once, and G reached once
    from 5 (5's down): the moves of 4 in ``untried_at_4`` and 5's other three are untried."""
    table = maze.transition_table()
    model = CountModel(maze.n_cells)
    moves = [(c, a, 4 if c == 6 else 2) for c in (6, 0, 1, 2, 3) for a in range(4)]
    moves += [(4, a, 1) for a in range(4) if a not in untried_at_4] + [(5, D, 1)]
    for cell, action, times in moves:
        s, a = torch.full((times,), cell), torch.full((times,), action)
        nxt = torch.from_numpy(table[s.numpy(), a.numpy()])
        model.update(s, a, nxt, (nxt == maze.goal_cell).float())
    return model


def _greedy(policy: dict[int, int]):
    """A greedy_q_values whose greedy action in each state of ``policy`` is the one given (elsewhere right)."""

    def q(states, goals):
        out = torch.zeros(goals.numel(), states.numel(), 4)
        for i, s in enumerate(states.tolist()):
            out[:, i, policy.get(s, R)] = 1.0
        return out

    return q


#: The route along the corridor: S up, then right, and down into G from 5.
ROUTE = {6: U, 0: R, 1: R, 2: R, 3: R, 4: R, 5: D}


def _greedy_path_start(maze, model, policy, greedy_path=True):
    ss = SmartStart(
        maze, model, 1, eta=1.0, c_ss=2.0, w_q=0.0, theta=0, planner=Planner(maze.width, gamma=0.99),
        generator=torch.Generator().manual_seed(0), greedy_path=greedy_path,
    )  # fmt: skip
    one = torch.ones(1, dtype=torch.bool)
    ss.end_episodes(one)
    online = lambda s, g: torch.zeros(g.numel(), s.numel(), 4)  # noqa: E731
    ss.start_episodes(one, torch.tensor([maze.start_cell]), torch.tensor([maze.goal_cell]), online, _greedy(policy))
    return ss


def test_greedy_path_sends_the_episode_to_the_untried_greedy_move_and_takes_it():
    """The greedy path from S goes up and right along the corridor to 4, whose greedy move (down, into the wall
    below 4) was never tried: S_ss is 4, the guided phase walks there, and the move taken on arrival is down, then
    the policy. Without the option, the paper's UCB picks the least visited state, 5 (once; 4 three times)."""
    maze = _maze()
    model = _goal_reached_model(maze, untried_at_4=(D,))
    ss = _greedy_path_start(maze, model, {**ROUTE, 4: D})
    assert ss.target.tolist() == [4] and ss.first_move.tolist() == [D]
    cell, walked = maze.start_cell, []
    while ss.active.any():
        action, cell = _step(ss, maze, cell)
        walked.append(action)
    assert walked == [U, R, R, R, R] and cell == 4
    assert _step(ss, maze, cell) == (D, 4)  # the bump: 4's down is tried now
    assert _step(ss, maze, cell)[0] == SENTINEL  # then the policy
    paper = _greedy_path_start(maze, _goal_reached_model(maze, untried_at_4=(D,)), {**ROUTE, 4: D}, greedy_path=False)
    assert paper.target.tolist() == [5] and paper.first_move.tolist() == [-1]


def test_greedy_path_pending_move_survives_a_checkpoint_mid_route():
    """Cut two steps into the guided phase to the untried greedy move, the controller's state (its target, the
    exact-arrival flag, the pending move) restored into a new controller finishes the walk and takes the move on
    arrival, as the uncut one would. (A run-level resume test can pass without any cut landing in such a phase.)"""
    maze = _maze()
    model = _goal_reached_model(maze, untried_at_4=(D,))
    ss = _greedy_path_start(maze, model, {**ROUTE, 4: D})
    cell = maze.start_cell
    for _ in range(2):
        _, cell = _step(ss, maze, cell)
    assert ss.active.tolist() == [True] and ss.first_move.tolist() == [D] and ss.exact.tolist() == [True]
    restored = SmartStart(
        maze, model, 1, eta=1.0, c_ss=2.0, w_q=0.0, theta=0, planner=Planner(maze.width, gamma=0.99),
        generator=torch.Generator().manual_seed(5), greedy_path=True,
    )  # fmt: skip
    restored.load_state_dict(ss.state_dict())
    walked = []
    while restored.active.any():
        action, cell = _step(restored, maze, cell)
        walked.append(action)
    assert walked == [R, R, R] and cell == 4
    assert _step(restored, maze, cell) == (D, 4)
    assert _step(restored, maze, cell)[0] == SENTINEL


@pytest.mark.parametrize(
    "policy, why",
    [(ROUTE, "the greedy path reaches G over tried moves"), ({**ROUTE, 2: L}, "it loops: 1 right to 2, 2 left to 1")],
)
def test_greedy_path_without_an_untried_move_leaves_smart_start_as_it_is(policy, why):
    """Where the greedy path from S meets no untried move, S_ss is the usual UCB choice: with 4's left and up untried
    (4 visited three times), the least visited state is 5 (once)."""
    maze = _maze()
    model = _goal_reached_model(maze, untried_at_4=(L, U))
    ss = _greedy_path_start(maze, model, policy)
    paper = _greedy_path_start(maze, model, policy, greedy_path=False)
    assert ss.target.tolist() == paper.target.tolist() == [5], why
    assert ss.first_move.tolist() == [-1]


def test_greedy_path_ends_at_a_move_the_count_model_has_not_counted_yet():
    """A move tried in the batch being collected is tried (the frontier saw it) but has no successor in the count
    model yet: the walk ends there, with no untried move found (the next batch boundary counts it). The hook has a
    third row here, so that G is not the maze's last cell, which is known (a successor of -1 must not be read as it)."""
    maze = parse_maze(HOOK + "......\n")
    model = _goal_reached_model(maze, untried_at_4=(D,))
    assert _greedy_path_start(maze, model, {**ROUTE, 4: D}).first_move.tolist() == [D]  # as in the test above ...
    ss = SmartStart(
        maze, model, 1, eta=1.0, c_ss=2.0, w_q=0.0, theta=0, planner=Planner(maze.width, gamma=0.99),
        generator=torch.Generator().manual_seed(0), greedy_path=True,
    )  # fmt: skip
    ss.frontier.observe(torch.tensor([4]), torch.tensor([D]), torch.tensor([4]))  # ... but 4's down was just tried
    ss.frontier.observe(torch.tensor([16]), torch.tensor([R]), torch.tensor([17]))  # and the last cell is known
    one = torch.ones(1, dtype=torch.bool)
    ss.end_episodes(one)
    online = lambda s, g: torch.zeros(g.numel(), s.numel(), 4)  # noqa: E731
    greedy = _greedy({**ROUTE, 4: D})
    ss.start_episodes(one, torch.tensor([maze.start_cell]), torch.tensor([maze.goal_cell]), online, greedy)
    assert ss.first_move.tolist() == [-1] and ss.target.tolist() == [5]  # the usual UCB choice


def test_greedy_path_waits_for_the_goal():
    """Before G has been reached, the option does nothing (the exploration options decide S_ss)."""
    maze = _maze()
    model = _hand_model(maze)  # no rewarded transition
    ss = _greedy_path_start(maze, model, {6: U, 0: R, 1: R, 2: R})  # 2's right is untried
    paper = _greedy_path_start(maze, model, {6: U, 0: R, 1: R, 2: R}, greedy_path=False)
    assert ss.target.tolist() == paper.target.tolist() and ss.first_move.tolist() == [-1]


def test_unknown_option_is_refused():
    maze = _maze()
    with pytest.raises(ValueError, match="select='nearest'"):
        _controller(maze, CountModel(maze.n_cells), select="nearest")


# --- in the training loop --------------------------------------------------------------------------------------------
def test_episodes_count_each_new_move_once_and_the_exploration_phase(tmp_path):
    cfg = compose_cfg(
        "+experiment=easy_small_ss_her_bounded", "smart_start.select=frontier", "smart_start.explore=frontier",
        "env.max_steps=200", "trainer.total_env_steps=1500", "agent.learning_starts=10000",
    )  # fmt: skip
    trainer = Trainer(cfg, tmp_path)
    collector, episodes = trainer.collector, []
    while collector.env_steps < 1500:
        batch, finished = collector.rollout()
        nxt = batch["next"]
        trainer.counts.update(batch["observation"], batch["action"], nxt["observation"], nxt["reward"])
        episodes += finished
    open_moves = [e.new_moves for e in episodes]
    in_progress = int(collector.ep_new_moves.sum())
    assert sum(open_moves) + in_progress == int((trainer.counts.sa_counts > 0).sum())
    guided = [e for e in episodes if e.smart_start]
    # S_ss is on the frontier (0 steps from it) while there is one; once none is left, -1.
    frontier_steps = [e.ss_frontier_steps for e in guided]
    assert 0 in frontier_steps and set(frontier_steps) <= {0, -1}
    assert frontier_steps == sorted(frontier_steps, reverse=True)
    assert sum(e.explore_steps for e in guided) > 0
    assert all(e.new_moves_after_ss <= e.new_moves for e in guided)
    # The new moves after S_ss are the exploration phase's work (the guided route runs over tried moves), and the
    # phases of an episode do not overlap: guided steps, then the exploration phase, within the episode's length.
    assert sum(e.new_moves_after_ss for e in guided) > 0
    assert all(e.ss_steps + e.explore_steps <= e.length for e in guided)


@pytest.mark.parametrize("from_start", [False, True])
def test_the_first_episode_explores_from_its_first_step_only_with_explore_from_start(from_start):
    """A copy's first episode has no guided phase. With ``explore_from_start`` it is an exploration phase from S; on
    the hand-built count model S's moves are all tried and the one untried move is 2's right, so the phase walks the
    one shortest route there (up, right, right) and tries it. Without the option the policy acts from the first
    step."""
    maze = _maze()
    ss = SmartStart(
        maze, _hand_model(maze), 1, eta=1.0, c_ss=2.0, w_q=0.0, theta=0, planner=Planner(maze.width),
        generator=torch.Generator().manual_seed(0), explore="frontier", explore_from_start=from_start,
    )  # fmt: skip
    one = torch.ones(1, dtype=torch.bool)
    ss.start_episodes(one, torch.tensor([maze.start_cell]), torch.tensor([maze.goal_cell]), None)
    assert not ss.used.any() and ss.exploring.tolist() == [from_start]
    if not from_start:
        assert _step(ss, maze, maze.start_cell) == (SENTINEL, maze.start_cell)
        return
    trace = [_step(ss, maze, cell) for cell in (maze.start_cell, 0, 1, 2)]
    assert trace == [(U, 0), (R, 1), (R, 2), (R, 3)] and ss.exploring.tolist() == [True]
