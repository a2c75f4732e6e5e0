"""The ``planner`` section: ms per Smart Start decision on a fully explored count model: UCB selection over all
visited states with a fresh ``GoalQNetwork`` plus ``Planner.plan`` value iteration, on the presets and random mazes
(``randomN``: an N x N :func:`~ss_drl.envs.maze.random_maze`)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import numpy as np
import torch

from benchmarks.common import CONFIG_DIR, fmt_ms, markdown_table, timed

PLANNER_MAZES = ("easy", "medium", "hard", "extreme", "random100")
EXTREME_TARGET_MS = 5.0


def load_planner_maze(name: str):
    """A preset (or maze file) by name, or ``randomN``: the N x N random maze of seed 0."""
    from ss_drl.envs.maze import load_maze, random_maze

    size = name.removeprefix("random")
    if name.startswith("random") and size.isdigit():
        return random_maze(int(size), int(size), seed=0)
    return load_maze(name)


def matmul_floor(n: int, embed_dim: int, hidden: Sequence[int], actions: int = 4) -> Callable[[], None]:
    """The matrix products alone of one Q evaluation of ``n`` states for one goal, in the row blocks of
    ``GoalQNetwork.goal_q_values``: the state half of the first layer (E -> H1), the hidden layers and the head, into
    preallocated outputs. Any evaluation of Q for all visited states with this network costs at least this much (the
    rest is extra)."""
    from ss_drl.agents.network import BLOCK_ROWS

    block = min(BLOCK_ROWS, n)
    sizes = [min(block, n - start) for start in range(0, n, block)]
    widths = [embed_dim, *hidden, actions]
    inputs = [torch.rand(block, w) for w in widths[:-1]]
    weights = [torch.rand(a, b) for a, b in zip(widths[:-1], widths[1:])]
    outputs = [torch.empty(block, w) for w in widths[1:]]

    def run() -> None:
        for rows in sizes:
            for x, w, out in zip(inputs, weights, outputs):
                torch.mm(x[:rows], w, out=out[:rows])

    return run


def bench_planner(repeats: int, mazes: Sequence[str] = PLANNER_MAZES, seed: int = 0) -> str:
    """ms per Smart Start decision (UCB selection + value iteration) on fully explored mazes (median of repeats)."""
    from omegaconf import OmegaConf

    from ss_drl.agents.network import GoalQNetwork
    from ss_drl.smart_start import Planner, select_smart_start
    from ss_drl.smart_start.counts import fully_explored_model

    ss = OmegaConf.load(CONFIG_DIR / "smart_start" / "on.yaml")
    agent = OmegaConf.load(CONFIG_DIR / "agent" / "dqn.yaml")
    rows, extreme_total = [], []
    for name in mazes:
        maze = load_planner_maze(name)
        counts = fully_explored_model(maze)
        visited = counts.visited_states()
        torch.manual_seed(seed)
        q_net = GoalQNetwork(maze, agent.encoder, agent.embed_dim, tuple(agent.hidden), agent.dueling).eval()

        def max_q(states, goals, q_net=q_net):
            # Every visited state for each goal in one batched evaluation (goal_q_values: the first layer's state
            # and goal halves computed separately), then max over actions.
            return q_net.goal_q_values(states, goals).amax(dim=-1)

        planner = Planner(maze.width, gamma=ss.gamma, theta=ss.theta, tol=ss.tol, max_sweeps=ss.max_sweeps)
        goals = torch.tensor([maze.goal_cell])
        rng = np.random.default_rng(seed)
        targets = {"start": maze.start_cell, "random visited": int(visited[int(rng.integers(visited.numel()))])}
        gen = torch.Generator().manual_seed(seed)
        select = functools.partial(select_smart_start, counts, max_q, goals, ss.c_ss, ss.w_q, gen)
        select()  # warm-up
        select_ms, _ = timed(select, repeats)
        floor = matmul_floor(visited.numel(), agent.embed_dim, list(agent.hidden))
        floor()  # warm-up
        floor_ms, _ = timed(floor, repeats)
        # S_ss by counts alone (w_q = 0, the paper-setup experiments): no network evaluation.
        counts_ms, _ = timed(functools.partial(select_smart_start, counts, max_q, goals, ss.c_ss, 0.0, gen), repeats)
        for label, target in targets.items():
            plan = functools.partial(planner.plan, counts, torch.tensor([target]), gen)
            plan()  # warm-up
            plan_ms, result = timed(plan, repeats)
            others = visited[visited != target]
            routed = float((result.values[others, 0] > 0).float().mean()) if others.numel() else 1.0
            r, c = maze.pos(target)
            rows.append(
                [
                    name,
                    f"{maze.height}x{maze.width}",
                    visited.numel(),
                    f"{label} ({r},{c})",
                    fmt_ms(select_ms),
                    fmt_ms(floor_ms),
                    fmt_ms(plan_ms),
                    fmt_ms(select_ms + plan_ms),
                    fmt_ms(counts_ms + plan_ms),
                    result.sweeps,
                    "yes" if result.converged else "no",
                    f"{100 * routed:.1f}%",
                ]
            )
            if name == "extreme":
                extreme_total.append((select_ms + plan_ms, counts_ms + plan_ms, floor_ms + plan_ms))
    headers = [
        "maze",
        "size",
        "visited states",
        "target S_ss",
        "selection ms",
        "its matmuls alone ms",
        "planning ms",
        "decision ms",
        "decision ms, w_q 0",
        "VI sweeps",
        "converged",
        "states with V>0",
    ]
    out = [
        "## planner: ms per Smart Start decision, fully explored count model "
        f"(median of {repeats}; torch threads {torch.get_num_threads()})",
        "",
        f"Selection: UCB over all visited states with a fresh `GoalQNetwork` ({agent.encoder}, "
        f"hidden {list(agent.hidden)}) evaluated by `GoalQNetwork.goal_q_values`, one goal; 'w_q 0': S_ss by counts "
        "alone (the paper-setup experiments), which needs no network pass. 'its matmuls alone': the matrix "
        "products of that evaluation, in its row blocks, on preallocated tensors, nothing else. Planning: "
        f"`Planner.plan` (gamma={ss.gamma}, theta={ss.theta}, tol={ss.tol}, max_sweeps={ss.max_sweeps}) towards the "
        "target. 'states with V>0': visited states other than the target from which the plan has a route.",
        "",
        markdown_table(headers, rows),
        "",
    ]
    if extreme_total:
        for form, worst in (
            ("UCB with Q", max(t[0] for t in extreme_total)),
            ("w_q 0", max(t[1] for t in extreme_total)),
        ):
            verdict = "met" if worst < EXTREME_TARGET_MS else "NOT met"
            out.append(
                f"- target < {EXTREME_TARGET_MS:g} ms per decision on Extreme, {form}: {verdict} "
                f"(worst target: {worst:.1f} ms)"
            )
        floor_total = max(t[2] for t in extreme_total)
        out.append(
            f"- the UCB's matrix products alone plus planning take {floor_total:.1f} ms on Extreme: the least a "
            "decision that evaluates Q for every visited state with this network can cost here"
        )
    return "\n".join(out) + "\n"
