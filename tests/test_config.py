"""Tests of the Hydra configs in conf/ and of ss_drl.training.config.validate_config (all in-process, no training)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from ss_drl.training.config import ConfigError, validate_config

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
YAML_FILES = sorted(CONF.rglob("*.yaml"))
BASE = "easy_small_dqn_her"  # a DQN experiment, so that the DQN-only rules (batch vs buffer) apply

STABLE_KEYS = (
    "seed",
    "env.layout",
    "env.max_steps",
    "trainer.total_env_steps",
    "agent.gamma",
    "her.strategy",
    "her.k",
    "smart_start.eta",
    "smart_start.c_ss",
)


def compose_cfg(experiment: str = BASE, overrides: tuple[str, ...] | list[str] = ()):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=[f"+experiment={experiment}", *overrides])


def method_of(name: str) -> str:
    """The method suffix of an experiment name: easy_small_ss_her -> ss_her."""
    for method in ("tabular_ss", "tabular", "dqn_her", "dqn", "ss_her", "ss"):
        if name.endswith("_" + method):
            return method
    raise AssertionError(f"experiment {name!r} has no known method suffix")


def assert_config_error(cfg, key: str, value) -> str:
    with pytest.raises(ConfigError) as info:
        validate_config(cfg)
    message = str(info.value)
    assert "\n" not in message, f"not one line: {message!r}"
    assert message.startswith(f"{key}:"), f"{message!r} does not name {key}"
    assert str(value) in message, f"{message!r} does not name the bad value {value!r}"
    return message


# --- (a) every experiment composes and validates ---
def test_experiments_found():
    assert EXPERIMENTS == sorted(f"{maze}_{method}" for maze in MAZES for method in METHODS)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_composes_and_validates(name):
    cfg = compose_cfg(name)
    validate_config(cfg)
    assert cfg.experiment == name
    for key in STABLE_KEYS:
        assert OmegaConf.select(cfg, key, default="<missing>") != "<missing>", f"{name}: {key} missing"
    method = method_of(name)
    assert cfg.method == method
    assert name == f"{cfg.env.preset}_{method}"
    assert cfg.env.layout is None
    assert cfg.env.max_steps == 1000
    if method in ("ss", "ss_her", "tabular_ss"):
        assert cfg.smart_start.eta == 1
        assert cfg.smart_start.c_ss == pytest.approx(0.1)
    if method in ("dqn", "dqn_her", "tabular"):
        assert cfg.smart_start.eta == 0
    if method in ("dqn", "ss", "tabular", "tabular_ss"):
        assert cfg.her.k == 0
    if method in ("dqn_her", "ss_her"):
        assert cfg.her.k > 0
        assert cfg.her.strategy == "future"
    assert cfg.agent.name == ("tabular" if method.startswith("tabular") else "dqn")


METHODS = ("dqn", "dqn_her", "ss", "ss_her", "tabular", "tabular_ss")
MAZES = ("easy", "easy_small", "medium_small", "medium", "hard_small", "hard", "extreme")


@pytest.mark.parametrize("method", METHODS)
def test_a_method_is_the_same_setting_on_every_maze(method):
    """One setting per method: the experiments of a method resolve to the same agent, HER and Smart Start settings on
    every maze, so a maze's result is the method's, not a tuning's."""
    settings = {}
    for maze in MAZES:
        cfg = compose_cfg(f"{maze}_{method}")
        settings[maze] = {group: OmegaConf.to_container(cfg[group]) for group in ("agent", "her", "smart_start")}
        settings[maze]["frames_per_batch"] = cfg.trainer.frames_per_batch
    first = settings[MAZES[0]]
    for maze in MAZES[1:]:
        diff = {k: (first[k], v) for k, v in settings[maze].items() if first[k] != v}
        assert not diff, f"{maze}_{method} differs from {MAZES[0]}_{method}: {diff}"


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_an_experiment_only_picks_a_maze_and_a_method(name):
    """conf/experiment/<maze>_<method>.yaml holds the two picks and its name; conf/maze/*.yaml no learning setting."""
    text = yaml.safe_load((CONF / "experiment" / f"{name}.yaml").read_text())
    maze, method = name[: -len(method_of(name)) - 1], method_of(name)
    assert text == {"defaults": [{"/maze": maze}, {"/method": method}], "experiment": name}
    maze_cfg = yaml.safe_load((CONF / "maze" / f"{maze}.yaml").read_text())
    assert set(maze_cfg) == {"defaults", "trainer"}
    assert set(maze_cfg["trainer"]) <= {"total_env_steps", "eval_interval"}


def test_the_smart_start_and_agent_group_defaults_are_the_deep_methods_settings():
    """No experiment or method overrides the dqn agent or Smart Start group: their defaults are the setting."""
    for method in ("dqn", "dqn_her", "ss", "ss_her"):
        text = yaml.safe_load((CONF / "method" / f"{method}.yaml").read_text())
        assert set(text) == {"defaults", "method"}, f"method/{method}.yaml sets more than its groups"


