"""Throughput benchmarks behind ``scripts/benchmark.py``: env steps, training, Smart Start decisions, HER sampling.

``python scripts/benchmark.py [--section env|train|planner|her|all] [--repeats R] [--quick]`` prints the exact
command line, the library versions and one markdown table per section. Every number is the median of R repeats.
All sections run with one torch thread (the trainer's default, ``trainer.torch_threads: 1``) unless ``--threads``
says otherwise.

Sections:

* ``env``: env steps/s of the raw gymnasium env, of the same env through TorchRL's ``GymEnv``, and of the native
  :class:`~ss_drl.envs.batched.BatchedMazeEnv` at N = 1, 16, 256 copies (``step_and_maybe_reset``; all copies count).
* ``train``: training throughput (env steps/s, updates included) on Easy of ss-drl (``easy_dqn_her``, and
  ``easy_ss_her`` for information) against Stable-Baselines3 ``DQN`` + ``HerReplayBuffer`` with the same network
  width, batch size, buffer size, learning_starts, update-to-data ratio and HER setting, run one after the other in
  this process. Only the training phase is timed (from learning_starts on); the whole-run rate is shown too.
* ``planner``: ms per Smart Start decision on a fully explored count model: UCB selection over all visited states
  with a fresh ``GoalQNetwork`` plus ``Planner.plan`` value iteration, on the presets and a 100x100 random maze.
* ``her``: ms per ``HindsightReplayBuffer.sample()`` (batch 128, future, k = 4) at 10k and 1M stored transitions.

Each ``bench_*`` function takes its sizes as arguments and returns the section's markdown, so tests can run it tiny.
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import platform
import shlex
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

CONFIG_DIR = Path(__file__).resolve().parent.parent / "conf"
SECTIONS = ("env", "train", "planner", "her")
#: Default repeats per section (``--repeats`` overrides them all). The train section is the slow one.
DEFAULT_REPEATS = {"env": 5, "train": 3, "planner": 15, "her": 5}
QUICK_REPEATS = 2
PLANNER_MAZES = ("easy", "medium", "hard", "extreme", "random100")
EXTREME_TARGET_MS = 5.0
MILLION = 1_000_000


# --- helpers ----------------------------------------------------------------------------------------------------------
def markdown_table(headers: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A markdown table; numbers are expected to be formatted already."""
    lines = ["| " + " | ".join(map(str, headers)) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(map(str, row)) + " |" for row in rows]
    return "\n".join(lines)


def fmt_rate(x: float) -> str:
    """Steps per second with thousands separators."""
    return f"{x:,.0f}"


def fmt_ms(x: float) -> str:
    return f"{x:.3f}" if x < 10 else f"{x:.1f}"


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values))


def _quiet_torchrl() -> None:
    # TorchRL logs an INFO line per replay-buffer storage it creates; keep the tables clean. Its import sets the
    # level (from RL_LOGGING_LEVEL), so import it first.
    import torchrl  # noqa: F401

    logging.getLogger("torchrl").setLevel(logging.WARNING)


# --- 1. env -----------------------------------------------------------------------------------------------------------
def _time_raw_gym(env_id: str, actions: list[int]) -> float:
    import gymnasium

    env = gymnasium.make(env_id).unwrapped
    env.reset(seed=0)
    step, reset = env.step, env.reset
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = step(action)
        if terminated or truncated:
            reset()
    elapsed = time.perf_counter() - start
    env.close()
    return len(actions) / elapsed


def _time_torchrl_loop(env, actions: list[torch.Tensor], steps_per_call: int) -> float:
    """Steps/s of ``step_and_maybe_reset`` over pre-generated actions (``steps_per_call`` env steps per call)."""
    td = env.reset()
    step = env.step_and_maybe_reset
    start = time.perf_counter()
    for action in actions:
        td.set("action", action)
        _, td = step(td)
    elapsed = time.perf_counter() - start
    return len(actions) * steps_per_call / elapsed


