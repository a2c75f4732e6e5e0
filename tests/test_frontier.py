"""The frontier explorer (ss_drl/agents/frontier.py): a hand trace, its rule on a real maze, seeded ties, the values
it reports for evaluation, resume, and an end-to-end run with the usual outputs."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest
import torch
from helpers import ROOT, compose_cfg
from omegaconf import OmegaConf
from tensordict import TensorDict

from ss_drl.agents.frontier import UNTRIED, FrontierExplorer
from ss_drl.envs.maze import load_maze, parse_maze
from ss_drl.graph import breadth_first
from ss_drl.training.greedy import greedy_rollout
from ss_drl.training.outputs import (
    CHECKPOINT_FILE,
    EPISODES_FILE,
    EVAL_FILE,
    SUMMARY_FILE,
    SUMMARY_KEYS,
    TRAIN_COLUMNS,
    TRAIN_FILE,
)
from ss_drl.training.trainer import Trainer

R, D, L, U = range(4)  # ss_drl.envs.maze.ACTIONS: right, down, left, up
#: A 2x5 maze: a corridor with S one cell from its left end, and G above its right end.
CORRIDOR = "####G\n.S...\n"
CFG = OmegaConf.create({"name": "frontier", "gamma": 0.9})


class FirstChoice(FrontierExplorer):
    """The explorer with every random choice replaced by the first option (moves in action order, cells by index),
    recording the options of each choice and each planned route, so that a trace can be written by hand."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.choices: list[list] = []
        self.plans: list[tuple[int, list | None]] = []

    def _choice(self, options):
        self.choices.append(list(options))
        return options[0]

    def plan(self, cell, targets):
        route = super().plan(cell, targets)
        self.plans.append((cell, None if route is None else list(route)))
        return route


def step_batch(s: int, a: int, s2: int, terminated: bool) -> TensorDict:
    """One transition as the collector's (T=1, N=1) batch holds it (the keys the explorer reads)."""
    return TensorDict(
        {
            "observation": torch.tensor([[s]]),
            "action": torch.tensor([[a]]),
            "next": {"observation": torch.tensor([[s2]]), "terminated": torch.tensor([[[terminated]]])},
        },
        batch_size=(1, 1),
    )


def drive(agent, maze, steps: int, max_steps: int = 1000, until_goal: bool = False):
    """Step ``agent`` in ``maze`` as the training loop does (act, then store the transition; G or the cut resets to
    S); returns the (cell, action, next cell) of every step."""
    table = maze.transition_table()
    cell, t, trace = maze.start_cell, 0, []
    for _ in range(steps):
        a = int(agent.act(torch.tensor([cell]), torch.tensor([maze.goal_cell]))[0])
        nxt = int(table[cell, a])
        terminated = nxt == maze.goal_cell
        agent.store(step_batch(cell, a, nxt, terminated))
        trace.append((cell, a, nxt))
        t += 1
        if terminated and until_goal:
            break
        cell, t = (maze.start_cell, 0) if terminated or t >= max_steps else (nxt, t)
    return trace