# --- (b) every field carries a one-line comment ---
KEY_LINE = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w-]*):(?P<rest>.*)$")
SKIPPED_BLOCKS = ("hydra", "defaults")


def _uncommented_fields(text: str) -> tuple[list[str], list[str]]:
    """(leaf key paths, offending lines) of a YAML file, parsed line by line; hydra: and defaults: are skipped."""
    lines = text.splitlines()
    leaves, bad = [], []
    stack: list[tuple[int, str]] = []  # (indent, key) of the enclosing mappings
    skip_indent = None
    for number, line in enumerate(lines, start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        indent = len(line) - len(line.lstrip(" "))
        if skip_indent is not None:
            if indent > skip_indent or (indent == skip_indent and line.lstrip().startswith("- ")):
                continue
            skip_indent = None
        match = KEY_LINE.match(line)
        assert match, f"unexpected line {number}: {line!r}"
        key, rest = match["key"], match["rest"]
        while stack and stack[-1][0] >= indent:
            stack.pop()
        if key in SKIPPED_BLOCKS and not rest.strip():
            skip_indent = indent
            continue
        value, _, comment = rest.partition(" #")
        following = next((n for n in lines[number:] if n.strip() and not n.lstrip().startswith("#")), None)
        is_section = not value.strip() and following is not None and len(following) - len(following.lstrip()) > indent
        if is_section:
            stack.append((indent, key))
            continue
        leaves.append(".".join([k for _, k in stack] + [key]))
        if not comment.strip():
            bad.append(f"line {number}: {line.strip()!r}")
    return leaves, bad


def _yaml_leaves(node, prefix="") -> list[str]:
    if isinstance(node, dict) and node:
        out = []
        for key, value in node.items():
            if not prefix and key in SKIPPED_BLOCKS:
                continue
            out += _yaml_leaves(value, f"{prefix}{key}.")
        return out
    return [prefix[:-1]]


@pytest.mark.parametrize("path", YAML_FILES, ids=lambda p: str(p.relative_to(CONF)))
def test_every_field_has_a_comment(path):
    text = path.read_text()
    leaves, bad = _uncommented_fields(text)
    assert not bad, f"{path.relative_to(ROOT)}: fields without a '#' comment: {bad}"
    # the line parser saw every field the YAML parser sees
    assert sorted(leaves) == sorted(_yaml_leaves(yaml.safe_load(text) or {}))


def test_comment_check_catches_a_bare_field():
    leaves, bad = _uncommented_fields("a: 1  # fine\nb:\n  c: 2\n  d: 3  # fine\ndefaults:\n  - x\nhydra:\n  e: 1\n")
    assert leaves == ["a", "b.c", "b.d"]
    assert bad == ["line 3: 'c: 2'"]


# --- (c) one test per validation rule ---
def test_base_config_is_valid():
    validate_config(compose_cfg())


@pytest.mark.parametrize(
    ("override", "key", "value"),
    [
        ("agent.gamma=abc", "agent.gamma", "abc"),
        ("trainer.total_env_steps=1.5", "trainer.total_env_steps", "1.5"),
        ("her.k=2.5", "her.k", "2.5"),
        ("smart_start.eta=high", "smart_start.eta", "high"),
        ("agent.gamma=true", "agent.gamma", "True"),
    ],
)
def test_wrong_type(override, key, value):
    message = assert_config_error(compose_cfg(overrides=[override]), key, value)
    assert "expected" in message


@pytest.mark.parametrize("gamma", ["0", "0.0", "1.5", "-0.5"])
def test_gamma_out_of_range(gamma):
    message = assert_config_error(compose_cfg(overrides=[f"agent.gamma={gamma}"]), "agent.gamma", gamma)
    assert "(0, 1]" in message


@pytest.mark.parametrize("gamma", ["1.0", "1", "0.5"])
def test_gamma_in_range(gamma):
    validate_config(compose_cfg(overrides=[f"agent.gamma={gamma}", "agent.step_cost=1"]))


def test_undiscounted_needs_a_step_cost():
    with pytest.raises(ConfigError, match=r"^agent.gamma: 1 needs agent.step_cost > 0"):
        validate_config(compose_cfg(overrides=["agent.gamma=1", "agent.step_cost=0"]))


def test_bound_all_actions_needs_a_distance_bound():
    with pytest.raises(ConfigError, match=r"^agent.bound_all_actions: needs agent.distance_floor or"):
        validate_config(
            compose_cfg(
                overrides=["agent.bound_all_actions=true", "agent.distance_floor=false", "agent.distance_ceiling=false"]
            )
        )
    validate_config(
        compose_cfg(
            overrides=[
                "agent.bound_all_actions=true",
                "agent.distance_floor=true",
                "agent.distance_ceiling=false",
                "agent.optimistic_floor=false",  # it needs both bounds
            ]
        )
    )
    assert_config_error(compose_cfg(overrides=["agent.bound_all_actions=yes"]), "agent.bound_all_actions", "yes")
    assert_config_error(compose_cfg(overrides=["agent.model_targets=1"]), "agent.model_targets", "1")


def test_optimistic_floor_needs_both_distance_bounds():
    for missing in ("agent.distance_floor", "agent.distance_ceiling"):
        with pytest.raises(ConfigError, match=r"^agent.optimistic_floor: needs agent.distance_floor and"):
            validate_config(
                compose_cfg(
                    overrides=[
                        "agent.optimistic_floor=true",
                        "agent.distance_floor=true",
                        "agent.distance_ceiling=true",
                        f"{missing}=false",
                    ]
                )
            )
    validate_config(
        compose_cfg(
            overrides=["agent.optimistic_floor=true", "agent.distance_floor=true", "agent.distance_ceiling=true"]
        )
    )
    assert_config_error(compose_cfg(overrides=["agent.optimistic_floor=on"]), "agent.optimistic_floor", "on")


@pytest.mark.parametrize("lr_end", ["0", "-0.001", "fast"])
def test_lr_end_must_be_a_positive_number(lr_end):
    assert_config_error(compose_cfg(overrides=[f"agent.lr_end={lr_end}"]), "agent.lr_end", lr_end)


def test_unknown_encoder():
    message = assert_config_error(compose_cfg(overrides=["agent.encoder=pixels"]), "agent.encoder", "pixels")
    for allowed in ("embedding", "coords", "hybrid"):
        assert allowed in message
    validate_config(compose_cfg(overrides=["agent.encoder=hybrid"]))


def test_eval_network_is_online_target_or_average():
    assert_config_error(compose_cfg(overrides=["agent.eval_network=polyak"]), "agent.eval_network", "polyak")


@pytest.mark.parametrize("eval_tau", ["0", "1.5", "slow"])
def test_eval_tau_must_be_a_rate_when_the_average_is_evaluated(eval_tau):
    cfg = compose_cfg(overrides=["agent.eval_network=average", f"agent.eval_tau={eval_tau}"])
    assert_config_error(cfg, "agent.eval_tau", eval_tau)


@pytest.mark.parametrize("eta", ["-0.1", "1.5"])
def test_eta_out_of_range(eta):
    message = assert_config_error(compose_cfg(overrides=[f"smart_start.eta={eta}"]), "smart_start.eta", eta)
    assert "[0, 1]" in message


@pytest.mark.parametrize("eta", ["0", "0.5", "1"])
def test_eta_in_range(eta):
    validate_config(compose_cfg(overrides=[f"smart_start.eta={eta}"]))


def test_negative_c_ss():
    assert_config_error(compose_cfg(overrides=["smart_start.c_ss=-0.1"]), "smart_start.c_ss", "-0.1")
    validate_config(compose_cfg(overrides=["smart_start.c_ss=0"]))


def test_negative_her_k():
    assert_config_error(compose_cfg(overrides=["her.k=-1"]), "her.k", "-1")
    validate_config(compose_cfg(overrides=["her.k=0"]))


def test_unknown_her_strategy():
    message = assert_config_error(compose_cfg(overrides=["her.strategy=sometimes"]), "her.strategy", "sometimes")
    for allowed in ("future", "final", "episode", "random"):
        assert allowed in message


@pytest.mark.parametrize("strategy", ["future", "final", "episode", "random"])
def test_known_her_strategy(strategy):
    validate_config(compose_cfg(overrides=[f"her.strategy={strategy}"]))


def test_unknown_env_preset():
    message = assert_config_error(compose_cfg(overrides=["env.preset=impossible"]), "env.preset", "impossible")
    assert "easy_small" in message


def test_layout_missing_file(tmp_path):
    path = tmp_path / "nowhere.txt"
    message = assert_config_error(compose_cfg(overrides=[f"env.layout='{path}'"]), "env.layout", path)
    assert "not found" in message


def test_layout_malformed_file(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("S..#\n.x..\n...G\n")
    message = assert_config_error(compose_cfg(overrides=[f"env.layout='{path}'"]), "env.layout", path)
    assert f"{path}:2:2" in message
    assert "'x'" in message


def test_layout_valid_file(tmp_path):
    path = tmp_path / "ok.txt"
    path.write_text("S..#\n....\n...G\n")
    validate_config(compose_cfg(overrides=[f"env.layout='{path}'"]))


@pytest.mark.parametrize("steps", ["0", "-5"])
def test_total_env_steps_not_positive(steps):
    message = assert_config_error(
        compose_cfg(overrides=[f"trainer.total_env_steps={steps}"]), "trainer.total_env_steps", steps
    )
    assert "> 0" in message


def test_batch_larger_than_buffer():
    cfg = compose_cfg(overrides=["agent.batch_size=64", "agent.buffer_size=32"])
    message = assert_config_error(cfg, "agent.batch_size", "64")
    assert "agent.buffer_size" in message and "32" in message
    validate_config(compose_cfg(overrides=["agent.batch_size=32", "agent.buffer_size=32"]))
