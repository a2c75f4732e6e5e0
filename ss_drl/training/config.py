"""Validation of a composed config before anything is trained or written.

Every problem is reported as one line naming the key, the bad value and what is allowed, as :class:`ConfigError`.
"""

from __future__ import annotations

import math
import numbers

from omegaconf import DictConfig

from ss_drl.agents.settings import DQNSettings
from ss_drl.agents.targets import environment_assumptions, resolve_bounds
from ss_drl.envs.maze import PRESETS, MazeError, load_maze
from ss_drl.her import STRATEGIES, storage_rows
from ss_drl.smart_start.controller import SmartStart


class ConfigError(ValueError):
    """A config value that cannot be used. ``str(err)`` is the one-line message for the user."""


def _get(cfg: DictConfig, key: str):
    node = cfg
    for part in key.split("."):
        if not isinstance(node, DictConfig) or part not in node:
            raise ConfigError(f"{key}: missing from the config")
        node = node[part]
    return node


def _range(low, high, low_open: bool, high_open: bool) -> str:
    if low is not None and high is not None:
        return f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {low}"
    return f"{'<' if high_open else '<='} {high}"


def _number(cfg, key: str, low=None, high=None, low_open=False, high_open=False, integer=False):
    value = _get(cfg, key)
    kind = "an integer" if integer else "a number"
    ok_type = isinstance(value, numbers.Integral if integer else numbers.Real) and not isinstance(value, bool)
    if not ok_type:
        raise ConfigError(f"{key}: expected {kind}, got {value!r} ({type(value).__name__})")
    if not math.isfinite(value):
        raise ConfigError(f"{key}: expected a finite number, got {value!r}")
    bad_low = low is not None and (value <= low if low_open else value < low)
    bad_high = high is not None and (value >= high if high_open else value > high)
    if bad_low or bad_high:
        raise ConfigError(f"{key}: {value!r} is out of range (allowed: {_range(low, high, low_open, high_open)})")
    return value


def _choice(cfg, key: str, allowed) -> str:
    value = _get(cfg, key)
    if value not in allowed:
        raise ConfigError(f"{key}: unknown value {value!r} (allowed: {', '.join(map(str, allowed))})")
    return value


def _boolean(cfg, key: str) -> bool:
    value = _get(cfg, key)
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: expected true or false, got {value!r} ({type(value).__name__})")
    return value


def _command_line_keys(cfg: DictConfig, prefix: str) -> list[str]:
    """The keys under ``prefix`` that the command line set (``key=value``, ``+key=value``, ``++key=value``)."""
    try:
        if "hydra" in cfg:
            task = list(cfg.hydra.overrides.task)
        else:
            from hydra.core.hydra_config import HydraConfig

            task = list(HydraConfig.get().overrides.task)
    except (ValueError, AttributeError, KeyError):  # no Hydra run (a test composing the config itself)
        return []
    keys = (o.split("=", 1)[0].lstrip("+~") for o in task)
    return [k[len(prefix) :] for k in keys if k.startswith(prefix)]


#: The frontier explorer's settings (conf/agent/frontier.yaml): it has no epsilon and no learning rate.
FRONTIER_KEYS = ("name", "gamma")


def _frontier_run(cfg: DictConfig) -> None:
    """The frontier explorer runs alone, and sees each transition before its next move."""
    if cfg.smart_start.eta > 0:
        raise ConfigError(
            f"smart_start.eta: {cfg.smart_start.eta!r} is out of range for the frontier explorer (allowed: 0; it "
            "chooses its own route to the frontier)"
        )
    if cfg.her.k > 0:
        raise ConfigError(
            f"her.k: {cfg.her.k!r} is out of range for the frontier explorer (allowed: 0; it has no replay)"
        )
    if float(cfg.env.get("slip", 0)) > 0:
        raise ConfigError(
            f"env.slip: {cfg.env.slip!r} is out of range for the frontier explorer (allowed: 0; its memory holds "
            "one successor per move: it assumes deterministic moves)"
        )
    if cfg.trainer.frames_per_batch > cfg.env.num_envs:
        raise ConfigError(
            f"trainer.frames_per_batch: {cfg.trainer.frames_per_batch!r} is out of range for the frontier explorer "
            f"(allowed: <= env.num_envs = {cfg.env.num_envs}: its memory must hold each move before it picks the next)"
        )