def bench_env(
    repeats: int,
    raw_steps: int = 20_000,
    gym_steps: int = 3_000,
    batched_iters: int = 3_000,
    num_envs: Sequence[int] = (1, 16, 256),
    env_id: str = "SSDRL/Easy-v0",
) -> str:
    """Env steps/s: raw gymnasium, TorchRL ``GymEnv`` and the native batched env at each N (median of repeats)."""
    import gymnasium  # noqa: F401
    from torchrl.envs import GymEnv

    import ss_drl  # noqa: F401  (registers the SSDRL/*-v0 ids)
    from ss_drl.envs import ENV_IDS
    from ss_drl.envs.batched import BatchedMazeEnv

    preset = ENV_IDS[env_id]
    rng = np.random.default_rng(0)
    gen = torch.Generator().manual_seed(0)
    raw_actions = rng.integers(0, 4, raw_steps).tolist()
    gym_actions = list(torch.randint(0, 4, (gym_steps,), generator=gen).unbind(0))
    batched_actions = {n: list(torch.randint(0, 4, (batched_iters, n), generator=gen).unbind(0)) for n in num_envs}

    wrapped = GymEnv(env_id, categorical_action_encoding=True)
    batched = {n: BatchedMazeEnv(preset, num_envs=n) for n in num_envs}
    # Warm-up (imports, first-call allocations), untimed.
    _time_raw_gym(env_id, raw_actions[:200])
    _time_torchrl_loop(wrapped, gym_actions[:50], 1)
    for n, env in batched.items():
        _time_torchrl_loop(env, batched_actions[n][:50], n)

    results: dict[str, list[float]] = {"raw": [], "gym": [], **{f"n{n}": [] for n in num_envs}}
    for _ in range(repeats):
        results["raw"].append(_time_raw_gym(env_id, raw_actions))
        results["gym"].append(_time_torchrl_loop(wrapped, gym_actions, 1))
        for n, env in batched.items():
            results[f"n{n}"].append(_time_torchrl_loop(env, batched_actions[n], n))
    wrapped.close()
    med = {key: median(values) for key, values in results.items()}

    rows = [
        [f"raw gymnasium `gymnasium.make({env_id!r}).unwrapped`", 1, raw_steps, fmt_rate(med["raw"])],
        [f"TorchRL `GymEnv({env_id!r})`, step_and_maybe_reset", 1, gym_steps, fmt_rate(med["gym"])],
    ]
    for n in num_envs:
        rows.append(
            [f"native `BatchedMazeEnv`, N={n}, step_and_maybe_reset", n, batched_iters * n, fmt_rate(med[f"n{n}"])]
        )
    out = [
        f"## env: env steps per second ({preset} maze, random actions, reset on done; median of {repeats})",
        "",
        markdown_table(["env", "copies", "steps per repeat", "env steps/s"], rows),
        "",
    ]
    if 1 in num_envs:
        out.append(f"- native N=1 / TorchRL GymEnv: {med['n1'] / med['gym']:.2f}x")
        out.append(f"- native N=1 / raw gymnasium: {med['n1'] / med['raw']:.2f}x")
    biggest = max(num_envs)
    verdict = "yes" if med[f"n{biggest}"] > MILLION else "no"
    out.append(f"- native N={biggest}: {fmt_rate(med[f'n{biggest}'])} steps/s; exceeds 1,000,000 steps/s: {verdict}")
    return "\n".join(out) + "\n"


