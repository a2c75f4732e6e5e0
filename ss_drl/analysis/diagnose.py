"""Diagnose a trained run: why a deep agent fails where tabular Smart Start succeeds (issue 12, "Diagnose before you
fix"). Measurements only, no fixes:

1. **Greedy accuracy by distance to G**: per bucket of BFS distance to G, the fraction of states whose greedy action
   (argmax of ``greedy_q_values(cells, [G])``) leads one step closer to G.
2. **Q along the greedy path from S**: ``max_a Q(s||G, a)`` at each state of the greedy rollout from S against the
   optimal value on the env's 0/1 reward scale, ``gamma^(d(s) - 1)``; the mean absolute error, the first step that
   leaves a shortest path and whether the rollout loops.
3. **Value error by distance**: mean absolute and mean signed error of ``max_a Q(s||G, a)`` against
   ``gamma^(d - 1)`` per distance bucket, over all free states that can reach G (G itself aside).
4. **Training data**: from train.csv the mean ``goal_share`` (overall and in the last quarter of the run); from
   episodes.csv the share of episodes that reach G after the first success and in the last quarter, and the share of
   episodes with a Smart Start guided phase.
5. **Exploration before the first goal**: from episodes.csv (runs that log ``end_state`` and ``states_visited``),
   over the training episodes that end before the first one that reaches G: the cells visited by then (coverage),
   the median true (BFS) and Manhattan distance to G of the cells those episodes end in, and the median true
   distance to G of their smart start states. An ε-greedy phase drawn towards G by a distance that ignores walls
   ends near G in Manhattan terms but far from it in steps.

The run may be on a maze or on a MiniGrid task (:class:`~ss_drl.envs.minigrid.MiniGridTask`): everything is measured
over the world's states (a maze's states are its cells; a task's are its cell, direction, doors and carried object),
with the distances of ``distances_to_goal()``. Where a task differs: a state counts as G when its cell is G's; the
greedy path's steps name their state (``state``, ``label``) besides its cell; episodes.csv's states are
``row:col:direction`` (without the doors and the carried object), so the true distance of one is the fewest steps
to G from any state with that cell and direction (a lower bound), and the Manhattan distance is its cell's; the
coverage is out of the task's reachable states rather than a maze's free cells.

The same numbers hold for a tabular run (its ``greedy_q_values`` knows only G, which is the only goal asked for here).

    python scripts/diagnose.py <run dir> [<run dir> ...] [--bucket-width 10] [--out DIR]

prints a markdown section per run and writes ``diagnosis.json`` (and ``diagnosis.md``) into each run directory; with
``--out DIR`` they go to ``DIR`` instead, ``diagnosis.json`` then holding a list with one object per run, in order.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ss_drl.analysis.aggregate import IncompleteRun, read_run_csv
from ss_drl.analysis.tables import format_markdown_table
from ss_drl.envs.maze import Maze, state_cells
from ss_drl.methods import method_label
from ss_drl.training.greedy import greedy_accuracy, greedy_policy, greedy_rollout
from ss_drl.training.learned import LAST_QUARTER
from ss_drl.training.outputs import CHECKPOINT_FILE, EPISODES_FILE, SUMMARY_FILE, TRAIN_FILE, write_json_atomic

DIAGNOSIS_FILE = "diagnosis.json"
DIAGNOSIS_MD = "diagnosis.md"
#: At most this many steps of the greedy path are listed in the markdown (all of them are in the JSON).
PATH_ROWS = 20


class DiagnoseError(ValueError):
    """A run directory or option that cannot be diagnosed; the message is one line."""


# --- the optimal values -------------------------------------------------------------------------------------------
def value_gamma(agent_cfg) -> float:
    """The discount of the optimal values ``gamma^(d - 1)`` that the agent's ``greedy_q_values`` are compared with.

    The agent's own gamma, except for the DQN's undiscounted cost form (gamma 1 with a step cost), whose
    ``greedy_q_values`` map distances to the 0/1 scale with :data:`~ss_drl.agents.dqn.UNDISCOUNTED_SCALE`.
    """
    gamma = float(agent_cfg.gamma)
    if gamma == 1 and float(agent_cfg.get("step_cost", 0.0)) > 0:
        from ss_drl.agents.dqn import UNDISCOUNTED_SCALE

        return UNDISCOUNTED_SCALE
    return gamma


def goal_distances(maze: Maze) -> np.ndarray:
    """(n_states,) fewest steps from every state to G (a maze's BFS from G, its moves being reversible; a MiniGrid
    task's search back from G's states); -1 for walls and states that cannot reach G."""
    return maze.distances_to_goal()


def max_q(agent, maze: Maze) -> np.ndarray:
    """(n_states,) ``max_a Q(s||G, a)`` of every state on the env's 0/1 scale, from one batched evaluation."""
    with torch.no_grad():
        q = agent.greedy_q_values(torch.arange(maze.n_states), torch.tensor([maze.goal_cell]))[0]
    return q.amax(dim=-1).double().cpu().numpy()


