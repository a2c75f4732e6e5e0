"""The ``train`` section: training throughput (env steps/s, updates included) of one experiment (``--experiment``,
default ``easy_dqn_her``) against Stable-Baselines3 ``DQN`` + ``HerReplayBuffer`` with the same network width, batch
size, buffer size, learning_starts, update-to-data ratio, target-network update and HER setting, against an older
checkout of ss-drl (``--baseline-checkout``; names mapped by docs/migration.md where the checkout predates them:
:func:`baseline_invocation`), and
against the eager-PyTorch ceiling (:func:`run_bare_update`). Only the training phase is timed (from learning_starts
on, from each run's own train.csv); the whole-run rate is shown too. Each ss-drl run, this checkout's and the
baseline's alike, is a subprocess ``python scripts/train.py`` of its checkout. Stable-Baselines3 is optional (the
``bench`` extra): without it the SB3 rows are left out with a note.

The default ss-drl run compared with SB3 is ``easy_dqn_her``: the replay-only DQN (``agent=dqn``) with HER, which
learns from its replay buffer alone, as SB3's DQN does. SB3 has no counterpart of the count model's bounds, so the
model-bounded learner (``easy_dqn_her_bounded``, which at 7ac5009 was ``easy_dqn_her``) is not the like-for-like
comparison: for it, and any experiment but a replay-only ``dqn_her``, the SB3 rows are skipped with a note. A second
row runs the experiment in SB3's form (:func:`sb3_form`): SB3's plain one-step DQN target with its Huber loss, no
dueling head and none of the replay-only DQN's bounds (its k-step maximum costs network passes SB3 never makes), so
that the two libraries do the same arithmetic per update. By default ``easy_ss_her`` (Smart Start on) is timed for
information.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from benchmarks.common import compose_config, fmt_rate, markdown_table, median

#: This checkout: the repository root that holds ``benchmarks/``, ``scripts/`` and ``ss_drl/``.
ROOT = Path(__file__).resolve().parent.parent

#: Updates between train.csv rows in the benchmark runs: the rows time the training phase.
LOG_INTERVAL = 10


def train_phase_window(run_dir) -> tuple[float, int, int]:
    """(seconds, env steps, updates) of the training phase, from the run's train.csv: between its first row (the
    first ``trainer.log_interval`` updates after ``learning_starts``) and its last, so rollouts and updates alike."""
    with open(Path(run_dir) / "train.csv") as f:
        rows = list(csv.DictReader(f))
    if len(rows) < 2:
        return float("nan"), 0, 0
    first, last = rows[0], rows[-1]
    return (
        float(last["wall_s"]) - float(first["wall_s"]),
        int(last["env_steps"]) - int(first["env_steps"]),
        int(last["updates"]) - int(first["updates"]),
    )


#: ss-drl's DQN in the form of SB3's: the plain one-step DQN target (no double DQN, no n-step, no clipping), the Huber
#: loss and no dueling head; :func:`sb3_form` also turns off every bound the experiment's learner has on.
SB3_FORM = (
    "agent.double_dqn=false",
    "agent.dueling=false",
    "agent.n_step=1",
    "agent.clip_targets=false",
    "agent.loss=smooth_l1",
)
SB3_FORM_NOTE = "plain one-step DQN target, Huber loss, no dueling head, no bound"


def sb3_form(agent_cfg) -> tuple[str, ...]:
    """The overrides that put the learner of ``agent_cfg`` (a composed ``agent`` node) in SB3's form: :data:`SB3_FORM`
    and each TD-target switch that is on in it turned off."""
    from ss_drl.agents.settings import DQNSettings
    from ss_drl.agents.targets import assumptions

    on = assumptions(DQNSettings.from_config(agent_cfg))
    return SB3_FORM + tuple(f"agent.{key}=false" for key in on)


def sb3_target_update(agent_cfg) -> tuple[int, float]:
    """SB3's ``(target_update_interval, tau)`` for ss-drl's target-network update. ss-drl counts in updates, SB3 in
    env steps (at most one target update per env step): a hard copy every ``target_update_interval`` updates is a copy
    (tau 1) every that many updates' env steps; a Polyak step at ``tau`` every update is one every
    ``max(1, train_freq // gradient_steps)`` env steps, at the tau that averages at the same rate per env step."""
    per_env_step = int(agent_cfg.gradient_steps) / int(agent_cfg.train_freq)
    if agent_cfg.target_update == "hard":
        return int(agent_cfg.target_update_interval) * int(agent_cfg.train_freq) // int(agent_cfg.gradient_steps), 1.0
    interval = max(1, int(agent_cfg.train_freq) // int(agent_cfg.gradient_steps))
    return interval, 1.0 - (1.0 - float(agent_cfg.tau)) ** (interval * per_env_step)


def _train_overrides(experiment: str, steps: int, learning_starts: int, max_steps: int, seed: int) -> list[str]:
    big = 10**12
    return [
        f"+experiment={experiment}",
        f"trainer.total_env_steps={learning_starts + steps}",
        f"trainer.eval_interval={big}",
        f"trainer.checkpoint_interval={big}",
        f"trainer.log_interval={LOG_INTERVAL}",
        f"trainer.torch_threads={torch.get_num_threads()}",
        f"agent.learning_starts={learning_starts}",
        f"env.max_steps={max_steps}",
        "logger=csv",
        f"seed={seed}",
    ]


def run_ssdrl(
    experiment: str,
    steps: int,
    learning_starts: int,
    max_steps: int,
    seed: int = 0,
    overrides: Sequence[str] = (),
    checkout: str | Path = ROOT,
) -> dict:
    """One ss-drl training run of ``checkout``'s code (this checkout by default); its training-phase and whole-run
    rates.

    Every run, this checkout's and a baseline checkout's alike, is a subprocess ``python scripts/train.py`` with
    ``cwd`` and ``PYTHONPATH`` the checkout (so that its own ``ss_drl`` and ``conf/`` are used), the same overrides
    and ``hydra.run.dir`` under a temporary directory: both sides pay the same start-up, which the train-phase window
    (:func:`train_phase_window`, from the run's own train.csv) leaves out anyway."""
    checkout = Path(checkout).resolve()
    args = _train_overrides(experiment, steps, learning_starts, max_steps, seed) + list(overrides)
    env = dict(os.environ, PYTHONPATH=str(checkout))
    with tempfile.TemporaryDirectory(prefix="ssdrl-bench-") as tmp:
        run_dir = Path(tmp) / "run"
        command = [sys.executable, "scripts/train.py", *args, f"hydra.run.dir={run_dir}"]
        proc = subprocess.run(command, cwd=checkout, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-15:])
            raise RuntimeError(f"training run failed in {checkout}: {' '.join(args)}\n{tail}")
        summary = json.loads((run_dir / "summary.json").read_text())
        seconds, env_steps, updates = train_phase_window(run_dir)
    return {
        "steps_per_s": env_steps / seconds,
        "updates_per_s": updates / seconds,
        "timed_steps": env_steps,
        "updates": updates,
        "whole_steps_per_s": summary["env_steps_per_s"],
        "decisions": summary.get("smart_start_decisions", 0),
    }


#: The replay-only DQN (setting LM) in 7ac5009's terms: docs/migration.md's table.
LM_OVERRIDES = (
    "agent.n_step_max=true",
    "agent.distance_ceiling=false",
    "agent.distance_floor=false",
    "agent.bound_all_actions=false",
    "agent.model_targets=false",
    "agent.optimistic_floor=false",
)
DEEP_METHODS = ("dqn_her", "ss_her", "dqn", "ss")  # longest suffix first
TABULAR_METHODS = ("tabular_ss", "tabular")


#: A file that only checkouts with today's names have (the rename of issue 48, 327f876, added it).
RENAMED_MARKER = Path("conf", "agent", "dqn_bounded.yaml")


def baseline_invocation(experiment: str, checkout: str | Path | None = None) -> tuple[str, list[str]]:
    """Today's ``+experiment=NAME`` as 7ac5009 ran it (docs/migration.md): ``(experiment there, overrides)``. A
    ``checkout`` that already has today's names (:data:`RENAMED_MARKER`) runs ``NAME`` as it is.

    ``<maze>_<method>_bounded`` is 7ac5009's ``<maze>_<method>`` (LCFATO, its shared setting); the replay-only
    ``<maze>_<method>`` is 7ac5009's ``<maze>_<method>`` with :data:`LM_OVERRIDES`; the tabular experiments are
    unchanged. Raises ValueError (one line) for an experiment 7ac5009 has no counterpart of (``<maze>_frontier``)."""
    if checkout is not None and (Path(checkout) / RENAMED_MARKER).is_file():
        return experiment, []
    for method in DEEP_METHODS:
        if experiment.endswith(f"_{method}_bounded"):
            return experiment[: -len("_bounded")], []
    for method in TABULAR_METHODS:
        if experiment.endswith(f"_{method}"):
            return experiment, []
    for method in DEEP_METHODS:
        if experiment.endswith(f"_{method}"):
            return experiment, list(LM_OVERRIDES)
    if experiment.endswith("_frontier"):
        raise ValueError(f"{experiment}: the frontier explorer is new since 7ac5009, so it has no baseline to run")
    raise ValueError(f"{experiment}: not in docs/migration.md's table, so it has no baseline to run")


def checkout_commit(checkout: str | Path) -> str:
    """The short commit of a git checkout (``?`` if git cannot tell)."""
    proc = subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return proc.stdout.strip() or "?"


def checkout_package(checkout: str | Path) -> str:
    """Where ``import ss_drl`` resolves from, run as :func:`run_ssdrl` runs a checkout; raises ValueError if it is not
    the checkout's own package (an installed ss-drl shadowing it)."""
    checkout = Path(checkout).resolve()
    env = dict(os.environ, PYTHONPATH=str(checkout))
    proc = subprocess.run(
        [sys.executable, "-c", "import ss_drl; print(ss_drl.__file__)"],
        cwd=checkout, env=env, capture_output=True, text=True,
    )  # fmt: skip
    path = Path(proc.stdout.strip() or "?")
    if proc.returncode != 0 or not path.resolve().is_relative_to(checkout):
        raise ValueError(f"{checkout}: its ss_drl is not what runs there (import ss_drl -> {path})")
    return str(path)


#: The bare-update rows of the train section.
BARE_SB3 = "bare PyTorch update of SB3's network (no env, no buffer, no TorchRL): the eager-PyTorch ceiling"
BARE_OWN = (
    "bare PyTorch update of this experiment's network (GoalQNetwork; no env, no buffer, no TorchRL, no bounds): "
    "the trainer's own ceiling"
)


def run_bare_update(agent_cfg, updates: int, seed: int = 0, world=None) -> dict:
    """The ceiling of an eager-PyTorch trainer: updates/s of a bare DQN update, batches made up in advance.

    Without ``world``: on SB3's Q-network for this env (the 6 coordinates of state, achieved and desired goal -> MLP
    of the agent's hidden widths -> 4 values: the least arithmetic at this width). With ``world`` (the experiment's
    maze or MiniGrid task, :func:`~ss_drl.training.trainer.make_maze`): on the experiment's own
    :class:`~ss_drl.agents.network.GoalQNetwork` over that world's states and goals (its encoder, embedding size,
    widths, dueling head and, with ``agent.sparse_tables``, sparse tables stepped by the lazy Adam as the trainer
    steps them), so the row shows how close the trainer is to its own network's ceiling. Either way a plain
    ``max_a Q'`` target from a copy, the same batch size, Adam and gradient clipping: no env, no replay buffer, no
    TorchRL or tensordict, no bounds; only the PyTorch arithmetic of one forward and backward pass on the batch
    and one target pass.
    """
    import copy

    from ss_drl.agents.tables import LazyAdam, clip_grad_norm, table_keys

    torch.manual_seed(seed)
    size = int(agent_cfg.batch_size)
    n_actions, sparse = 4, False
    if world is None:
        layers, width = [], 6
        for hidden in agent_cfg.hidden:
            layers += [torch.nn.Linear(width, int(hidden)), torch.nn.ReLU()]
            width = int(hidden)
        net = torch.nn.Sequential(*layers, torch.nn.Linear(width, 4))

        def inputs():
            return (torch.rand(size, 6),)
    else:
        from ss_drl.agents.network import GoalQNetwork

        sparse, n_actions = bool(agent_cfg.get("sparse_tables", False)), world.n_actions
        hidden = tuple(int(h) for h in agent_cfg.hidden)
        net = GoalQNetwork(world, agent_cfg.encoder, int(agent_cfg.embed_dim), hidden, bool(agent_cfg.dueling), sparse)

        def inputs():
            return (torch.randint(0, world.n_states, (size,)), torch.randint(0, world.n_cells, (size,)))

    target = copy.deepcopy(net).requires_grad_(False)
    params = list(net.parameters())
    optimizers = []
    if sparse:  # the tables by the lazy Adam, the rest by Adam, as DQNAgent steps them
        tables = [net.get_parameter(name) for name, _ in table_keys(net)]
        optimizers.append(LazyAdam(tables, lr=float(agent_cfg.lr)))
        params = [p for p in params if all(p is not t for t in tables)]
    optimizers.append(torch.optim.Adam(params, lr=float(agent_cfg.lr), fused=True))
    gamma, clip = float(agent_cfg.gamma), float(agent_cfg.grad_clip)
    batches = [
        (inputs(), torch.randint(0, n_actions, (size, 1)), inputs(), torch.rand(size, 1), torch.rand(size, 1) < 0.1)
        for _ in range(min(updates, 64))
    ]

    def update(obs, action, next_obs, reward, terminated) -> None:
        pred = net(*obs).gather(-1, action)
        with torch.no_grad():
            td_target = reward + gamma * (~terminated).float() * target(*next_obs).amax(-1, keepdim=True)
        loss = torch.nn.functional.mse_loss(pred, td_target)
        for optimizer in optimizers:
            optimizer.zero_grad()
        loss.backward()
        if clip > 0 and sparse:
            clip_grad_norm(list(net.parameters()), clip)
        elif clip > 0:
            torch.nn.utils.clip_grad_norm_(net.parameters(), clip, foreach=True)
        for optimizer in optimizers:
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

    target_update_interval, tau = sb3_target_update(agent_cfg)
    return dict(
        learning_rate=float(agent_cfg.lr),
        buffer_size=int(agent_cfg.buffer_size),
        learning_starts=int(learning_starts),
        batch_size=int(agent_cfg.batch_size),
        gamma=float(agent_cfg.gamma),
        train_freq=int(agent_cfg.train_freq),
        gradient_steps=int(agent_cfg.gradient_steps),
        target_update_interval=target_update_interval,
        tau=tau,
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


def world_name(env_cfg) -> str:
    """What an ``env`` config node trains on, as the section names it: the MiniGrid id and layout, the maze file,
    or the preset."""
    if env_cfg.get("id"):
        return f"{env_cfg.id} (layout {env_cfg.layout_seed})"
    return str(env_cfg.layout) if env_cfg.get("layout") else str(env_cfg.preset)


def sb3_env_id(preset: str) -> str | None:
    """The registered gymnasium id of a maze preset (``SSDRL/Easy-v0`` for ``easy``), or None."""
    from ss_drl.envs import ENV_IDS

    return {name: env_id for env_id, name in ENV_IDS.items()}.get(str(preset))


def bench_train(
    repeats: int,
    steps: int = 1_500,
    max_steps: int | None = None,
    learning_starts: int | None = None,
    experiments: Sequence[str] = ("easy_dqn_her", "easy_ss_her"),
    include_sb3: bool = True,
    env_id: str | None = None,
    baseline_checkout: str | Path | None = None,
    command: str | None = None,
    overrides: Sequence[str] = (),
) -> str:
    """Training throughput of ss-drl vs SB3 DQN + HER on the same maze and settings (median of repeats), and of
    ss-drl vs an older checkout of itself (``baseline_checkout``).

    ``experiments[0]`` is the experiment timed. It is compared with SB3, as it runs and in SB3's form, when SB3 can
    mirror it (the replay-only ``dqn_her`` on a maze with a gymnasium id; otherwise the SB3 rows are skipped with a
    note), and with ``baseline_checkout``'s run of the same experiment, named as there (:func:`baseline_invocation`),
    when one is given: the two interleaved, same budget, seed, learning_starts and timing. The rest of
    ``experiments`` are timed for information. The default compares the replay-only ``easy_dqn_her`` (see the
    module's docstring). ``max_steps``/``learning_starts`` default to the experiment's ``env.max_steps`` and
    ``max(agent.learning_starts, env.max_steps)``: SB3's ``HerReplayBuffer`` cannot sample before the first episode
    has ended, which is only certain after ``max_steps`` env steps. ``command`` (the command line) heads the section.
    ``overrides`` (Hydra overrides) apply to the timed experiment's own runs, not to the baseline's.
    """
    from ss_drl.methods import method_label
    from ss_drl.training.trainer import make_maze

    experiment = experiments[0]
    overrides = tuple(overrides)
    base = compose_config([f"+experiment={experiment}", *overrides])
    baseline = None
    if baseline_checkout is not None:
        baseline_checkout = Path(baseline_checkout).resolve()
        base_name, base_overrides = baseline_invocation(experiment, baseline_checkout)  # ValueError: no baseline
        if not (baseline_checkout / "conf" / "experiment" / f"{base_name}.yaml").is_file():
            raise ValueError(
                f"{baseline_checkout}: has no conf/experiment/{base_name}.yaml (the baseline of {experiment})"
            )
        package = checkout_package(baseline_checkout)
        commit = checkout_commit(baseline_checkout)
        baseline = (base_name, base_overrides, commit, package)
    max_steps = int(base.env.max_steps if max_steps is None else max_steps)
    if learning_starts is None:
        learning_starts = max(int(base.agent.learning_starts), max_steps)
    learning_starts = int(learning_starts)
    agent, her = base.agent, base.get("her")
    deep = "hidden" in agent  # a DQN learner: it has an SB3 form and a bare-update ceiling
    world = world_name(base.env)
    # SB3 runs a gymnasium id: a preset's, never in place of a maze file or a MiniGrid task.
    env_id = env_id or (None if base.env.get("id") or base.env.get("layout") else sb3_env_id(base.env.preset))
    mirror = method_label(base) == "dqn_her" and env_id is not None
    out = [
        f"## train: training throughput of `{experiment}` on {world} (median of {repeats}; {steps} timed env "
        f"steps after learning_starts={learning_starts}; torch threads {torch.get_num_threads()})",
        "",
    ]
    if overrides:
        out += [f"Overrides of `{experiment}`'s runs: `{' '.join(overrides)}`", ""]
    if command:
        out += [f"`$ {command}`", ""]
    have_sb3 = include_sb3 and mirror and sb3_available()
    notes = []
    if include_sb3 and not mirror:
        notes.append(
            "> **Note:** SB3 rows skipped: SB3's `DQN` + `HerReplayBuffer` mirrors only the replay-only `dqn_her` on "
            f"a maze with a gymnasium id, and `{experiment}` is {method_label(base)} on {world}."
        )
    elif include_sb3 and not have_sb3:
        notes.append(
            "> **Note:** stable-baselines3 is not installed, so the SB3 rows are skipped. Install it with "
            '`pip install -c constraints.txt "stable-baselines3>=2.3"` (or `pip install -e ".[bench]"`).'
        )

    runs: dict[str, list[dict]] = {name: [] for name in experiments}
    form = sb3_form(agent) if mirror else ()
    form_key = f"{experiment}, SB3's form"
    base_key = f"{experiment}, baseline"
    runs[form_key], runs[base_key] = [], []
    if have_sb3:
        runs["sb3"] = []
        kwargs = sb3_kwargs(agent, her, learning_starts, learning_starts + steps)
        # Warm-up of SB3 in this process (imports, allocator, first-call overheads): a short run, untimed. Each
        # ss-drl run is a fresh subprocess whose start-up the train-phase window leaves out.
        warm = dict(kwargs, learning_starts=min(learning_starts, 40))
        run_sb3(env_id, warm, min(steps, 40), min(learning_starts, 40), max_steps=min(max_steps, 40))
    bare: list[dict] = []
    bare_own: list[dict] = []
    own_world = make_maze(base.env) if deep else None  # the experiment's maze or MiniGrid task
    # Interleaved (ours, baseline, ours, baseline, ...), so that drifting load on a shared machine hits every run alike.
    for _ in range(repeats):
        runs[experiment].append(run_ssdrl(experiment, steps, learning_starts, max_steps, overrides=overrides))
        if baseline:
            runs[base_key].append(
                run_ssdrl(
                    baseline[0], steps, learning_starts, max_steps, overrides=baseline[1], checkout=baseline_checkout
                )
            )
        if mirror:
            runs[form_key].append(run_ssdrl(experiment, steps, learning_starts, max_steps, overrides=form))
        if have_sb3:
            runs["sb3"].append(run_sb3(env_id, kwargs, steps, learning_starts, max_steps))
        for name in experiments[1:]:
            runs[name].append(run_ssdrl(name, steps, learning_starts, max_steps))
        if deep:
            bare.append(run_bare_update(agent, steps))
            bare_own.append(run_bare_update(agent, steps, world=own_world))

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

    rows = [row(f"`{experiment}`", "ss-drl (TorchRL)", runs[experiment])]
    if baseline:
        rows.append(row(f"`{baseline[0]}` at {baseline[2]} (baseline)", f"ss-drl {baseline[2]}", runs[base_key]))
    if mirror:
        rows.append(row(f"`{experiment}` in SB3's form", "ss-drl (TorchRL)", runs[form_key]))
    if have_sb3:
        rows.append(row("SB3 `DQN` + `HerReplayBuffer`", f"stable-baselines3 {sb3_version()}", runs["sb3"]))
    for name in experiments[1:]:
        rows.append(row(f"`{name}` (Smart Start on; for information)", "ss-drl (TorchRL)", runs[name]))
    if deep:
        # At train_freq env steps per gradient_steps updates, the bare update rate bounds the env steps/s.
        steps_per_update = int(agent.train_freq) / int(agent.gradient_steps)
        bare_rates = {label: median([r["updates_per_s"] for r in results]) for label, results in
                      ((BARE_SB3, bare), (BARE_OWN, bare_own))}  # fmt: skip
        bare_rate = bare_rates[BARE_SB3]
        for label, rate in bare_rates.items():
            rows.append(
                [
                    label,
                    f"torch {torch.__version__}",
                    "-",
                    steps,
                    fmt_rate(rate * steps_per_update),
                    f"{rate:.1f}",
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
    for note in notes:
        out += [note, ""]
    ours = median([r["steps_per_s"] for r in runs[experiment]])
    if baseline:
        theirs = median([r["steps_per_s"] for r in runs[base_key]])
        out.append(
            f"- ratio ours/baseline (train-phase env steps/s, `{experiment}` vs {baseline[2]}'s `{baseline[0]}`): "
            f"**{ours / theirs:.2f}x**"
        )
        out.append(
            f"- baseline: `python scripts/train.py +experiment={baseline[0]}"
            + "".join(f" {o}" for o in baseline[1])
            + f"` (docs/migration.md), run in {baseline_checkout} (its `ss_drl`: {baseline[3]}) with the same "
            "budget, seed, learning_starts and timing; every run is a subprocess `python scripts/train.py` of its "
            "checkout, the two interleaved"
        )
    if deep:
        own = bare_rates[BARE_OWN] * steps_per_update
        out.append(f"- ours/own ceiling (train-phase env steps/s against the bare update of its network): "
                   f"**{ours / own:.2f}**")  # fmt: skip
    if have_sb3:
        same_form = median([r["steps_per_s"] for r in runs[form_key]])
        theirs = median([r["steps_per_s"] for r in runs["sb3"]])
        out.append(f"- ratio ours/SB3 (train-phase env steps/s, `{experiment}`): **{ours / theirs:.2f}x**")
        out.append(f"- ratio ours/SB3 with SB3's form of DQN ({SB3_FORM_NOTE}): **{same_form / theirs:.2f}x**")
        out.append(
            f"- ceiling/SB3: **{bare_rate * steps_per_update / theirs:.2f}x**: at this update-to-data ratio no "
            "trainer built on eager PyTorch steps the env faster than its bare update allows, env and buffer free"
        )
    if mirror:
        out.append(f"- SB3's form ({SB3_FORM_NOTE}): `{experiment}` {' '.join(form)}")
    for name in experiments[1:]:
        decisions = median([r["decisions"] for r in runs[name]])
        out.append(f"- `{name}`: {decisions:.0f} Smart Start decisions per run (one per episode start after the first)")
    out.append(
        "- whole-run = all env steps / wall time (ss-drl: the trainer's `env_steps_per_s`, which includes the "
        "greedy evaluations at step 0 and at the end; SB3: both `learn` calls)"
    )
    if not mirror:
        return "\n".join(out) + "\n"
    from ss_drl.agents.settings import DQNSettings
    from ss_drl.agents.targets import assumptions

    bounds = ", ".join(assumptions(DQNSettings.from_config(agent))) or "none"
    interval, tau = sb3_target_update(agent)
    if agent.target_update == "hard":
        ours_target = f"hard copy every {agent.target_update_interval} updates"
        their_target = f"hard copy every {interval} env steps"
    else:
        ours_target = f"Polyak, tau={agent.tau} every update"
        their_target = f"Polyak, tau={tau:.4g} every {interval} env step(s)"
    parity = [
        ["learner", f"{method_label(base)} (`{experiment}`; bounds on: {bounds})", "`DQN` + `HerReplayBuffer`"],
        ["env", f"`BatchedMazeEnv({base.env.preset!r}, 1, max_steps={max_steps})`", f"`gymnasium.make({env_id!r})`"],
        [
            "network",
            f"{agent.encoder} cell encoders 2x{agent.embed_dim} -> MLP {list(agent.hidden)}, dueling={agent.dueling}",
            f"3 flattened (row, col) pairs -> MLP net_arch={list(agent.hidden)}",
        ],
        ["batch / buffer", f"{agent.batch_size} / {agent.buffer_size}", f"{agent.batch_size} / {agent.buffer_size}"],
        ["learning_starts", learning_starts, learning_starts],
        [
            "update-to-data",
            f"train_freq={agent.train_freq}, gradient_steps={agent.gradient_steps}",
            f"train_freq={agent.train_freq}, gradient_steps={agent.gradient_steps}",
        ],
        ["target net", ours_target, their_target],
        ["HER", f"{her.strategy}, k={her.k}", f"{her.strategy}, n_sampled_goal={her.k}"],
        [
            "loss / target",
            f"{agent.loss}, double DQN={agent.double_dqn}, {agent.n_step}-step, clipped={agent.clip_targets} (in "
            f"SB3's form: {SB3_FORM_NOTE})",
            "smooth L1, plain one-step DQN target",
        ],
        [
            "reward / gamma",
            f"env reward - {agent.step_cost} per step, gamma={agent.gamma}",
            f"env reward, gamma={agent.gamma}",
        ],
    ]
    out += ["", "Settings compared:", "", markdown_table(["", "ss-drl", "SB3"], parity)]
    return "\n".join(out) + "\n"


def sb3_version() -> str:
    import stable_baselines3

    return stable_baselines3.__version__
