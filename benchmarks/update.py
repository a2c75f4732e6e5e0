"""The ``update`` section: ms per ``DQNAgent.update()`` under each of the TD-target options of issue 12, side by side.

The settings are the stages of ``docs/long_horizons.md``: J (no bound), L (J + ``agent.hindsight_bound``), LM (L +
``agent.n_step_max``, stage 10, the default until session 19), LMC (LM + ``agent.distance_ceiling``), LCF (L +
``agent.distance_ceiling`` + ``agent.distance_floor``, stage 12), LCFA (LCF + ``agent.bound_all_actions``, stage
14), LCFAT (LCFA + ``agent.model_targets``, stage 15) and LCFATO (LCFAT + ``agent.optimistic_floor``, stage 20, the
default), and LCFATO once more with its target network stepped by TorchRL's ``SoftUpdate`` instead of ss-drl's
``PolyakUpdate`` (the same arithmetic; what the fused lerp saves). Each agent is built as the trainer builds it
(``make_agent``) and gets the same replay data: random-walk episodes on the maze, with real moves and G terminal,
which a count model also counts (the distance ceiling and floor read it; it does not grow here, so their searches
run once, in the warm-up). The settings are timed in turn within each repeat, so the machine's load falls on all of
them alike; the table gives the median ms per update and the ratio to J's median.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from benchmarks.common import compose_config, fmt_ms, markdown_table, median

#: The TD-target options of issue 12, in the order of the stages that added them.
OPTIONS = (
    "hindsight_bound",
    "n_step_max",
    "distance_ceiling",
    "distance_floor",
    "bound_all_actions",
    "model_targets",
    "optimistic_floor",
)


def _setting(*on: str) -> tuple[str, ...]:
    """Overrides that turn on the options ``on`` and every other one of :data:`OPTIONS` off, whatever the defaults."""
    return tuple(f"agent.{option}={str(option in on).lower()}" for option in OPTIONS)


#: (name, overrides) of each setting timed, in the order of the stages that added them.
SETTINGS = (
    ("J", _setting()),
    ("L", _setting("hindsight_bound")),
    ("LM", _setting("hindsight_bound", "n_step_max")),
    ("LMC", _setting("hindsight_bound", "n_step_max", "distance_ceiling")),
    ("LCF", _setting("hindsight_bound", "distance_ceiling", "distance_floor")),
    ("LCFA", _setting("hindsight_bound", "distance_ceiling", "distance_floor", "bound_all_actions")),
    (
        "LCFAT",
        _setting("hindsight_bound", "distance_ceiling", "distance_floor", "bound_all_actions", "model_targets"),
    ),
    (
        "LCFATO",
        _setting(
            "hindsight_bound",
            "distance_ceiling",
            "distance_floor",
            "bound_all_actions",
            "model_targets",
            "optimistic_floor",
        ),
    ),
)


def random_walk_batch(maze, rows: int, episode_len: int, seed: int = 0):
    """A (rows, 1) batch of consecutive random-walk steps on ``maze`` from S: real moves (bumps included), G entered
    ends an episode (terminal, reward 1), and an episode is cut after ``episode_len`` steps."""
    from tensordict import TensorDict

    table = maze.transition_table()
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 4, rows)
    obs, nxt = np.empty(rows, np.int64), np.empty(rows, np.int64)
    terminated, truncated = np.zeros(rows, bool), np.zeros(rows, bool)
    state, t = maze.start_cell, 0
    for i in range(rows):
        obs[i], nxt[i] = state, table[state, actions[i]]
        t += 1
        terminated[i] = nxt[i] == maze.goal_cell
        truncated[i] = not terminated[i] and t == episode_len
        state, t = (maze.start_cell, 0) if terminated[i] or truncated[i] else (int(nxt[i]), t)
    goal = torch.full((rows, 1), maze.goal_cell, dtype=torch.int64)
    flag = lambda x: torch.from_numpy(x).view(rows, 1, 1)  # noqa: E731
    return TensorDict(
        {
            "observation": torch.from_numpy(obs).view(rows, 1),
            "desired_goal": goal,
            "action": torch.from_numpy(actions).view(rows, 1),
            "next": {
                "observation": torch.from_numpy(nxt).view(rows, 1),
                "desired_goal": goal.clone(),
                "reward": flag(terminated).float(),
                "terminated": flag(terminated),
                "truncated": flag(truncated),
                "done": flag(terminated | truncated),
            },
        },
        batch_size=(rows, 1),
    )


def bench_update(
    repeats: int, maze: str = "hard", transitions: int = 20_000, updates: int = 100, episode_len: int = 1000
) -> str:
    """ms per update of each setting in :data:`SETTINGS` on ``maze`` (median over repeats of the mean of
    ``updates`` updates), and its ratio to the first setting's."""
    from torchrl.objectives import SoftUpdate

    from ss_drl.envs.maze import load_maze
    from ss_drl.smart_start import CountModel
    from ss_drl.training.trainer import make_agent

    layout = load_maze(maze)
    data = random_walk_batch(layout, transitions, episode_len)
    reference = SETTINGS[-1][0] + ", TorchRL SoftUpdate"  # the default, its target stepped by TorchRL's updater
    agents = {}
    for name, overrides in (*SETTINGS, (reference, SETTINGS[-1][1])):
        cfg = compose_config([f"+experiment={maze}_ss_her", *overrides])
        counts = CountModel(layout.n_cells)
        counts.update(data["observation"], data["action"], data["next", "observation"], data["next", "reward"])
        torch.manual_seed(0)
        agent = make_agent(cfg, layout, 0, counts)
        if name == reference:  # instead of ss-drl's PolyakUpdate (the same result)
            agent.target_updater = SoftUpdate(agent.loss, tau=float(cfg.agent.tau))
        agent.store(data.clone())
        for _ in range(5):  # warm-up (and the ceiling's first BFS)
            agent.update()
        agents[name] = agent
    times: dict[str, list[float]] = {name: [] for name in agents}
    for _ in range(repeats):
        for name, agent in agents.items():
            start = time.perf_counter()
            for _ in range(updates):
                agent.update()
            times[name].append((time.perf_counter() - start) / updates * 1e3)
    base = median(times[SETTINGS[0][0]])
    rows = []
    for name, overrides in SETTINGS:
        on = [o.split("=")[0].removeprefix("agent.") for o in overrides if o.endswith("=true")]
        ms = median(times[name])
        rows.append([name, ", ".join(on) or "none", fmt_ms(ms), f"{ms / base:.2f}x"])
    ms = median(times[reference])
    rows.append([reference, "as " + SETTINGS[-1][0], fmt_ms(ms), f"{ms / base:.2f}x"])
    return "\n".join(
        [
            f"## update: ms per DQNAgent.update() on {maze} ({transitions:,} random-walk transitions stored, batch "
            f"{int(cfg.agent.batch_size)}; median of {repeats} interleaved repeats of {updates} updates)",
            "",
            markdown_table(["setting", "bounds on", "ms per update", f"vs {SETTINGS[0][0]}"], rows),
        ]
    )