# --- buckets ------------------------------------------------------------------------------------------------------
def _buckets(dist: np.ndarray, width: int) -> list[tuple[int, int, np.ndarray]]:
    """(lo, hi, cells) per non-empty bucket ``lo..hi`` of distances ``(k - 1) * width + 1 .. k * width``, over the
    cells with distance > 0, in increasing distance."""
    if width < 1:
        raise DiagnoseError(f"bucket width must be >= 1 (got {width})")
    cells = np.flatnonzero(dist > 0)
    index = (dist[cells] - 1) // width
    out = []
    for k in np.unique(index):
        lo, hi = int(k) * width + 1, (int(k) + 1) * width
        out.append((lo, hi, cells[index == k]))
    return out


def _label(lo: int, hi: int) -> str:
    return str(lo) if lo == hi else f"{lo}-{hi}"


def accuracy_by_distance(policy: torch.Tensor, maze: Maze, width: int = 10) -> list[dict]:
    """Per distance bucket, the fraction of its states whose action in ``policy`` (n_states,) leads one step closer
    to G: ``[{"distances", "min", "max", "states", "accuracy"}]``."""
    dist = goal_distances(maze)
    table = maze.transition_table()
    actions = policy.cpu().numpy()
    rows = []
    for lo, hi, cells in _buckets(dist, width):
        closer = dist[table[cells, actions[cells]]] == dist[cells] - 1
        rows.append(
            {"distances": _label(lo, hi), "min": lo, "max": hi, "states": len(cells), "accuracy": float(closer.mean())}
        )
    return rows


def _errors(q: np.ndarray, dist: np.ndarray, gamma: float) -> np.ndarray:
    """``q - gamma^(d - 1)`` of cells with distances ``dist`` (> 0)."""
    return q - gamma ** (dist.astype(np.float64) - 1)


def value_error_by_distance(q_max: np.ndarray, maze: Maze, gamma: float, width: int = 10) -> tuple[list[dict], dict]:
    """Per distance bucket and over all free states that can reach G (G aside), the mean absolute and the mean
    signed error of ``q_max`` (n_states,) against the optimal ``gamma^(d - 1)``: (bucket rows, overall)."""
    dist = goal_distances(maze)
    rows = []
    for lo, hi, cells in _buckets(dist, width):
        err = _errors(q_max[cells], dist[cells], gamma)
        rows.append(
            {
                "distances": _label(lo, hi),
                "min": lo,
                "max": hi,
                "states": len(cells),
                "mean_abs_error": float(np.abs(err).mean()),
                "mean_signed_error": float(err.mean()),
            }
        )
    cells = np.flatnonzero(dist > 0)
    err = _errors(q_max[cells], dist[cells], gamma)
    overall = {
        "states": len(cells),
        "mean_abs_error": float(np.abs(err).mean()),
        "mean_signed_error": float(err.mean()),
    }
    return rows, overall