def validate_config(cfg: DictConfig) -> None:
    """Check every value a run uses; raise :class:`ConfigError` on the first bad one."""
    _number(cfg, "seed", low=0, integer=True)
    # env
    _number(cfg, "env.slip", low=0, high=1)  # before the MiniGrid check, which reads it
    if cfg.env.get("id") not in (None, ""):
        _minigrid_env(cfg)
    else:
        _maze_env(cfg)
    _number(cfg, "env.max_steps", low=1, integer=True)
    _number(cfg, "env.num_envs", low=1, integer=True)
    _trainer_and_learner(cfg)


def _minigrid_env(cfg: DictConfig) -> None:
    """A MiniGrid task: its id, layout seed and state cap, and the task itself (built here, so that an unsupported
    task or one with too many states is refused before the run starts)."""
    from ss_drl.envs.minigrid import MiniGridError, minigrid_task

    if not isinstance(cfg.env.id, str):
        raise ConfigError(f"env.id: expected a MiniGrid id such as MiniGrid-FourRooms-v0, got {cfg.env.id!r}")
    seed = _number(cfg, "env.layout_seed", low=0, integer=True)
    cap = _number(cfg, "env.max_states", low=1, integer=True)
    if cfg.env.slip > 0:
        raise ConfigError(f"env.slip: {cfg.env.slip!r} is out of range for a MiniGrid task (allowed: 0)")
    try:
        minigrid_task(cfg.env.id, int(seed), int(cap))
    except MiniGridError as exc:
        raise ConfigError(str(exc)) from None


def _maze_env(cfg: DictConfig) -> None:
    layout = _get(cfg, "env.layout")
    if layout in (None, ""):
        _choice(cfg, "env.preset", PRESETS)
        target = cfg.env.preset
    else:
        if not isinstance(layout, str):
            raise ConfigError(f"env.layout: expected a path to a maze file, got {layout!r}")
        target = layout
    try:
        load_maze(target)
    except MazeError as exc:
        key = "env.preset" if layout in (None, "") else "env.layout"
        raise ConfigError(f"{key}: {exc}") from None


