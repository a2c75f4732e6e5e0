"""The ``update`` section: ms per ``DQNAgent.update()`` of the two DQN learners, side by side with the reference
that has no bound.

The rows, named by the stages of ``docs/ablations.md`` (the lab notebook is ``docs/notebook/long_horizons.md``):

* **J**: the replay-only DQN with every bound off (stage 8): the reference the ratios are to;
* **dqn**: the replay-only DQN as ``agent=dqn`` composes it (stage 10's LM: the hindsight bound and the k-step
  maximum);
* **dqn_bounded**: the model-bounded DQN as ``agent=dqn_bounded`` composes it (stage 20's LCFATO: the count model's
  distance floor and ceiling on every action, the model targets and the optimistic floor);
* **dqn_bounded, TorchRL SoftUpdate**: the model-bounded DQN once more, its target network stepped by TorchRL's
  ``SoftUpdate`` instead of ss-drl's ``PolyakUpdate`` (the same arithmetic; what the fused lerp saves);
* **dqn_bounded, separate passes**: the model-bounded DQN with its model targets' successors bootstrapped in passes
  of their own, as at 7ac5009 (``TDTarget(fused=False)``; what one batched pass per network saves);
* **dqn_bounded, per-row options**: the model-bounded DQN with the options that change its arithmetic to cut the
  work per update (:data:`PER_ROW_OPTIONS`: the factored bootstrap, successors by the target network's max, sparse
  per-cell tables), each off by default.

A second table asks why the update makes three network passes and not two: the online network's pass over the
batch, which the loss differentiates, against the one pass over batch and bootstrap states together that would
replace it and the online bootstrap pass (:func:`bench_online_passes`).

The learners' rows are composed from the ``agent`` group (:data:`LEARNERS`), so they follow ``conf/agent/*.yaml``;
J is ``agent=dqn`` with each switch that is on there turned off. The "bounds on" column lists the switches on in the
built agent's settings (:func:`ss_drl.agents.targets.assumptions`). Each agent is built as the trainer builds it
(``make_agent``, in ``<maze>_ss_her``) and gets the same replay data: random-walk episodes on the maze, with real
moves and G terminal, which a count model also counts (the distance ceiling and floor read it; it does not grow
here, so their searches run once, in the warm-up). The settings are timed in turn within each repeat, so the
machine's load falls on all of them alike; the table gives the median ms per update and the ratio to J's median.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from benchmarks.common import compose_config, fmt_ms, markdown_table, median

#: (row, ``agent`` group, stage of docs/ablations.md) of each learner timed: its setting is the group's composition.
LEARNERS = (("dqn", "dqn", "LM"), ("dqn_bounded", "dqn_bounded", "LCFATO"))
#: The reference row: the replay-only DQN with every bound off.
REFERENCE = ("J", "J")
#: The model-bounded DQN with its target network stepped by TorchRL's ``SoftUpdate``.
SOFT_UPDATE = "dqn_bounded, TorchRL SoftUpdate"
#: The model-bounded DQN with the model targets' successors in passes of their own (``TDTarget(fused=False)``).
SEPARATE = "dqn_bounded, separate passes"
#: The model-bounded DQN with the options that cut the work per update.
PER_ROW = "dqn_bounded, per-row options"
PER_ROW_OPTIONS = ("agent.factored_bootstrap=true", "agent.successor_double_dqn=false", "agent.sparse_tables=true")
#: The rows that re-time the model-bounded DQN with one part changed.
VARIANTS = (SOFT_UPDATE, SEPARATE, PER_ROW)


def switches_on(settings) -> list[str]:
    """The TD target's switches (bounds and their modifiers), and the policy that reads them, on in ``settings``."""
    from ss_drl.agents.targets import assumptions

    return list(assumptions(settings))