def greedy_path_values(agent, maze: Maze, q_max: np.ndarray, gamma: float, max_steps: int) -> dict:
    """The greedy rollout from S (:func:`~ss_drl.training.greedy.greedy_rollout`) and, at each state it acts in,
    ``max_a Q(s||G, a)`` against the optimal ``gamma^(d(s) - 1)``.

    ``first_off_shortest`` is the first step whose successor is not one step closer to G (None when the whole path
    is a shortest one); ``loops`` says whether the rollout stopped on a state it had visited before. In a MiniGrid
    task each step also names its ``state`` (id) and ``label`` (``row:col:direction``), ``cell`` being its cell.
    """
    dist = goal_distances(maze)
    cell_of = state_cells(maze)
    rollout = greedy_rollout(agent, maze, max_steps)
    path = rollout.path
    steps, first_off = [], None
    for t, (state, nxt) in enumerate(zip(path[:-1], path[1:])):
        d = int(dist[state])
        optimal = gamma ** (d - 1)
        row, col = maze.pos(state)
        step = {"step": t, "cell": int(state) if cell_of is None else int(cell_of(torch.tensor(state)))}
        if cell_of is not None:
            step.update(state=int(state), label=maze.label(state))
        step.update(
            row=row,
            col=col,
            distance=d,
            q_max=float(q_max[state]),
            optimal=float(optimal),
            error=float(q_max[state] - optimal),
        )
        steps.append(step)
        if first_off is None and dist[nxt] != d - 1:
            first_off = t
    loops = (not rollout.success) and path[-1] in path[:-1]
    off = None
    if first_off is not None:
        s = steps[first_off]
        keys = ("cell", "row", "col") if cell_of is None else ("cell", "state", "label", "row", "col")
        off = {"step": first_off, **{k: s[k] for k in keys}, "distance": s["distance"]}
    return {
        "success": bool(rollout.success),
        "length": int(rollout.length),
        "optimal_length": int(dist[maze.start_state]),
        "loops": bool(loops),
        "first_off_shortest": off,
        "mean_abs_error": float(np.mean([abs(s["error"]) for s in steps])) if steps else None,
        "steps": steps,
    }


def diagnose_agent(agent, maze: Maze, gamma: float, max_steps: int, width: int = 10) -> dict:
    """Points 1-3 for an agent on its maze: greedy accuracy and value error by distance, Q along the greedy path."""
    policy = greedy_policy(agent, maze)
    q_max = max_q(agent, maze)
    value_rows, value_overall = value_error_by_distance(q_max, maze, gamma, width)
    return {
        "greedy_accuracy": greedy_accuracy(policy, maze),
        "accuracy_by_distance": accuracy_by_distance(policy, maze, width),
        "greedy_path": greedy_path_values(agent, maze, q_max, gamma, max_steps),
        "value_error": value_overall,
        "value_error_by_distance": value_rows,
    }


# --- training data ------------------------------------------------------------------------------------------------
def _mean(values: np.ndarray) -> float | None:
    return float(values.mean()) if values.size else None


def training_data(run_dir: Path, total_env_steps: float | None = None) -> dict:
    """Point 4, from train.csv and episodes.csv.

    The last quarter is ``env_steps > 0.75 * total`` (as in :mod:`ss_drl.training.learned`), with ``total`` the
    run's env steps (``total_env_steps``, else the largest env steps in the two files). A missing or unusable file
    (train.csv of an old run, one without ``goal_share``) leaves its numbers None with a ``*_note`` saying why.
    """
    run_dir = Path(run_dir)
    train, episodes, notes = None, None, {}
    if (run_dir / TRAIN_FILE).is_file():
        try:
            train = read_run_csv(run_dir / TRAIN_FILE, ("env_steps",), ("env_steps", "goal_share"), ("goal_share",))
        except IncompleteRun as e:
            notes["train_note"] = f"{TRAIN_FILE} unusable: {e}"
        else:
            if train["goal_share"].size and np.isnan(train["goal_share"]).all():
                notes["train_note"] = f"{TRAIN_FILE} has no goal_share column (a run from before it was logged)"
                train = None
    else:
        notes["train_note"] = f"no {TRAIN_FILE} (a run from before it was written)"
    columns = ("env_steps", "success", "smart_start")
    if (run_dir / EPISODES_FILE).is_file():
        try:
            episodes = read_run_csv(run_dir / EPISODES_FILE, columns, columns)
        except IncompleteRun as e:
            notes["episodes_note"] = f"{EPISODES_FILE} unusable: {e}"
    else:
        notes["episodes_note"] = f"no {EPISODES_FILE}"
    if total_env_steps is None:
        seen = [float(t["env_steps"].max()) for t in (train, episodes) if t is not None and t["env_steps"].size]
        total_env_steps = max(seen) if seen else None
    cut = None if total_env_steps is None else float(LAST_QUARTER) * float(total_env_steps)

    def last_quarter(env_steps: np.ndarray) -> np.ndarray:
        return np.zeros(env_steps.shape, dtype=bool) if cut is None else env_steps > cut

    out: dict = {"total_env_steps": total_env_steps, "last_quarter_after_env_steps": cut}
    out["train_rows"] = None if train is None else int(train["env_steps"].size)
    out["goal_share_mean"] = None if train is None else _mean(train["goal_share"])
    out["goal_share_last_quarter"] = (
        None if train is None else _mean(train["goal_share"][last_quarter(train["env_steps"])])
    )
    if episodes is None:
        for key in ("episodes", "first_success_episode", "episodes_after_first_success"):
            out[key] = None
        for key in ("success_after_first_success", "success_last_quarter", "smart_start_share"):
            out[key] = None
        out["smart_start_share_last_quarter"] = None
    else:
        success, smart = episodes["success"] > 0, episodes["smart_start"] > 0
        last = last_quarter(episodes["env_steps"])
        hits = np.flatnonzero(success)
        first = int(hits[0]) if hits.size else None
        out["episodes"] = int(success.size)
        out["first_success_episode"] = None if first is None else first + 1
        out["episodes_after_first_success"] = None if first is None else int(success.size - first - 1)
        out["success_after_first_success"] = None if first is None else _mean(success[first + 1 :].astype(float))
        out["success_last_quarter"] = _mean(success[last].astype(float))
        out["smart_start_share"] = _mean(smart.astype(float))
        out["smart_start_share_last_quarter"] = _mean(smart[last].astype(float))
    out.update(notes)
    return out