# --- the hand trace -----------------------------------------------------------------------------------------------
def test_the_moves_it_tries_on_a_hand_drawn_maze_against_a_hand_trace():
    """CORRIDOR's cells, by flat index (row * 5 + col): 5 6 7 8 9 in the corridor (S = 6), G = 4 above 9.

    With first-option choices, the hand trace (each cell tries its untried moves in the order R, D, L, U; a bump
    into a wall or off the grid is a tried move):
    1-3    S 6: R to 7, R to 8, R to 9;
    4-6    9: R off the grid (bump), D off the grid (bump), L back to 8 (9 keeps U untried);
    7-8    8: D bump, L to 7;   9-10  7: D bump, L to 6;   11-12  6: D bump, L to 5;   13  5: R to 6;
    14     6: U into the wall (bump): 6 has no untried move left;
    15     the nearest cells with an untried move are 5 and 7 (one step each, a tie: 5 first): L to 5;
    16-18  5: D bump, L off the grid (bump), U into the wall (bump): 5 is done;
    19-20  nearest untried move: 7 (two steps, 8 and 9 are three and four): R to 6, R to 7 along known cells;
    21     7: U bump;   22  nearest: 8, R;   23  8: U bump;   24  nearest: 9, R;   25  9: U into G.
    """
    maze = parse_maze(CORRIDOR)
    agent = FirstChoice(CFG, maze)
    trace = drive(agent, maze, 100, until_goal=True)
    actions = [a for _, a, _ in trace]
    assert actions == [R, R, R, R, D, L, D, L, D, L, D, L, R, U, L, D, L, U, R, R, U, R, U, R, U]
    assert [cell for cell, _, _ in trace] == [6, 7, 8, 9, 9, 9, 8, 8, 7, 7, 6, 6, 5, 6, 6, 5, 5, 5, 5, 6, 7, 7, 8, 8, 9]
    assert trace[-1] == (9, U, 4)
    # A route is planned only where the cell stands with no untried move: steps 15, 19, 22 and 24.
    assert agent.plans == [(6, [(6, L)]), (5, [(5, R), (6, R)]), (7, [(7, R)]), (8, [(8, R)])]
    # The one tie between frontier cells (step 15); every other choice of several options is among untried moves.
    ties = [options for options in agent.choices if len(options) > 1 and max(options) >= 4]
    assert ties == [[5, 7]]
    # The memory: bumps are tried moves that lead back to their cell; G is terminal (no move to try from it).
    assert agent.successor[9] == [9, 9, 8, 4] and agent.successor[5] == [6, 5, 5, 5]
    assert agent.terminal == {4} and agent.frontier == set() and agent.untried(4) == []
    # Once everything is tried, it walks the shortest known route to G: 6 -> 7 -> 8 -> 9 -> G.
    assert [a for _, a, _ in drive(agent, maze, 4)] == [R, R, R, U]


def test_nearest_frontier_ties_are_broken_at_random_by_the_seed():
    """The memory of step 14 of the hand trace (cell 6 done; 5 and 7 one step away with untried moves): over seeds,
    both nearest cells are chosen; the same seed chooses the same."""
    maze = parse_maze(CORRIDOR)
    first = FirstChoice(CFG, maze)
    trace = drive(first, maze, 14)
    chosen = {}
    for seed in range(20):
        agent = FrontierExplorer(CFG, maze, seed=seed)
        for transition in trace:
            agent.store(step_batch(*transition, terminated=False))
        assert agent.untried(6) == [] and agent.frontier == {5, 7, 8, 9}
        chosen[seed] = agent.plan(6, agent.frontier)
    assert {tuple(route) for route in chosen.values()} == {((6, L),), ((6, R),)}
    again = FrontierExplorer(CFG, maze, seed=3)
    for transition in trace:
        again.store(step_batch(*transition, terminated=False))
    assert again.plan(6, again.frontier) == chosen[3]


def known_distances_to(cells: set[int], successor: list[list[int]]) -> list[int]:
    """Fewest known moves from every cell into ``cells`` (-1: none), on the memory's own transitions."""
    backward = [[] for _ in successor]
    for s, row in enumerate(successor):
        for s2 in row:
            if s2 != UNTRIED and s2 != s:
                backward[s2].append(s)
    dist = [-1] * len(successor)
    for cell in cells:
        dist[cell] = 0
    breadth_first(sorted(cells), dist, backward)
    return dist