def setting_overrides(maze: str) -> list[tuple[str, str, tuple[str, ...]]]:
    """(row, stage, overrides of ``+experiment=<maze>_ss_her``) of J and of each of :data:`LEARNERS`. J is
    ``agent=dqn`` with every switch that is on there turned off, whatever the YAML turns on."""
    from ss_drl.agents.settings import DQNSettings

    base = compose_config([f"+experiment={maze}_ss_her", "agent=dqn"])
    off = tuple(f"agent.{key}=false" for key in switches_on(DQNSettings.from_config(base.agent)))
    return [(*REFERENCE, ("agent=dqn", *off))] + [(row, stage, (f"agent={group}",)) for row, group, stage in LEARNERS]


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
    """ms per update of J and each of :data:`LEARNERS` on ``maze`` (median over repeats of the mean of ``updates``
    updates), then the model-bounded DQN with TorchRL's ``SoftUpdate`` and with separate passes, and each one's
    ratio to J's."""
    from torchrl.objectives import SoftUpdate

    from ss_drl.envs.maze import load_maze
    from ss_drl.smart_start import CountModel
    from ss_drl.training.trainer import make_agent

    layout = load_maze(maze)
    data = random_walk_batch(layout, transitions, episode_len)
    settings = setting_overrides(maze)
    bounded = settings[-1]
    agents, stages = {}, {}
    variants = [(v, bounded[1], bounded[2] + (PER_ROW_OPTIONS if v == PER_ROW else ())) for v in VARIANTS]
    for name, stage, overrides in (*settings, *variants):
        cfg = compose_config([f"+experiment={maze}_ss_her", *overrides])
        counts = CountModel(layout.n_cells)
        counts.update(data["observation"], data["action"], data["next", "observation"], data["next", "reward"])
        torch.manual_seed(0)
        agent = make_agent(cfg, layout, 0, counts)
        if name == SOFT_UPDATE:  # instead of ss-drl's PolyakUpdate (the same result)
            agent.target_updater = SoftUpdate(agent.loss, tau=agent.settings.tau)
        if name == SEPARATE:  # the successors' bootstrap in passes of their own
            agent.td_target.fused = False
        agent.store(data.clone())
        for _ in range(5):  # warm-up (and the ceiling's first BFS)
            agent.update()
        agents[name], stages[name] = agent, stage
    times: dict[str, list[float]] = {name: [] for name in agents}
    for _ in range(repeats):
        for name, agent in agents.items():
            start = time.perf_counter()
            for _ in range(updates):
                agent.update()
            times[name].append((time.perf_counter() - start) / updates * 1e3)
    reference = REFERENCE[0]
    base = median(times[reference])
    rows = []
    for name, agent in agents.items():
        ms = median(times[name])
        on = "as " + bounded[0] if name in VARIANTS else ", ".join(switches_on(agent.settings)) or "none"
        if name == PER_ROW:
            on += ", " + " ".join(PER_ROW_OPTIONS)
        rows.append([name, stages[name], on, fmt_ms(ms), f"{ms / base:.2f}x"])
    batch = agents[reference].settings.batch_size
    return "\n".join(
        [
            f"## update: ms per DQNAgent.update() on {maze} ({transitions:,} random-walk transitions stored, batch "
            f"{batch}; median of {repeats} interleaved repeats of {updates} updates)",
            "",
            markdown_table(["setting", "stage", "bounds on", "ms per update", f"vs {reference}"], rows),
            "",
            bench_online_passes(agents[LEARNERS[-1][0]], layout, repeats, updates),
        ]
    )


def bootstrap_rows(agent) -> int:
    """Rows the TD target sends through the online network's bootstrap pass in one update of ``agent``: the loss is
    computed once on a sample, counting the rows of each online pass made for the bootstrap (no gradient step is
    made)."""
    loss, rows = agent.loss, []

    def counting(obs, goal):
        rows.append(obs.shape[0])
        return type(loss)._online(loss, obs, goal)

    loss._online = counting
    try:
        loss(agent.replay_buffer.sample())
    finally:
        del loss._online
    return sum(rows)


def bench_online_passes(agent, layout, repeats: int, updates: int) -> str:
    """ms of the online network's forward and backward in one update of ``agent``'s size, two ways: today's (a pass
    with gradients over the batch, then one without over the bootstrap rows) and one pass with gradients over both,
    whose backward then multiplies through the bootstrap rows too, though their gradients are zero. The network is
    ``agent``'s (a fresh copy of its architecture); the states are random cells."""
    from ss_drl.agents.network import GoalQNetwork

    s = agent.settings
    batch, extra = s.batch_size, bootstrap_rows(agent)
    torch.manual_seed(0)
    net = GoalQNetwork(layout, s.encoder, s.embed_dim, s.hidden, s.dueling)
    obs, goal, boot_obs, boot_goal = (torch.randint(layout.n_cells, (n,)) for n in (batch, batch, extra, extra))
    both = torch.cat((obs, boot_obs)), torch.cat((goal, boot_goal))

    def two_passes():
        q = net(obs, goal)
        with torch.no_grad():
            held = net(boot_obs, boot_goal)[:batch]
        net.zero_grad(set_to_none=True)
        (q - held).square().mean().backward()

    def one_pass():
        q_all = net(*both)
        q, held = q_all[:batch], q_all[batch:][:batch].detach()
        net.zero_grad(set_to_none=True)
        (q - held).square().mean().backward()

    ways = {
        "two (the update's): the batch with gradients, the bootstrap rows without": two_passes,
        "one: the batch and the bootstrap rows together, with gradients": one_pass,
    }
    for way in ways.values():  # warm-up
        way()
    times: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(repeats):
        for name, way in ways.items():
            start = time.perf_counter()
            for _ in range(updates):
                way()
            times[name].append((time.perf_counter() - start) / updates * 1e3)
    base = median(next(iter(times.values())))
    rows = [[name, f"{batch + extra:,}", fmt_ms(median(t)), f"{median(t) / base:.2f}x"] for name, t in times.items()]
    return "\n".join(
        [
            f"### update: the online network's passes in one {LEARNERS[-1][0]} update ({batch} batch rows, {extra:,} "
            "bootstrap rows; forward and backward, median ms)",
            "",
            markdown_table(["online passes", "rows forward", "ms", "vs two"], rows),
        ]
    )