# --- exploration before the first goal ---------------------------------------------------------------------------
def label_distances(maze: Maze) -> dict[str, int] | None:
    """In a MiniGrid task, the true distance to G of each label episodes.csv writes (``row:col:direction``, which
    leaves out the doors and the carried object): the fewest steps to G from any state with that label (-1 when
    none can reach G). None in a maze, whose labels name one state each."""
    if state_cells(maze) is None:
        return None
    dist = goal_distances(maze)
    out: dict[str, int] = {}
    for state in range(maze.n_states):
        label, d = maze.label(state), int(dist[state])
        best = out.get(label, -1)
        out[label] = d if d >= 0 and (best < 0 or d < best) else best
    return out


def _state(
    text: str, maze: Maze, dist: np.ndarray, labels: dict[str, int] | None, path: Path, line: int, column: str
) -> tuple[int, int, int]:
    """(row, col, true distance to G) of a state written by episodes.csv: ``row:col`` in a maze (``dist``: its
    :func:`goal_distances`), ``row:col:direction`` in a MiniGrid task (``labels``: its :func:`label_distances`),
    whose row and column are its cell's."""
    expected = "row:col" if labels is None else "row:col:direction"
    try:
        fields = [int(v) for v in text.split(":")]
    except ValueError:
        fields = []
    if len(fields) != expected.count(":") + 1:
        raise DiagnoseError(f"{path} line {line}: bad {column} value {text!r} (expected {expected})")
    row, col = fields[:2]
    if not (0 <= row < maze.height and 0 <= col < maze.width):
        world = "maze" if labels is None else "grid"
        raise DiagnoseError(f"{path} line {line}: {column} {text} lies outside the {maze.height}x{maze.width} {world}")
    if labels is None:
        return row, col, int(dist[maze.cell((row, col))])
    label = ":".join(map(str, fields))
    if label not in labels:
        raise DiagnoseError(
            f"{path} line {line}: {column} {text} is not a state of {maze.name} (no reachable state has that cell "
            "and direction)"
        )
    return row, col, labels[label]


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def exploration_before_first_goal(run_dir: Path, maze: Maze) -> dict:
    """Point 5, from episodes.csv; ``note`` (and no numbers) for a run from before ``end_state`` was logged.

    In a MiniGrid task the true distance of a state written as ``row:col:direction`` is that of
    :func:`label_distances` (a lower bound), its Manhattan distance its cell's, and ``free_states`` is the task's
    number of reachable states (what ``states_visited`` counts), a maze's free cells otherwise."""
    path = Path(run_dir) / EPISODES_FILE
    if not path.is_file():
        return {"note": f"no {EPISODES_FILE}"}
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            rows, header = list(reader), reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DiagnoseError(f"{path}: cannot read it ({type(e).__name__}: {' '.join(str(e).split())})") from None
    if rows and ("end_state" not in header or "states_visited" not in header):
        return {"note": f"{EPISODES_FILE} has no end_state/states_visited columns (a run from before they were logged)"}
    missing = [c for c in ("env_steps", "success", "ss_target") if c not in header]
    if missing:
        raise DiagnoseError(f"{path}: lacks the columns {', '.join(missing)}")
    dist, labels = goal_distances(maze), label_distances(maze)
    goal_row, goal_col = maze.goal
    before, first_goal = [], None
    for line, row in enumerate(rows, start=2):
        if None in row:  # csv.DictReader's key for fields beyond the header's
            raise DiagnoseError(f"{path} line {line}: more fields than the header's {len(header)}")
        if None in row.values():  # and its value for the fields a row lacks
            raise DiagnoseError(f"{path} line {line}: fewer fields than the header's {len(header)} (a cut file?)")
        for column in ("env_steps", "states_visited"):
            if not row[column].isdigit():
                raise DiagnoseError(f"{path} line {line}: bad {column} value {row[column]!r} (expected a count)")
        if row["success"] == "1":
            first_goal = int(row["env_steps"])
            break
        before.append((line, row))
    ends = [_state(r["end_state"], maze, dist, labels, path, line, "end_state") for line, r in before]
    targets = [
        _state(r["ss_target"], maze, dist, labels, path, line, "ss_target") for line, r in before if r["ss_target"]
    ]
    manhattan = [abs(row - goal_row) + abs(col - goal_col) for row, col, _ in ends]
    return {
        "first_goal_env_step": first_goal,
        "episodes": len(before),
        "env_steps": int(before[-1][1]["env_steps"]) if before else 0,
        "states_visited": int(before[-1][1]["states_visited"]) if before else 0,
        "free_states": maze.n_free if labels is None else maze.n_states,
        "end_true_distance_median": _median([float(d) for _, _, d in ends]),
        "end_manhattan_distance_median": _median([float(m) for m in manhattan]),
        "ss_target_true_distance_median": _median([float(d) for _, _, d in targets]),
    }