@pytest.mark.parametrize("seed", [0, 1])
def test_every_move_is_untried_or_on_a_shortest_known_route_to_the_nearest_untried_move(seed):
    """The rule, checked at every step on easy_small (seeded random choices) against a memory the test keeps itself:
    where the cell has an untried move, the move is one of them; elsewhere the move is known and takes the agent one
    known step nearer to the nearest cell with an untried move; memory is kept across resets (episodes of 200 steps
    here), and no move is tried twice."""
    maze = load_maze("easy_small")
    agent = FrontierExplorer(CFG, maze, seed=seed)
    successor = [[UNTRIED] * 4 for _ in range(maze.n_cells)]
    known, terminal = {maze.start_cell}, set()  # cells stood on; cells entered with terminated
    tried = walks = 0
    for cell, a, nxt in drive(agent, maze, 1500, max_steps=200):
        if UNTRIED in successor[cell]:
            assert successor[cell][a] == UNTRIED
            tried += 1
        else:
            frontier = {c for c in known - terminal if UNTRIED in successor[c]}
            dist = known_distances_to(frontier or terminal, successor)  # explored: the route to G
            assert successor[cell][a] == nxt != cell, "a walking move is a known move that leaves the cell"
            assert dist[cell] > 0 and dist[nxt] == dist[cell] - 1
            walks += 1
        successor[cell][a] = nxt
        known.add(nxt)
        if nxt == maze.goal_cell:
            terminal.add(nxt)
    assert terminal == {maze.goal_cell}
    assert tried == sum(x != UNTRIED for row in successor for x in row)  # each tried once
    assert walks > 0 and agent.successor == successor and agent.frontier == set()


# --- values for evaluation ----------------------------------------------------------------------------------------
def test_greedy_values_walk_the_shortest_known_route():
    """Q(s, a) = gamma^d(s'), d the fewest known steps from s' to the goal; 0 for untried moves and for cells with
    no known route. Before G is known every value is 0; once the memory holds a shortest path, greedy is optimal."""
    maze = parse_maze(CORRIDOR)
    before = FirstChoice(CFG, maze)
    drive(before, maze, 24)  # the hand trace up to the step before G
    goal = torch.tensor([maze.goal_cell])
    assert before.greedy_q_values(torch.arange(maze.n_cells), goal).abs().sum() == 0
    assert not greedy_rollout(before, maze, 50).success
    agent = FirstChoice(CFG, maze)
    drive(agent, maze, 25)  # ... and its last step, into G from 9: the moves of the other cells are all known
    q = agent.greedy_q_values(torch.tensor([9, 8, 6]), goal)[0]
    g = 0.9
    assert torch.allclose(q[0], torch.tensor([g, g, g**2, 1.0]))  # 9: R and D bump (9 is 1 step away), L to 8, U in
    assert torch.allclose(q[1], torch.tensor([g, g**2, g**3, g**2]))  # 8: R to 9, bumps, L to 7 (3 steps away)
    assert torch.allclose(q[2], torch.tensor([g**3, g**4, g**5, g**4]))  # 6 = S: 4 steps from G, 5 is 5
    rollout = greedy_rollout(agent, maze, 50)
    assert rollout.success and rollout.path == [6, 7, 8, 9, 4] and rollout.accuracy == 1.0
    assert agent.q_values(torch.tensor([9]), goal).shape == (1, 1, 4)
    # Any goal the memory reaches: the values towards cell 5 (the corridor's left end) from 7.
    towards_5 = agent.greedy_q_values(torch.tensor([7]), torch.tensor([5]))[0, 0]
    assert torch.allclose(towards_5, torch.tensor([g**3, g**2, g, g**2]))


# --- the training loop: no updates, resume, outputs ---------------------------------------------------------------
RUN = ["+experiment=easy_small_frontier", "trainer.eval_interval=50", "trainer.checkpoint_interval=100000"]


def rows_without_wall(path):
    with path.open() as f:
        rows = list(csv.reader(f))
    i = rows[0].index("wall_s")
    return [r[:i] + r[i + 1 :] for r in rows]