def _trainer_and_learner(cfg: DictConfig) -> None:
    # trainer
    _number(cfg, "trainer.total_env_steps", low=0, low_open=True, integer=True)
    _number(cfg, "trainer.frames_per_batch", low=1, integer=True)
    _number(cfg, "trainer.eval_interval", low=1, integer=True)
    if _get(cfg, "trainer.eval_episodes") is not None:
        _number(cfg, "trainer.eval_episodes", low=1, integer=True)
    _number(cfg, "trainer.checkpoint_interval", low=1, integer=True)
    _number(cfg, "trainer.log_interval", low=1, integer=True)
    _number(cfg, "trainer.torch_threads", low=1, integer=True)
    resume = _get(cfg, "trainer.resume")
    if not isinstance(resume, (bool, str)) and resume is not None:
        raise ConfigError(f"trainer.resume: expected true, false, auto or a run directory, got {resume!r}")
    # agent
    name = _choice(cfg, "agent.name", ("dqn", "tabular", "frontier"))
    # The frontier explorer's values gamma^steps must fall with the steps to the goal: gamma 1 is refused for it.
    _number(cfg, "agent.gamma", low=0, high=1, low_open=True, high_open=name == "frontier")
    if name == "frontier":  # no epsilon; HER, Smart Start and the batch are checked with the rest (_frontier_run)
        unknown = sorted(set(cfg.agent) - set(FRONTIER_KEYS))
        if unknown:
            raise ConfigError(
                f"agent.{unknown[0]}: not a setting of the frontier explorer (its keys: {', '.join(FRONTIER_KEYS)})"
            )
    else:
        _number(cfg, "agent.eps_start", low=0, high=1)
        _number(cfg, "agent.eps_end", low=0, high=1)
        _number(cfg, "agent.eps_decay_steps", low=1, integer=True)
    if name == "tabular":
        _number(cfg, "agent.alpha", low=0, high=1, low_open=True)
    elif name == "dqn":
        # Types, choices and unknown keys: the typed settings' schema. Ranges and combinations: here.
        try:
            settings = DQNSettings.from_config(cfg.agent)
            # A bound the user turned on that this environment cannot support is refused here; one that comes with
            # the learner's defaults is turned off when the run starts (ss_drl.training.trainer.dqn_settings).
            # The combinations below are checked on the bounds that will be in force, so that turning one off on
            # the command line is not refused for a companion that this environment turns off anyway.
            agent, _ = resolve_bounds(
                settings, environment_assumptions(cfg.env), explicit=_command_line_keys(cfg, "agent.")
            )
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        _number(cfg, "agent.lr", low=0, low_open=True)
        batch = _number(cfg, "agent.batch_size", low=1, integer=True)
        buffer = _number(cfg, "agent.buffer_size", low=1, integer=True)
        if batch > buffer:
            raise ConfigError(f"agent.batch_size: {batch} is larger than agent.buffer_size ({buffer})")
        # The HER buffer stores whole steps of the env copies, and one collection batch must fit in it.
        copies = int(cfg.env.num_envs)
        rows, batch_rows = storage_rows(buffer, copies), max(1, int(cfg.trainer.frames_per_batch) // copies)
        if batch_rows > rows:
            raise ConfigError(
                f"agent.buffer_size: {buffer} holds {rows} steps of the {copies} env copies, fewer than one collection "
                f"batch (trainer.frames_per_batch {cfg.trainer.frames_per_batch}: {batch_rows} steps)"
            )
        _number(cfg, "agent.embed_dim", low=1, integer=True)
        _number(cfg, "agent.target_update_interval", low=1, integer=True)
        _number(cfg, "agent.tau", low=0, high=1, low_open=True)
        _number(cfg, "agent.learning_starts", low=0, integer=True)
        _number(cfg, "agent.train_freq", low=1, integer=True)
        _number(cfg, "agent.gradient_steps", low=1, integer=True)
        _number(cfg, "agent.grad_clip", low=0)
        _number(cfg, "agent.step_cost", low=0)
        _number(cfg, "agent.n_step", low=1, integer=True)
        if agent.bound_all_actions and not (agent.distance_floor or agent.distance_ceiling):
            raise ConfigError("agent.bound_all_actions: needs agent.distance_floor or agent.distance_ceiling")
        if agent.optimistic_floor and not (agent.distance_floor and agent.distance_ceiling):
            raise ConfigError("agent.optimistic_floor: needs agent.distance_floor and agent.distance_ceiling")
        if agent.bounded_policy and not agent.bound_all_actions:
            raise ConfigError("agent.bounded_policy: needs agent.bound_all_actions (the bounds on every action)")
        if agent.sparse_tables and agent.target_update != "soft":
            raise ConfigError("agent.sparse_tables: needs agent.target_update=soft (its Polyak step is lazy)")
        if agent.sparse_tables and agent.encoder == "coords":
            raise ConfigError(
                "agent.sparse_tables: the 'coords' encoder has no per-cell table (use hybrid or embedding)"
            )
        if agent.gamma == 1 and agent.step_cost == 0:
            raise ConfigError("agent.gamma: 1 needs agent.step_cost > 0 (undiscounted 0/1 rewards make every value 1)")
    # HER
    _choice(cfg, "her.strategy", STRATEGIES)
    _number(cfg, "her.k", low=0, integer=True)
    # Smart Start
    _number(cfg, "smart_start.eta", low=0, high=1)
    _number(cfg, "smart_start.guided_epsilon", low=0, high=1)
    _number(cfg, "smart_start.c_ss", low=0)
    _number(cfg, "smart_start.w_q", low=0)
    _number(cfg, "smart_start.theta", low=0, integer=True)
    _number(cfg, "smart_start.gamma", low=0, high=1, low_open=True, high_open=True)
    _number(cfg, "smart_start.tol", low=0, low_open=True)
    _number(cfg, "smart_start.max_sweeps", low=1, integer=True)
    if _get(cfg, "smart_start.guided_limit") is not None:
        _number(cfg, "smart_start.guided_limit", low=1)
    _choice(cfg, "smart_start.select", SmartStart.SELECT)
    _choice(cfg, "smart_start.explore", SmartStart.EXPLORE)
    _boolean(cfg, "smart_start.explore_after_goal")
    _boolean(cfg, "smart_start.explore_from_start")
    _boolean(cfg, "smart_start.greedy_path")
    if cfg.smart_start.greedy_path and "deterministic" not in environment_assumptions(cfg.env):
        raise ConfigError(
            "smart_start.greedy_path: true needs deterministic moves (env.slip is "
            f"{cfg.env.slip!r}): it walks one observed successor per move"
        )
    if name == "frontier":
        _frontier_run(cfg)
    # logger
    _choice(cfg, "logger.backend", ("csv", "wandb"))
    _choice(cfg, "logger.mode", ("offline", "online", "disabled"))
