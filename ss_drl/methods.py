"""Method labels, derived from a run's resolved config, never declared: a reader can never mistake one learner for
the other.

``dqn``, ``dqn_her``, ``ss``, ``ss_her``: the replay-only DQN without or with HER (``her.k > 0``) and Smart Start
(``smart_start.eta > 0``); the suffix ``_bounded`` when any of the count model's bounds is on (the model-bounded
DQN); ``tabular`` and ``tabular_ss`` for Keulen's tabular agent; ``frontier`` for the frontier explorer (a baseline
run without HER or Smart Start). Plots, tables, ``summary.json`` and W&B use it, and
it labels run directories written before the learners were named (docs/migration.md) by what they ran.
"""

from __future__ import annotations

from collections.abc import Mapping

from ss_drl.agents.settings import COUNT_MODEL_KEYS


def method_label(config: Mapping) -> str:
    """The method a resolved config (a dict or DictConfig with ``agent``, ``her``, ``smart_start``) runs."""
    agent = config["agent"]
    smart_start = float(config["smart_start"]["eta"]) > 0
    if agent["name"] == "frontier":
        return "frontier"
    if agent["name"] == "tabular":
        return "tabular_ss" if smart_start else "tabular"
    her = int(config["her"]["k"]) > 0
    label = ("ss" if smart_start else "dqn") + ("_her" if her else "")
    return label + ("_bounded" if any(bool(agent.get(key, False)) for key in COUNT_MODEL_KEYS) else "")