# --- one run ------------------------------------------------------------------------------------------------------
def _summary(run_dir: Path) -> dict:
    path = run_dir / SUMMARY_FILE
    if not path.is_file():
        return {}
    try:
        summary = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DiagnoseError(f"{path}: unreadable {SUMMARY_FILE} ({' '.join(str(e).split())})") from None
    return summary if isinstance(summary, dict) else {}


def diagnose_run(run_dir: str | Path, width: int = 10) -> dict:
    """Points 1-4 for one run directory (its checkpoint.pt, train.csv, episodes.csv and summary.json)."""
    from ss_drl.evaluate import OldCheckpoint, load_agent
    from ss_drl.training.checkpoint import UnreadableCheckpoint

    run_dir = Path(run_dir)
    if width < 1:
        raise DiagnoseError(f"bucket width must be >= 1 (got {width})")
    if not run_dir.is_dir():
        raise DiagnoseError(f"not a directory: {run_dir}")
    if not (run_dir / CHECKPOINT_FILE).is_file():
        raise DiagnoseError(f"no {CHECKPOINT_FILE} in {run_dir}")
    summary = _summary(run_dir)
    try:
        agent, maze, cfg = load_agent(run_dir)
    except (OldCheckpoint, UnreadableCheckpoint) as e:  # one line naming the file and the reason
        raise DiagnoseError(str(e)) from None
    except Exception as e:  # noqa: BLE001  (a broken checkpoint of any kind: one line naming the run)
        raise DiagnoseError(
            f"cannot load {run_dir / CHECKPOINT_FILE}: {type(e).__name__}: {' '.join(str(e).split())}"
        ) from None
    gamma = value_gamma(cfg.agent)
    total = summary.get("env_steps")
    total = total if isinstance(total, (int, float)) and not isinstance(total, bool) else None
    return {
        "run_dir": str(run_dir),
        "experiment": str(cfg.experiment),
        "method": method_label(cfg),
        "seed": int(cfg.seed),
        "agent": str(cfg.agent.name),
        "agent_gamma": float(cfg.agent.gamma),
        "value_gamma": gamma,
        "maze": maze.name,
        **({} if state_cells(maze) is None else {"world": "minigrid", "states": maze.n_states}),
        "optimal_length": maze.shortest_path_length,
        "slip": float(cfg.env.get("slip", 0) or 0),
        "bucket_width": int(width),
        **diagnose_agent(agent, maze, gamma, int(cfg.env.max_steps), width),
        "training": training_data(run_dir, total),
        "exploration": exploration_before_first_goal(run_dir, maze),
    }