# --- 2. train ---------------------------------------------------------------------------------------------------------
def compose_config(overrides: Sequence[str]):
    """Compose ``conf/config.yaml`` in-process with Hydra overrides."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides))


class _TrainPhaseClock:
    """Wraps ``agent.observe`` to time the training phase: from the end of the last ``observe`` call before
    ``learning_starts`` (so the window holds the rollouts and updates of every learning round) to the end of the last.
    """

    def __init__(self, agent, learning_starts: int):
        self.agent = agent
        self.learning_starts = int(learning_starts)
        self._observe = agent.observe
        agent.observe = self.observe  # the instance attribute shadows the method
        self.last = (time.perf_counter(), 0, 0)  # (time, env steps, updates) after the previous observe call
        self.start: tuple[float, int, int] | None = None
        self.end: tuple[float, int, int] | None = None

    def observe(self, batch, env_steps: int) -> None:
        if self.start is None and env_steps >= self.learning_starts:
            self.start = self.last
        self._observe(batch, env_steps)
        self.last = (time.perf_counter(), env_steps, self.agent.updates)
        if self.start is not None:
            self.end = self.last

    def window(self) -> tuple[float, int, int]:
        """(seconds, env steps, updates) of the training phase."""
        if self.start is None or self.end is None:
            return float("nan"), 0, 0
        return self.end[0] - self.start[0], self.end[1] - self.start[1], self.end[2] - self.start[2]


# ss-drl's DQN in the form of SB3's: plain DQN target (no double DQN) and no dueling head; same width and batch.
SB3_FORM = ("agent.double_dqn=false", "agent.dueling=false")


def _train_overrides(experiment: str, steps: int, learning_starts: int, max_steps: int, seed: int) -> list[str]:
    big = 10**12
    return [
        f"+experiment={experiment}",
        f"trainer.total_env_steps={learning_starts + steps}",
        f"trainer.eval_interval={big}",
        f"trainer.checkpoint_interval={big}",
        f"trainer.torch_threads={torch.get_num_threads()}",
        f"agent.learning_starts={learning_starts}",
        f"env.max_steps={max_steps}",
        "logger=csv",
        f"seed={seed}",
    ]


def run_ssdrl(
    experiment: str, steps: int, learning_starts: int, max_steps: int, seed: int = 0, overrides: Sequence[str] = ()
) -> dict:
    """One ss-drl training run; its training-phase and whole-run rates."""
    from ss_drl.training.trainer import Trainer

    cfg = compose_config(_train_overrides(experiment, steps, learning_starts, max_steps, seed) + list(overrides))
    with tempfile.TemporaryDirectory(prefix="ssdrl-bench-") as run_dir:
        trainer = Trainer(cfg, run_dir)
        clock = _TrainPhaseClock(trainer.agent, learning_starts)
        summary = trainer.train()
    seconds, env_steps, updates = clock.window()
    return {
        "steps_per_s": env_steps / seconds,
        "updates_per_s": updates / seconds,
        "timed_steps": env_steps,
        "updates": updates,
        "whole_steps_per_s": summary["env_steps_per_s"],
        "decisions": summary["smart_start_decisions"],
    }


def run_bare_update(agent_cfg, updates: int, seed: int = 0) -> dict:
    """The ceiling of an eager-PyTorch trainer: updates/s of a bare DQN update in SB3's form, on SB3's network.

    SB3's Q-network for this env (the 6 coordinates of state, achieved and desired goal -> MLP of the agent's hidden
    widths -> 4 values: the least arithmetic at this width), a plain ``max_a Q'`` target from a copy, the same batch
    size, Adam and gradient clipping; the batches are made up in advance. No env, no replay buffer, no TorchRL or
    tensordict: only the PyTorch arithmetic that every update of either library runs. At the update-to-data ratio
    compared, no trainer built on eager PyTorch can step the env faster than this rate allows on this machine.
    """
    import copy

    torch.manual_seed(seed)
    layers, width = [], 6
    for size in agent_cfg.hidden:
        layers += [torch.nn.Linear(width, int(size)), torch.nn.ReLU()]
        width = int(size)
    net = torch.nn.Sequential(*layers, torch.nn.Linear(width, 4))
    target = copy.deepcopy(net).requires_grad_(False)
    optimizer = torch.optim.Adam(net.parameters(), lr=float(agent_cfg.lr), fused=True)
    gamma, clip, size = float(agent_cfg.gamma), float(agent_cfg.grad_clip), int(agent_cfg.batch_size)
    batches = [
        (
            torch.rand(size, 6),
            torch.randint(0, 4, (size, 1)),
            torch.rand(size, 6),
            torch.rand(size, 1),
            torch.rand(size, 1) < 0.1,
        )
        for _ in range(min(updates, 64))
    ]

    def update(obs, action, next_obs, reward, terminated) -> None:
        pred = net(obs).gather(-1, action)
        with torch.no_grad():
            td_target = reward + gamma * (~terminated).float() * target(next_obs).amax(-1, keepdim=True)
        loss = torch.nn.functional.mse_loss(pred, td_target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if clip > 0:
            torch.nn.utils.clip_grad_norm_(net.parameters(), clip, foreach=True)
        optimizer.step()

    for batch in batches[:8]:  # warm-up
        update(*batch)
    start = time.perf_counter()
    for i in range(updates):
        update(*batches[i % len(batches)])
    return {"updates_per_s": updates / (time.perf_counter() - start)}


def sb3_available() -> bool:
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        return False
    return True


def sb3_kwargs(agent_cfg, her_cfg, learning_starts: int, total_steps: int) -> dict:
    """SB3 ``DQN`` arguments matching an ss-drl agent/HER config (see the parity table the section prints)."""
    from stable_baselines3 import HerReplayBuffer

    return dict(
        learning_rate=float(agent_cfg.lr),
        buffer_size=int(agent_cfg.buffer_size),
        learning_starts=int(learning_starts),
        batch_size=int(agent_cfg.batch_size),
        gamma=float(agent_cfg.gamma),
        train_freq=int(agent_cfg.train_freq),
        gradient_steps=int(agent_cfg.gradient_steps),
        # ss-drl counts target copies in updates, SB3 in env steps.
        target_update_interval=int(agent_cfg.target_update_interval)
        * int(agent_cfg.train_freq)
        // int(agent_cfg.gradient_steps),
        exploration_initial_eps=float(agent_cfg.eps_start),
        exploration_final_eps=float(agent_cfg.eps_end),
        exploration_fraction=min(1.0, int(agent_cfg.eps_decay_steps) / total_steps),
        max_grad_norm=float(agent_cfg.grad_clip) if agent_cfg.grad_clip > 0 else float("inf"),
        policy_kwargs=dict(net_arch=[int(h) for h in agent_cfg.hidden]),
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs=dict(n_sampled_goal=int(her_cfg.k), goal_selection_strategy=str(her_cfg.strategy)),
    )


def run_sb3(env_id: str, kwargs: dict, steps: int, learning_starts: int, max_steps: int, seed: int = 0) -> dict:
    """One SB3 DQN + HER run: ``learn(learning_starts)`` untimed for the rate, then ``learn(steps)`` timed."""
    import gymnasium
    from stable_baselines3 import DQN

    env = gymnasium.make(env_id, max_steps=max_steps)
    model = DQN("MultiInputPolicy", env, device="cpu", seed=seed, verbose=0, **kwargs)
    t0 = time.perf_counter()
    model.learn(total_timesteps=learning_starts)
    t1 = time.perf_counter()
    updates_before = model._n_updates
    model.learn(total_timesteps=steps, reset_num_timesteps=False)
    t2 = time.perf_counter()
    env.close()
    updates = model._n_updates - updates_before
    return {
        "steps_per_s": steps / (t2 - t1),
        "updates_per_s": updates / (t2 - t1),
        "timed_steps": steps,
        "updates": updates,
        "whole_steps_per_s": (learning_starts + steps) / (t2 - t0),
    }


def bench_train(
    repeats: int,
    steps: int = 1_500,
    max_steps: int | None = None,
    learning_starts: int | None = None,
    experiments: Sequence[str] = ("easy_dqn_her", "easy_ss_her"),
    include_sb3: bool = True,
    env_id: str = "SSDRL/Easy-v0",
) -> str:
    """Training throughput of ss-drl vs SB3 DQN + HER on the same maze and settings (median of repeats).

    ``max_steps``/``learning_starts`` default to the experiment's ``env.max_steps`` and
    ``max(agent.learning_starts, env.max_steps)``: SB3's ``HerReplayBuffer`` cannot sample before the first episode
    has ended, which is only certain after ``max_steps`` env steps.
    """
    base = compose_config([f"+experiment={experiments[0]}"])
    max_steps = int(base.env.max_steps if max_steps is None else max_steps)
    if learning_starts is None:
        learning_starts = max(int(base.agent.learning_starts), max_steps)
    learning_starts = int(learning_starts)
    agent, her = base.agent, base.her
    out = [
        f"## train: training throughput on {base.env.preset} (median of {repeats}; {steps} timed env steps after "
        f"learning_starts={learning_starts}; torch threads {torch.get_num_threads()})",
        "",
    ]
    have_sb3 = include_sb3 and sb3_available()
    note = None
    if include_sb3 and not have_sb3:
        note = (
            "> **Note:** stable-baselines3 is not installed, so the SB3 rows are skipped. Install it with "
            '`pip install -c constraints.txt "stable-baselines3>=2.3"` (or `pip install -e ".[bench]"`).'
        )

    runs: dict[str, list[dict]] = {name: [] for name in experiments}
    sb3_form = f"{experiments[0]}, SB3's form"
    runs[sb3_form] = []
    if have_sb3:
        runs["sb3"] = []
        kwargs = sb3_kwargs(agent, her, learning_starts, learning_starts + steps)
    bare: list[dict] = []
    # Warm-up (imports, allocator, first-call overheads): a short run of each, untimed.
    run_ssdrl(experiments[0], min(steps, 40), min(learning_starts, 40), max_steps=min(max_steps, 40))
    if have_sb3:
        warm = dict(kwargs, learning_starts=min(learning_starts, 40))
        run_sb3(env_id, warm, min(steps, 40), min(learning_starts, 40), max_steps=min(max_steps, 40))
    # Interleaved, so that drifting load on a shared machine hits every method alike.
    for _ in range(repeats):
        runs[experiments[0]].append(run_ssdrl(experiments[0], steps, learning_starts, max_steps))
        runs[sb3_form].append(run_ssdrl(experiments[0], steps, learning_starts, max_steps, overrides=SB3_FORM))
        if have_sb3:
            runs["sb3"].append(run_sb3(env_id, kwargs, steps, learning_starts, max_steps))
        for name in experiments[1:]:
            runs[name].append(run_ssdrl(name, steps, learning_starts, max_steps))
        bare.append(run_bare_update(agent, steps))

    def row(label: str, framework: str, results: list[dict]) -> list:
        m = {key: median([r[key] for r in results]) for key in ("steps_per_s", "updates_per_s", "whole_steps_per_s")}
        return [
            label,
            framework,
            results[0]["timed_steps"],
            results[0]["updates"],
            fmt_rate(m["steps_per_s"]),
            f"{m['updates_per_s']:.1f}",
            fmt_rate(m["whole_steps_per_s"]),
        ]

    rows = [
        row(f"`{experiments[0]}`", "ss-drl (TorchRL)", runs[experiments[0]]),
        row(f"`{experiments[0]}` {' '.join(SB3_FORM)} (SB3's form)", "ss-drl (TorchRL)", runs[sb3_form]),
    ]
    if have_sb3:
        rows.append(row("SB3 `DQN` + `HerReplayBuffer`", f"stable-baselines3 {_sb3_version()}", runs["sb3"]))
    for name in experiments[1:]:
        rows.append(row(f"`{name}` (Smart Start on; for information)", "ss-drl (TorchRL)", runs[name]))
    # At train_freq env steps per gradient_steps updates, the bare update rate bounds the env steps/s.
    steps_per_update = int(agent.train_freq) / int(agent.gradient_steps)
    bare_rate = median([r["updates_per_s"] for r in bare])
    rows.append(
        [
            "bare PyTorch update of SB3's network (no env, no buffer, no TorchRL): the eager-PyTorch ceiling",
            f"torch {torch.__version__}",
            "-",
            steps,
            fmt_rate(bare_rate * steps_per_update),
            f"{bare_rate:.1f}",
            "-",
        ]
    )
    headers = [
        "run",
        "framework",
        "timed env steps",
        "updates",
        "train-phase env steps/s",
        "updates/s",
        "whole-run env steps/s",
    ]
    out += [markdown_table(headers, rows), ""]
    if note:
        out += [note, ""]
    if have_sb3:
        ours = median([r["steps_per_s"] for r in runs[experiments[0]]])
        same_form = median([r["steps_per_s"] for r in runs[sb3_form]])
        theirs = median([r["steps_per_s"] for r in runs["sb3"]])
        out.append(f"- ratio ours/SB3 (train-phase env steps/s, `{experiments[0]}`): **{ours / theirs:.2f}x**")
        out.append(
            f"- ratio ours/SB3 with SB3's form of DQN (plain target, no dueling head): **{same_form / theirs:.2f}x**"
        )
        out.append(
            f"- ceiling/SB3: **{bare_rate * steps_per_update / theirs:.2f}x**: at this update-to-data ratio no "
            "trainer built on eager PyTorch steps the env faster than its bare update allows, env and buffer free"
        )
    for name in experiments[1:]:
        decisions = median([r["decisions"] for r in runs[name]])
        out.append(f"- `{name}`: {decisions:.0f} Smart Start decisions per run (one per episode start after the first)")
    out.append(
        "- whole-run = all env steps / wall time (ss-drl: the trainer's `env_steps_per_s`, which includes the "
        "greedy evaluations at step 0 and at the end; SB3: both `learn` calls)"
    )
    parity = [
        ["env", f"`BatchedMazeEnv({base.env.preset!r}, 1, max_steps={max_steps})`", f"`gymnasium.make({env_id!r})`"],
        [
            "network",
            f"cell embeddings 2x{agent.embed_dim} -> MLP {list(agent.hidden)}, dueling={agent.dueling}",
            f"3 flattened (row, col) pairs -> MLP net_arch={list(agent.hidden)}",
        ],
        ["batch / buffer", f"{agent.batch_size} / {agent.buffer_size}", f"{agent.batch_size} / {agent.buffer_size}"],
        ["learning_starts", learning_starts, learning_starts],
        [
            "update-to-data",
            f"train_freq={agent.train_freq}, gradient_steps={agent.gradient_steps}",
            f"train_freq={agent.train_freq}, gradient_steps={agent.gradient_steps}",
        ],
        [
            "target net",
            f"hard copy every {agent.target_update_interval} updates",
            f"every {agent.target_update_interval * agent.train_freq // agent.gradient_steps} env steps",
        ],
        ["HER", f"{her.strategy}, k={her.k}", f"{her.strategy}, n_sampled_goal={her.k}"],
        [
            "loss / target",
            f"{agent.loss}, double DQN={agent.double_dqn}",
            "smooth L1, plain DQN target",
        ],
    ]
    out += ["", "Settings compared:", "", markdown_table(["", "ss-drl", "SB3"], parity)]
    return "\n".join(out) + "\n"


def _sb3_version() -> str:
    import stable_baselines3

    return stable_baselines3.__version__


# --- 3. planner -------------------------------------------------------------------------------------------------------
def load_planner_maze(name: str):
    from ss_drl.envs.maze import load_maze, random_maze

    if name == "random100":
        return random_maze(100, 100, seed=0)
    return load_maze(name)


def explored_counts(maze):
    """A count model that has seen every free cell x every action once (``Maze.transition_table()``)."""
    from ss_drl.smart_start import CountModel

    table = maze.transition_table()
    free = np.flatnonzero(~maze.walls.reshape(-1))
    s = np.repeat(free, 4)
    a = np.tile(np.arange(4), free.size)
    s2 = table[s, a]
    r = (s2 == maze.goal_cell).astype(np.float32)
    counts = CountModel(maze.n_cells, 4)
    counts.update(torch.from_numpy(s), torch.from_numpy(a), torch.from_numpy(s2), torch.from_numpy(r))
    return counts


def _timed(fn: Callable, repeats: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return median(times) * 1e3, result


def matmul_floor(n: int, embed_dim: int, hidden: Sequence[int], actions: int = 4) -> Callable[[], None]:
    """The matrix products alone of one Q evaluation of ``n`` states for one goal, in ``goal_q_values``' row blocks:
    the state half of the first layer (E -> H1), the hidden layers and the head, into preallocated outputs. Any
    evaluation of Q for all visited states with this network costs at least this much (the rest is extra)."""
    from ss_drl.smart_start.selection import BLOCK_ROWS

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

    from ss_drl.agents.dqn import GoalQNetwork
    from ss_drl.smart_start import Planner, select_smart_start
    from ss_drl.smart_start.selection import goal_q_values

    ss = OmegaConf.load(CONFIG_DIR / "smart_start" / "on.yaml")
    agent = OmegaConf.load(CONFIG_DIR / "agent" / "dqn.yaml")
    rows, extreme_total = [], []
    for name in mazes:
        maze = load_planner_maze(name)
        counts = explored_counts(maze)
        visited = counts.visited_states()
        torch.manual_seed(seed)
        q_net = GoalQNetwork(maze, agent.encoder, agent.embed_dim, tuple(agent.hidden), agent.dueling).eval()

        def max_q(states, goals, q_net=q_net):
            # Every visited state for each goal in one batched evaluation (goal_q_values: the first layer's state
            # and goal halves computed separately), then max over actions.
            return goal_q_values(q_net, states, goals).amax(dim=-1)

        planner = Planner(maze.width, gamma=ss.gamma, theta=ss.theta, tol=ss.tol, max_sweeps=ss.max_sweeps)
        goals = torch.tensor([maze.goal_cell])
        rng = np.random.default_rng(seed)
        targets = {"start": maze.start_cell, "random visited": int(visited[int(rng.integers(visited.numel()))])}
        gen = torch.Generator().manual_seed(seed)
        select = functools.partial(select_smart_start, counts, max_q, goals, ss.c_ss, ss.w_q, gen)
        select()  # warm-up
        select_ms, _ = _timed(select, repeats)
        floor = matmul_floor(visited.numel(), agent.embed_dim, list(agent.hidden))
        floor()  # warm-up
        floor_ms, _ = _timed(floor, repeats)
        # S_ss by counts alone (w_q = 0, the paper-setup experiments): no network evaluation.
        counts_ms, _ = _timed(functools.partial(select_smart_start, counts, max_q, goals, ss.c_ss, 0.0, gen), repeats)
        for label, target in targets.items():
            plan = functools.partial(planner.plan, counts, torch.tensor([target]), gen)
            plan()  # warm-up
            plan_ms, result = _timed(plan, repeats)
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
        f"hidden {list(agent.hidden)}) evaluated by `goal_q_values`, one goal; 'w_q 0': S_ss by counts alone (the "
        "paper-setup experiments), which needs no network pass. 'its matmuls alone': the matrix products of that "
        "evaluation, in its row blocks, on preallocated tensors, nothing else. Planning: `Planner.plan` "
        f"(gamma={ss.gamma}, theta={ss.theta}, tol={ss.tol}, max_sweeps={ss.max_sweeps}) towards the target. "
        "'states with V>0': visited states other than the target from which the plan has a route.",
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


# --- 4. her -----------------------------------------------------------------------------------------------------------
def synthetic_batch(rows: int, first_row: int, episode_len: int = 100, n_cells: int = 300):
    """A (rows, 1) batch of HER-buffer transitions: random cells, episodes of ``episode_len`` steps (truncated)."""
    from tensordict import TensorDict

    t = torch.arange(first_row, first_row + rows)
    done = ((t + 1) % episode_len == 0).view(rows, 1, 1)
    goal = torch.full((rows, 1), n_cells - 1, dtype=torch.int64)
    return TensorDict(
        {
            "observation": torch.randint(0, n_cells, (rows, 1)),
            "desired_goal": goal,
            "action": torch.randint(0, 4, (rows, 1)),
            "next": {
                "observation": torch.randint(0, n_cells, (rows, 1)),
                "desired_goal": goal.clone(),
                "reward": torch.zeros(rows, 1, 1, dtype=torch.float32),
                "terminated": torch.zeros(rows, 1, 1, dtype=torch.bool),
                "truncated": done,
                "done": done.clone(),
            },
        },
        batch_size=(rows, 1),
    )


def filled_buffer(size: int, batch_size: int = 128, k: int = 4, episode_len: int = 100, chunk: int = 250_000):
    """A full :class:`HindsightReplayBuffer` of ``size`` transitions (one env copy), filled by a few large extends."""
    from ss_drl.her import HindsightReplayBuffer

    buffer = HindsightReplayBuffer(
        size, num_envs=1, batch_size=batch_size, strategy="future", k=k, generator=torch.Generator().manual_seed(0)
    )
    chunk = min(chunk, size)
    for first in range(0, size, chunk):
        buffer.extend(synthetic_batch(min(chunk, size - first), first, episode_len))
    return buffer


def bench_her(
    repeats: int,
    sizes: Sequence[int] = (10_000, 1_000_000),
    samples: int = 200,
    batch_size: int = 128,
    k: int = 4,
    episode_len: int = 100,
) -> str:
    """ms per ``HindsightReplayBuffer.sample()`` at each stored size (median of samples, then of repeats)."""
    rows, medians = [], {}
    for size in sizes:
        torch.manual_seed(0)
        start = time.perf_counter()
        buffer = filled_buffer(size, batch_size, k, episode_len)
        fill_s = time.perf_counter() - start
        for _ in range(10):  # warm-up
            buffer.sample()
        per_repeat, all_times = [], []
        for _ in range(repeats):
            times = []
            for _ in range(samples):
                t0 = time.perf_counter()
                buffer.sample()
                times.append((time.perf_counter() - t0) * 1e3)
            per_repeat.append(median(times))
            all_times += times
        medians[size] = median(per_repeat)
        p90 = float(np.percentile(all_times, 90))
        rows.append([f"{size:,}", f"{len(buffer):,}", f"{fill_s:.2f}", fmt_ms(medians[size]), fmt_ms(p90)])
        del buffer
    out = [
        f"## her: ms per `HindsightReplayBuffer.sample()` (batch {batch_size}, future, k={k}; synthetic episodes of "
        f"{episode_len} steps; median of {samples} samples, median of {repeats} repeats)",
        "",
        markdown_table(["stored transitions", "len(buffer)", "fill s", "sample ms (median)", "sample ms (p90)"], rows),
        "",
    ]
    if len(sizes) > 1:
        small, big = min(sizes), max(sizes)
        out.append(
            f"- ratio {big:,} / {small:,}: {medians[big] / medians[small]:.2f}x (O(batch) sampling: ~1 expected)"
        )
    return "\n".join(out) + "\n"


# --- CLI --------------------------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scripts/benchmark.py",
        description="ss-drl throughput benchmarks; prints markdown tables (medians over repeats).",
    )
    parser.add_argument("--section", choices=(*SECTIONS, "all"), default="all", help="which benchmark (default all)")
    parser.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="repeats per measurement (default: " + ", ".join(f"{k} {v}" for k, v in DEFAULT_REPEATS.items()) + ")",
    )
    parser.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads, for ss-drl and SB3 alike (default 1)"
    )
    parser.add_argument("--quick", action="store_true", help="small sizes and 2 repeats: a smoke run in seconds")
    parser.add_argument(
        "--train-steps",
        type=int,
        default=None,
        help="timed env steps after learning_starts in the train section (default 1500; --quick 200)",
    )
    return parser


def header(argv: Sequence[str], prog: str) -> str:
    import gymnasium
    import tensordict
    import torchrl

    sb3 = _sb3_version() if sb3_available() else "not installed"
    command = " ".join(shlex.quote(part) for part in (prog, *argv))
    return "\n".join(
        [
            "# ss-drl benchmark",
            "",
            f"`$ python {command}`",
            "",
            f"python {platform.python_version()}, torch {torch.__version__} (threads {torch.get_num_threads()}), "
            f"torchrl {torchrl.__version__}, tensordict {tensordict.__version__}, gymnasium {gymnasium.__version__}, "
            f"stable-baselines3 {sb3}; {os.cpu_count()} CPUs ({platform.processor() or platform.machine()}); "
            f"load average {', '.join(f'{x:.2f}' for x in os.getloadavg())}",
            "",
        ]
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``scripts/benchmark.py``; returns the exit code (0)."""
    if argv is None:
        prog, argv = sys.argv[0], sys.argv[1:]
    else:
        prog = "scripts/benchmark.py"
    args = build_parser().parse_args(argv)
    _quiet_torchrl()
    if args.threads < 1:
        build_parser().error(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    sections = SECTIONS if args.section == "all" else (args.section,)
    print(header(argv, prog), flush=True)
    for section in sections:
        repeats = args.repeats or (QUICK_REPEATS if args.quick else DEFAULT_REPEATS[section])
        start = time.perf_counter()
        if section == "env":
            sizes = dict(raw_steps=2_000, gym_steps=500, batched_iters=500) if args.quick else {}
            text = bench_env(repeats, **sizes)
        elif section == "train":
            steps = args.train_steps or (200 if args.quick else 1_500)
            text = bench_train(repeats, steps=steps)
        elif section == "planner":
            text = bench_planner(repeats)
        else:
            text = bench_her(repeats, samples=50 if args.quick else 200)
        print(text, flush=True)
        print(f"_{section}: {time.perf_counter() - start:.0f} s_\n", flush=True)
    return 0