@pytest.mark.slow  # five training runs
def test_resume_equals_an_uninterrupted_run(tmp_path):
    """Stopped at 100 (while exploring), 250 and 600 env steps and resumed each time, a run equals the uninterrupted
    one: its episodes, evaluations, first goal and memory (the planned route and the generator travel in the
    checkpoint). The cut points sit on the evaluation cadence, so neither run evaluates anywhere the other does not."""
    whole = Trainer(compose_cfg(*RUN, "trainer.total_env_steps=1500"), tmp_path / "whole")
    whole.train()
    cut = tmp_path / "cut"
    routes = 0
    for i, steps in enumerate((100, 250, 600, 1500)):
        trainer = Trainer(compose_cfg(*RUN, f"trainer.total_env_steps={steps}", f"trainer.resume={i > 0}"), cut)
        trainer.train()
        routes += bool(trainer.agent.state_dict()["routes"])
    assert routes, "no cut fell where the explorer was on a planned route: pick other cut points"
    for file in (EPISODES_FILE, EVAL_FILE):
        assert rows_without_wall(cut / file) == rows_without_wall(tmp_path / "whole" / file)
    a, b = (json.loads((d / SUMMARY_FILE).read_text()) for d in (tmp_path / "whole", cut))
    for key in ("first_goal_env_step", "first_goal_episode", "episodes", "learned_env_step", "final_eval_length"):
        assert a[key] == b[key], key
    state_a, state_b = whole.agent.state_dict(), trainer.agent.state_dict()
    assert (state_a["successor"] == state_b["successor"]).all() and state_a["routes"] == state_b["routes"]
    assert torch.equal(state_a["generator"], state_b["generator"])


@pytest.mark.slow  # an end-to-end run of 2000 env steps, then plot.py, evaluate.py and diagnose.py on it
def test_easy_small_frontier_end_to_end(tmp_path):
    """``+experiment=easy_small_frontier`` writes the outputs of every method: episodes.csv, eval.csv, a train.csv
    with its header only (no learning update), summary.json labelled ``frontier`` with its first goal and the
    learned rule, a checkpoint; and the analysis scripts read it."""
    run = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "train.py"), "+experiment=easy_small_frontier",
         "trainer.total_env_steps=2000", f"hydra.run.dir={run}"],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads((run / SUMMARY_FILE).read_text())
    assert list(summary) == list(SUMMARY_KEYS)
    assert summary["method"] == "frontier" and summary["experiment"] == "easy_small_frontier"
    assert summary["completed"] and summary["env_steps"] == 2000 and summary["updates_per_s"] == 0
    assert 0 < summary["first_goal_env_step"] < 1000 and summary["first_goal_episode"] == 1
    assert summary["learned_env_step"] is not None and summary["final_eval_length"] == summary["optimal_length"] == 19
    # Its memory holds every move by then, so its greedy action is a shortest-path move in every cell.
    assert summary["final_greedy_accuracy"] == 1.0 and summary["bounds_in_force"] == []
    assert (run / TRAIN_FILE).read_text().splitlines() == [",".join(TRAIN_COLUMNS)]
    with (run / EPISODES_FILE).open() as f:
        episodes = list(csv.DictReader(f))
    assert int(episodes[0]["env_steps"]) == summary["first_goal_env_step"] and episodes[0]["success"] == "1"
    assert {e["epsilon"] for e in episodes} == {"0.0"} and {e["smart_start"] for e in episodes} == {"0"}
    assert (run / CHECKPOINT_FILE).is_file()
    outputs = {}
    for script, extra in (("plot.py", ["--out", str(tmp_path / "plots")]), ("evaluate.py", []), ("diagnose.py", [])):
        done = subprocess.run(
            [sys.executable, str(ROOT / "scripts" / script), str(run), *extra],
            capture_output=True, text=True, cwd=ROOT, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, f"{script}: {done.stderr}"
        assert "Warning" not in done.stderr, f"{script}: {done.stderr}"
        outputs[script] = done.stdout
    plots = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert "easy_small_first_goal.png" in plots and "easy_small_learning.png" not in plots  # no train.csv rows
    assert "length 19, success 1" in outputs["evaluate.py"]
    assert "(frontier, agent frontier)" in outputs["diagnose.py"]