# --- output -------------------------------------------------------------------------------------------------------
def _finite(value):
    """JSON-safe: non-finite floats (a diverged Q) become None, recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def _f(value, spec: str = ".3f") -> str:
    return "n/a" if value is None else format(value, spec)


def _path_rows(steps: list[dict], first_off: int | None) -> list[dict]:
    """At most :data:`PATH_ROWS` steps, evenly spread, the first, the last and the first off-shortest one included."""
    if len(steps) <= PATH_ROWS:
        return steps
    keep = set(np.linspace(0, len(steps) - 1, PATH_ROWS - 1).round().astype(int).tolist())
    if first_off is not None:
        keep.add(first_off)
    return [steps[i] for i in sorted(keep)]


def format_markdown(d: dict) -> str:
    """One markdown section for one run's diagnosis (:func:`diagnose_run`)."""
    task = d.get("world") == "minigrid"
    world = f"MiniGrid task {d['maze']} ({d['states']} states; " if task else f"Maze {d['maze']} ("
    lines = [
        f"## {d['experiment']} seed {d['seed']} ({d['method']}, agent {d['agent']})",
        "",
        f"Run: `{d['run_dir']}`. {world}shortest path {d['optimal_length']}); optimal values "
        f"gamma^(d-1) with gamma {d['value_gamma']:g} (agent's gamma {d['agent_gamma']:g}).",
        "",
    ]
    if d.get("slip"):
        lines += [
            f"The run's moves slip (env.slip {d['slip']:g}); what follows measures its greedy policy on the maze "
            "without slips (the deterministic walk from S, shortest-path distances and their values). "
            "`scripts/evaluate.py` rolls the policy out with the slips, as the trainer's evaluations do.",
            "",
        ]
    lines += [
        f"### Greedy accuracy and value error by distance to G (buckets of {d['bucket_width']})",
        "",
    ]
    values = {r["distances"]: r for r in d["value_error_by_distance"]}
    rows = [
        [
            r["distances"],
            r["states"],
            _f(r["accuracy"]),
            _f(values[r["distances"]]["mean_abs_error"], ".4f"),
            _f(values[r["distances"]]["mean_signed_error"], "+.4f"),
        ]
        for r in d["accuracy_by_distance"]
    ]
    v = d["value_error"]
    rows.append(
        [
            "all",
            v["states"],
            _f(d["greedy_accuracy"]),
            _f(v["mean_abs_error"], ".4f"),
            _f(v["mean_signed_error"], "+.4f"),
        ]
    )
    headers = ["distance", "states", "greedy accuracy", "mean abs value error", "mean signed value error"]
    lines += [format_markdown_table(headers, rows), ""]

    p = d["greedy_path"]
    off = p["first_off_shortest"]
    where = (
        "it stays on a shortest path"
        if off is None
        else f"it leaves a shortest path at step {off['step']}, in "
        + (f"state {off['label']}" if task else f"cell ({off['row']}, {off['col']})")
        + f" at distance {off['distance']}"
    )
    if p["success"]:
        outcome = f"reaches G in {p['length']} steps (optimal {p['optimal_length']})"
    elif p["loops"]:
        outcome = (
            f"loops: after {len(p['steps'])} steps it is back in a {'state' if task else 'cell'} it visited, so it "
            "never reaches G"
        )
    else:
        outcome = f"does not reach G within {p['length']} steps"
    lines += [
        "### Q along the greedy path from S",
        "",
        f"- The greedy rollout from S {outcome}; {where}.",
        f"- Mean |max_a Q(s||G,a) - gamma^(d(s)-1)| along the path: {_f(p['mean_abs_error'], '.4f')} "
        f"over {len(p['steps'])} states.",
        "",
    ]
    if p["steps"]:
        shown = _path_rows(p["steps"], None if off is None else off["step"])
        rows = [
            [
                s["step"],
                *([s["label"]] if task else []),
                f"({s['row']}, {s['col']})",
                s["distance"],
                _f(s["q_max"], ".4f"),
                _f(s["optimal"], ".4f"),
                _f(s["error"], "+.4f"),
            ]
            for s in shown
        ]
        if len(shown) < len(p["steps"]):
            lines += [f"{len(shown)} of {len(p['steps'])} steps (all in {DIAGNOSIS_FILE}):", ""]
        headers = ["step", *(["state"] if task else []), "cell", "distance", "max Q", "optimal", "error"]
        lines += [format_markdown_table(headers, rows), ""]

    t = d["training"]
    lines += ["### Training data", ""]
    if "train_note" in t:
        lines.append(f"- goal_share: {t['train_note']}.")
    else:
        lines.append(
            f"- Mean goal_share (batch share with the real goal G): {_f(t['goal_share_mean'])} overall, "
            f"{_f(t['goal_share_last_quarter'])} in the last quarter "
            f"(env steps > {_f(t['last_quarter_after_env_steps'], 'g')})."
        )
    if "episodes_note" in t:
        lines.append(f"- Episodes: {t['episodes_note']}.")
    else:
        if t["first_success_episode"] is None:
            lines.append(f"- No training episode reached G ({t['episodes']} episodes).")
        else:
            lines.append(
                f"- First success in episode {t['first_success_episode']} of {t['episodes']}; share of the "
                f"{t['episodes_after_first_success']} episodes after it that reach G: "
                f"{_f(t['success_after_first_success'])}."
            )
        lines.append(f"- Share of episodes that reach G in the last quarter: {_f(t['success_last_quarter'])}.")
        lines.append(
            f"- Share of episodes with a Smart Start guided phase: {_f(t['smart_start_share'])} overall, "
            f"{_f(t['smart_start_share_last_quarter'])} in the last quarter."
        )
    lines += ["", "### Exploration before the first goal", "", *exploration_lines(d["exploration"], task)]
    return "\n".join(lines) + "\n"


