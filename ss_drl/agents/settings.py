"""The DQN learner's typed settings: the schema of ``conf/agent/dqn.yaml`` and ``conf/agent/dqn_bounded.yaml``.

The YAML files hold each default once (``dqn_bounded`` extends ``dqn``); this dataclass holds each key's type and,
for a key with a fixed set of values, its choices. :meth:`DQNSettings.from_config` checks a composed ``agent``
node against it (unknown or missing keys, types, choices) with one-line errors; the validator
(:mod:`ss_drl.training.config`) then checks the ranges. :class:`~ss_drl.agents.dqn.DQNAgent` is built from a
``DQNSettings``, never from the raw config.
"""

from __future__ import annotations

import dataclasses
import numbers
import typing
from typing import Literal

ENCODERS = ("embedding", "coords", "hybrid")

#: The switches that read the count model: a learner with any of them on is the model-bounded one.
COUNT_MODEL_KEYS = ("distance_floor", "distance_ceiling", "model_targets")


@dataclasses.dataclass(frozen=True)
class DQNSettings:
    """One field per key of the ``agent`` group for the DQN learner; the meanings are in ``conf/agent/dqn.yaml``."""

    name: Literal["dqn"]
    gamma: float
    step_cost: float
    lr: float
    batch_size: int
    buffer_size: int
    encoder: Literal["embedding", "coords", "hybrid"]
    embed_dim: int
    hidden: tuple[int, ...]
    dueling: bool
    loss: Literal["l2", "smooth_l1"]
    double_dqn: bool
    target_update: Literal["hard", "soft"]
    target_update_interval: int
    tau: float
    eval_network: Literal["online", "target"]
    eps_start: float
    eps_end: float
    eps_decay_steps: int
    learning_starts: int
    train_freq: int
    gradient_steps: int
    grad_clip: float
    sparse_tables: bool
    factored_bootstrap: bool
    successor_double_dqn: bool
    n_step: int
    clip_targets: bool
    # The bounds on the TD target (ss_drl/agents/targets.py).
    hindsight_bound: bool
    n_step_max: bool
    distance_floor: bool
    distance_ceiling: bool
    bound_all_actions: bool
    model_targets: bool
    optimistic_floor: bool
    # The policy: greedy on Q for G held to the all-action bounds (DQNAgent.policy_q).
    bounded_policy: bool

    @classmethod
    def from_config(cls, node, prefix: str = "agent") -> DQNSettings:
        """Build from a mapping (an OmegaConf ``agent`` node); ``ValueError`` with one line naming the key on an
        unknown or missing key, a wrong type or a value outside its choices."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        hints = typing.get_type_hints(cls)
        given = dict(node.items())
        for key in given:
            if key not in fields:
                raise ValueError(f"{prefix}.{key}: not a setting of the DQN learner (see conf/agent/dqn.yaml)")
        values = {}
        for key in fields:
            if key not in given:
                raise ValueError(f"{prefix}.{key}: missing from the config")
            values[key] = _typed(f"{prefix}.{key}", given[key], hints[key])
        return cls(**values)

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["hidden"] = list(self.hidden)
        return out


def _typed(key: str, value, kind):
    """``value`` checked against the annotation ``kind`` (and converted: an int where a float is expected, a list
    of ints to a tuple)."""
    if typing.get_origin(kind) is Literal:
        choices = typing.get_args(kind)
        if value not in choices:
            raise ValueError(f"{key}: unknown value {value!r} (allowed: {', '.join(map(str, choices))})")
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{key}: expected true or false, got {value!r} ({type(value).__name__})")
        return value
    if kind is int:
        if not isinstance(value, numbers.Integral) or isinstance(value, bool):
            raise ValueError(f"{key}: expected an integer, got {value!r} ({type(value).__name__})")
        return int(value)
    if kind is float:
        if not isinstance(value, numbers.Real) or isinstance(value, bool):
            raise ValueError(f"{key}: expected a number, got {value!r} ({type(value).__name__})")
        return float(value)
    if typing.get_origin(kind) is tuple:  # tuple[int, ...]: a non-empty list of positive integers (the trunk's widths)
        ok = not isinstance(value, (str, bytes)) and hasattr(value, "__iter__")
        items = list(value) if ok else []
        if not items or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in items):
            raise ValueError(f"{key}: expected a non-empty list of positive integers, got {value!r}")
        return tuple(items)
    raise TypeError(f"{key}: no check for {kind!r}")