def exploration_lines(x: dict, task: bool) -> list[str]:
    """The report's lines on :func:`exploration_before_first_goal`'s ``x`` (``task``: a MiniGrid task's states)."""
    if "note" in x:
        return [f"- {x['note']}."]
    first, n, unit = x["first_goal_env_step"], x["episodes"], "states" if task else "free cells"
    if first is not None and n == 0:
        return [f"- G first reached at {first} env steps, in the first training episode: no episode before it."]
    if first is None:
        head = f"- G never reached: the {n} training episodes ({x['env_steps']} env steps)"
    else:
        head = (
            f"- G first reached at {first} env steps: the {n} training episodes before it ({x['env_steps']} env steps)"
        )
    ends = (
        "The states they end in (cell and direction) lie a median of at least"
        if task
        else "The cells they end in lie a median"
    )
    return [
        f"{head} visited {x['states_visited']} of the {x['free_states']} {unit}.",
        f"- {ends} {_f(x['end_true_distance_median'], 'g')} steps from G "
        f"({_f(x['end_manhattan_distance_median'], 'g')} in Manhattan distance); their smart start states a "
        f"median {_f(x['ss_target_true_distance_median'], 'g')} steps.",
    ]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="diagnose.py", description="Measure why a trained agent's greedy policy fails (issue 12, point 5)."
    )
    parser.add_argument("run_dirs", nargs="+", type=Path, help="run directories with checkpoint.pt")
    parser.add_argument("--bucket-width", type=int, default=10, help="width of the distance buckets (default 10)")
    parser.add_argument(
        "--out", type=Path, default=None, help=f"write {DIAGNOSIS_FILE} (a list, one per run) and {DIAGNOSIS_MD} here"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.bucket_width < 1:
            raise DiagnoseError(f"--bucket-width must be >= 1 (got {args.bucket_width})")
        if args.out is not None:
            # The folder is made after the diagnosis: the nearest part of the path that exists must be a folder.
            existing = next(p for p in (args.out.absolute(), *args.out.absolute().parents) if p.exists())
            if not existing.is_dir():
                raise DiagnoseError(f"--out {args.out}: {existing} is not a directory")
        results = [diagnose_run(run_dir, args.bucket_width) for run_dir in args.run_dirs]
    except DiagnoseError as e:
        print(f"diagnose.py: error: {e}", file=sys.stderr)
        return 2
    sections = [format_markdown(d) for d in results]
    print("\n".join(sections), end="")
    if args.out is None:
        for d, section in zip(results, sections):
            write_json_atomic(Path(d["run_dir"]) / DIAGNOSIS_FILE, _finite(d))
            (Path(d["run_dir"]) / DIAGNOSIS_MD).write_text(section)
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / DIAGNOSIS_FILE).write_text(json.dumps([_finite(d) for d in results], indent=2) + "\n")
        (args.out / DIAGNOSIS_MD).write_text("\n".join(sections))
    return 0
