"""Tests of the Hydra configs in conf/ and of ss_drl.training.config.validate_config (all in-process, no training)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from helpers import compose_cfg as compose
from omegaconf import OmegaConf

from ss_drl.agents.settings import COUNT_MODEL_KEYS
from ss_drl.methods import method_label
from ss_drl.training.config import ConfigError, validate_config

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
YAML_FILES = sorted(CONF.rglob("*.yaml"))
BASE = "easy_small_dqn_her"  # a DQN experiment, so that the DQN-only rules (batch vs buffer) apply

#: The deep methods: the replay-only DQN (``<method>``) and the model-bounded one (``<method>_bounded``).
REPLAY_ONLY = ("dqn", "dqn_her", "ss", "ss_her")
BOUNDED = tuple(f"{method}_bounded" for method in REPLAY_ONLY)
METHODS = (*REPLAY_ONLY, *BOUNDED, "tabular", "tabular_ss", "frontier")
MAZES = ("easy", "medium", "hard", "extreme", "easy_small", "medium_small", "hard_small")
#: The MiniGrid groups (conf/minigrid/*.yaml): any task (``minigrid``, env.id on the command line) and the four named.
MINIGRID = {
    "minigrid": "default",
    "fourrooms": "fourrooms",
    "multiroom_n4": "multiroom_n4",
    "multiroom_n6": "multiroom_n6",
    "doorkey_8x8": "doorkey_8x8",
}
#: Every switch of the DQN learner that reads the count model (those that make a learner the model-bounded one, the
#: two that only refine them, and the policy that reads them).
COUNT_MODEL_SWITCHES = (
    "distance_floor",
    "distance_ceiling",
    "model_targets",
    "bound_all_actions",
    "optimistic_floor",
    "bounded_policy",
)

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
    """The config of ``+experiment=<experiment>`` with ``overrides``, as scripts/train.py would compose it."""
    return compose(f"+experiment={experiment}", *overrides)


def method_of(name: str) -> str:
    """The method suffix of an experiment name: easy_small_ss_her -> ss_her, hard_dqn_bounded -> dqn_bounded."""
    for method in sorted(METHODS, key=len, reverse=True):  # the longest first: ss_her_bounded before ss_her and ss
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
    """Every ``<maze>_<method>`` exists for the 7 shipped mazes and the 11 methods, every ``<task>_<method>`` for the
    MiniGrid groups, and nothing else."""
    assert len(METHODS) == 11 and len(MAZES) == 7
    worlds = (*MAZES, *MINIGRID)
    assert EXPERIMENTS == sorted(f"{world}_{method}" for world in worlds for method in METHODS)


def test_method_of_reads_the_longest_suffix():
    assert method_of("easy_small_ss_her_bounded") == "ss_her_bounded"
    assert method_of("hard_ss") == "ss"
    assert method_of("medium_tabular_ss") == "tabular_ss"
    with pytest.raises(AssertionError):
        method_of("easy_ppo")


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_composes_and_validates(name):
    cfg = compose_cfg(name)
    validate_config(cfg)
    assert cfg.experiment == name
    assert "method" not in cfg, "the method label is derived from the config (ss_drl/methods.py), never declared"
    method = method_of(name)
    world = name[: -len(method) - 1]
    for key in STABLE_KEYS:  # a MiniGrid task is named by env.id, a maze by env.layout (or env.preset)
        key = "env.id" if key == "env.layout" and world in MINIGRID else key
        assert OmegaConf.select(cfg, key, default="<missing>") != "<missing>", f"{name}: {key} missing"
    assert method_label(cfg) == method, f"{name} resolves to the method {method_label(cfg)!r}"
    if world in MINIGRID:
        assert cfg.env.id.startswith("MiniGrid-") and cfg.env.layout_seed == cfg.seed
    else:
        assert name == f"{cfg.env.preset}_{method}"
        assert cfg.env.layout is None
    assert cfg.env.max_steps == 1000
    base = method.removesuffix("_bounded")
    if base in ("ss", "ss_her", "tabular_ss"):
        assert cfg.smart_start.eta == 1
        assert cfg.smart_start.c_ss == pytest.approx(0.1)
    if base in ("dqn", "dqn_her", "tabular", "frontier"):
        assert cfg.smart_start.eta == 0
    if base in ("dqn", "ss", "tabular", "tabular_ss", "frontier"):
        assert cfg.her.k == 0
    if base in ("dqn_her", "ss_her"):
        assert cfg.her.k > 0
        assert cfg.her.strategy == "future"
    assert cfg.agent.name == {"tabular": "tabular", "tabular_ss": "tabular", "frontier": "frontier"}.get(method, "dqn")


def _settings(cfg) -> dict:
    settings = {group: OmegaConf.to_container(cfg[group], resolve=True) for group in ("agent", "her", "smart_start")}
    settings["frames_per_batch"] = cfg.trainer.frames_per_batch
    return settings


@pytest.mark.parametrize("method", METHODS)
def test_a_method_is_the_same_setting_on_every_maze(method):
    """One setting per method and learner: the experiments of a method resolve to the same agent, HER and Smart Start
    settings on every shipped maze, so a maze's result is the method's, not a tuning's."""
    settings = {maze: _settings(compose_cfg(f"{maze}_{method}")) for maze in (*MAZES, *MINIGRID)}
    first = settings[MAZES[0]]
    for maze in (*MAZES[1:], *MINIGRID):  # the MiniGrid tasks take the mazes' setting too (issue 50)
        diff = {k: (first[k], v) for k, v in settings[maze].items() if first[k] != v}
        assert not diff, f"{maze}_{method} differs from {MAZES[0]}_{method}: {diff}"


@pytest.mark.parametrize("maze", MAZES)
def test_the_replay_only_dqn_uses_no_count_model_bound_and_the_bounded_one_all(maze):
    """``<maze>_{dqn,dqn_her,ss,ss_her}`` is the replay-only DQN: no switch that reads the count model is on.
    ``<maze>_<method>_bounded`` is the model-bounded DQN: every one is on. The two differ in nothing else than the
    bounds, the k-step maximum (which the bounded one drops) and the update ratio (one update per two env steps for
    the bounded one, whose policy reads the bounds: the notebook, session 51), and each learner is one setting for
    all four methods."""
    assert set(COUNT_MODEL_KEYS) <= set(COUNT_MODEL_SWITCHES)
    agents = {}
    for method in (*REPLAY_ONLY, *BOUNDED):
        agent = OmegaConf.to_container(compose_cfg(f"{maze}_{method}").agent, resolve=True)
        on = {key: agent[key] for key in COUNT_MODEL_SWITCHES}
        if method in REPLAY_ONLY:
            assert not any(on.values()), f"{maze}_{method} (replay-only) has count-model switches on: {on}"
        else:
            assert all(value is True for value in on.values()), f"{maze}_{method} has count-model switches off: {on}"
        agents[method] = agent
    for method in REPLAY_ONLY:  # one agent setting per learner, the same with or without HER and Smart Start
        assert agents[method] == agents[REPLAY_ONLY[0]]
        assert agents[f"{method}_bounded"] == agents[BOUNDED[0]]
    replay_only, bounded = agents[REPLAY_ONLY[0]], agents[BOUNDED[0]]
    differ = sorted(key for key in replay_only if replay_only[key] != bounded[key])
    assert differ == sorted((*COUNT_MODEL_SWITCHES, "n_step_max", "train_freq")), differ
    assert (replay_only["train_freq"], bounded["train_freq"]) == (1, 2)


@pytest.mark.parametrize("method", REPLAY_ONLY)
def test_a_bounded_method_is_its_replay_only_method_with_the_other_learner(method):
    """``<method>_bounded`` runs the same HER and Smart Start as ``<method>``: only the learner differs, and, with
    Smart Start, the exploration phase after S_ss and in the first episode, until G is first reached
    (``smart_start=frontier``, issue 49), in place of the paper's epsilon-greedy phase, which the replay-only methods
    keep for reproduction."""
    for maze in MAZES:
        replay_only = _settings(compose_cfg(f"{maze}_{method}"))
        bounded = _settings(compose_cfg(f"{maze}_{method}_bounded"))
        del replay_only["agent"], bounded["agent"]
        if method.startswith("ss"):
            assert replay_only["smart_start"]["explore"] == "epsilon_greedy"
            exploration = {"explore": "frontier", "explore_from_start": True, "explore_after_goal": False}
            assert bounded["smart_start"] == {**replay_only["smart_start"], **exploration}
            del replay_only["smart_start"], bounded["smart_start"]
        assert replay_only == bounded, f"{maze}_{method} and {maze}_{method}_bounded differ beyond the learner"


def test_the_model_bounded_smart_start_methods_differ_only_in_her():
    """``ss_bounded`` and ``ss_her_bounded`` share the learner and the Smart Start with its exploration phase, so
    that comparing them isolates HER."""
    for maze in MAZES:
        ss, ss_her = (_settings(compose_cfg(f"{maze}_{m}")) for m in ("ss_bounded", "ss_her_bounded"))
        assert ss["smart_start"]["explore"] == "frontier"
        assert ss["smart_start"] == ss_her["smart_start"] and ss["agent"] == ss_her["agent"]


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_an_experiment_only_picks_a_maze_and_a_method(name):
    """conf/experiment/<maze>_<method>.yaml holds the two picks and its name; conf/maze/*.yaml no learning setting;
    nor does conf/minigrid/*.yaml, which sets the task (env.id) and the budget."""
    text = yaml.safe_load((CONF / "experiment" / f"{name}.yaml").read_text())
    maze, method = name[: -len(method_of(name)) - 1], method_of(name)
    group, file = ("minigrid", MINIGRID[maze]) if maze in MINIGRID else ("maze", maze)
    assert text == {"defaults": [{f"/{group}": file}, {"/method": method}], "experiment": name}
    maze_cfg = yaml.safe_load((CONF / group / f"{file}.yaml").read_text())
    assert set(maze_cfg) - {"env"} == {"defaults", "trainer"}
    assert set(maze_cfg.get("env", {})) <= {"id"}
    assert set(maze_cfg["trainer"]) <= {"total_env_steps", "eval_interval"}


def test_the_smart_start_and_agent_group_defaults_are_the_deep_methods_settings():
    """No deep method sets a value of its own: it picks the learner (agent=dqn or agent=dqn_bounded), HER and Smart
    Start, whose group defaults are the setting; and it declares no label (ss_drl/methods.py derives it)."""
    for method in (*REPLAY_ONLY, *BOUNDED):
        text = yaml.safe_load((CONF / "method" / f"{method}.yaml").read_text())
        assert set(text) == {"defaults"}, f"method/{method}.yaml sets more than its groups"
        learner = "dqn_bounded" if method.endswith("_bounded") else "dqn"
        assert {"override /agent": learner} in text["defaults"], f"method/{method}.yaml does not pick agent={learner}"


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


@pytest.mark.parametrize("hidden", ["[]", "[0]", "[64,-1]", "[true]", "64"])
def test_the_trunk_needs_at_least_one_layer_of_positive_width(hidden):
    """``agent.hidden=[]`` passed the check and then crashed at the first evaluation (the trunk had no first layer)."""
    message = assert_config_error(compose_cfg("easy_ss_her", [f"agent.hidden={hidden}"]), "agent.hidden", "")
    assert "expected a non-empty list of positive integers" in message


@pytest.mark.parametrize("override", ["env.slip=nan", "agent.lr=nan", "agent.tau=inf", "smart_start.c_ss=-inf"])
def test_a_number_that_is_not_finite_is_refused(override):
    """NaN passed every range check (all comparisons with it are false): env.slip=nan reached the trainer and raised
    there, a traceback."""
    key, value = override.split("=")
    message = assert_config_error(compose_cfg(overrides=[override]), key, value)
    assert "expected a finite number" in message


@pytest.mark.parametrize("gamma", ["0", "0.0", "1.5", "-0.5"])
def test_gamma_out_of_range(gamma):
    message = assert_config_error(compose_cfg(overrides=[f"agent.gamma={gamma}"]), "agent.gamma", gamma)
    assert "(0, 1]" in message


@pytest.mark.parametrize("gamma", ["1.0", "1", "0.5"])
def test_gamma_in_range(gamma):
    validate_config(compose_cfg(overrides=[f"agent.gamma={gamma}", "agent.step_cost=1"]))


def test_the_frontier_explorer_has_only_its_own_keys():
    """conf/agent/frontier.yaml has no epsilon and no learning rate: a key of another learner is refused, by name."""
    validate_config(compose_cfg("easy_small_frontier"))
    for key, value in (("eps_start", "0.1"), ("alpha", "0.1")):
        message = assert_config_error(
            compose_cfg("easy_small_frontier", [f"++agent.{key}={value}"]), f"agent.{key}", key
        )
        assert "name, gamma" in message


def test_the_frontier_explorer_needs_gamma_below_1():
    message = assert_config_error(compose_cfg("easy_small_frontier", ["agent.gamma=1"]), "agent.gamma", "1")
    assert "(0, 1)" in message
    validate_config(compose_cfg("easy_small_frontier", ["agent.gamma=0.9"]))


@pytest.mark.parametrize(
    ("override", "key", "value"),
    [
        ("smart_start=on", "smart_start.eta", "1.0"),
        ("her.k=4", "her.k", "4"),
        ("trainer.frames_per_batch=16", "trainer.frames_per_batch", "16"),
    ],
)
def test_the_frontier_explorer_runs_alone_and_sees_every_move(override, key, value):
    """No Smart Start and no HER (the label ``frontier`` would hide them), and at most one step per batch (its memory
    must hold each move before it picks the next)."""
    assert_config_error(compose_cfg("easy_small_frontier", [override]), key, value)
    validate_config(compose_cfg("easy_small_frontier", ["env.num_envs=4", "trainer.frames_per_batch=4"]))


def test_greedy_path_needs_deterministic_moves():
    """It walks one observed successor per move: refused under slips, before training; allowed without them."""
    cfg = compose_cfg("easy_small_ss_her_bounded", ["smart_start.greedy_path=true", "env.slip=0.1"])
    with pytest.raises(
        ConfigError, match=r"^smart_start.greedy_path: true needs deterministic moves \(env.slip is 0.1\)"
    ):
        validate_config(cfg)
    validate_config(compose_cfg("easy_small_ss_her_bounded", ["smart_start.greedy_path=true"]))
    with pytest.raises(ConfigError, match=r"^smart_start.greedy_path: expected true or false"):
        validate_config(compose_cfg("easy_small_ss_her_bounded", ["smart_start.greedy_path=2"]))


def test_undiscounted_needs_a_step_cost():
    with pytest.raises(ConfigError, match=r"^agent.gamma: 1 needs agent.step_cost > 0"):
        validate_config(compose_cfg(overrides=["agent.gamma=1", "agent.step_cost=0"]))


def test_sparse_tables_needs_a_table_and_polyak_targets():
    """Refused before training (exit 2, nothing written), not when the agent is built (it was a traceback-free but
    late exit 1): the lazy Polyak step needs soft target updates, and the coords encoder has no per-cell table."""
    with pytest.raises(ConfigError, match=r"^agent.sparse_tables: needs agent.target_update=soft"):
        validate_config(compose_cfg(overrides=["agent.sparse_tables=true", "agent.target_update=hard"]))
    with pytest.raises(ConfigError, match=r"^agent.sparse_tables: the 'coords' encoder has no per-cell table"):
        validate_config(compose_cfg(overrides=["agent.sparse_tables=true", "agent.encoder=coords"]))
    for encoder in ("hybrid", "embedding"):
        validate_config(compose_cfg(overrides=["agent.sparse_tables=true", f"agent.encoder={encoder}"]))


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


def test_bounded_policy_needs_the_bounds_on_every_action():
    with pytest.raises(ConfigError, match=r"^agent.bounded_policy: needs agent.bound_all_actions"):
        validate_config(compose_cfg("easy_ss_her", ["agent.bounded_policy=true"]))  # replay-only: no all-action bound
    validate_config(compose_cfg("easy_ss_her_bounded", ["agent.bounded_policy=true"]))
    assert_config_error(compose_cfg(overrides=["agent.bounded_policy=1"]), "agent.bounded_policy", "1")


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


@pytest.mark.parametrize("key", ["agent.distance_floor", "agent.distance_ceiling"])
def test_turning_a_bound_off_under_slips_is_not_refused_for_a_companion_the_slips_turn_off(key):
    """Under slips every count-model bound is turned off when the run starts, so a user turning one of them off on
    the command line must not be refused because ``optimistic_floor`` (on by default, off under slips) needs it.
    It was: the combination checks read the config as given, not the bounds in force. With deterministic moves the
    same override is still refused, since there the optimistic floor stays on."""
    validate_config(compose_cfg("easy_ss_her_bounded", ["env.slip=0.1", f"{key}=false"]))
    with pytest.raises(ConfigError, match=r"^agent.optimistic_floor: needs agent.distance_floor and"):
        validate_config(compose_cfg("easy_ss_her_bounded", [f"{key}=false"]))


def test_unknown_encoder():
    message = assert_config_error(compose_cfg(overrides=["agent.encoder=pixels"]), "agent.encoder", "pixels")
    for allowed in ("embedding", "coords", "hybrid"):
        assert allowed in message
    validate_config(compose_cfg(overrides=["agent.encoder=hybrid"]))


@pytest.mark.parametrize("value", ["polyak", "average"])
def test_eval_network_is_online_or_target(value):
    """``average`` (with ``eval_tau``) was deleted: it is refused like any other unknown value, naming the choices."""
    message = assert_config_error(compose_cfg(overrides=[f"agent.eval_network={value}"]), "agent.eval_network", value)
    assert "online" in message and "target" in message
    for allowed in ("online", "target"):
        validate_config(compose_cfg(overrides=[f"agent.eval_network={allowed}"]))


@pytest.mark.parametrize(
    ("key", "value"),
    [("lr_end", "0.0001"), ("eval_tau", "0.01"), ("advantage_learning", "true")],
)
def test_deleted_options_are_refused(key, value):
    """A deleted option given with ``+`` (the composed config no longer has it) is refused, naming the key."""
    assert key not in compose_cfg().agent
    assert_config_error(compose_cfg(overrides=[f"+agent.{key}={value}"]), f"agent.{key}", "not a setting")


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


def test_a_buffer_smaller_than_one_collection_batch_is_refused():
    """The HER buffer stores whole steps of the env copies (ceil(buffer_size / num_envs) of them), and each
    collection batch is written whole (frames_per_batch // num_envs steps): accepted, a smaller buffer crashed at
    the first write, after the run directory was made."""
    with pytest.raises(ConfigError) as info:
        validate_config(compose_cfg(overrides=["agent.batch_size=8", "agent.buffer_size=8"]))  # 8 steps < 16
    assert str(info.value) == (
        "agent.buffer_size: 8 holds 8 steps of the 1 env copies, fewer than one collection batch "
        "(trainer.frames_per_batch 16: 16 steps)"
    )
    # 4 copies: 15 transitions are ceil(15 / 4) = 4 steps, and 16 frames are 4 steps: it fits; 13 (4 steps) too, and
    # 12 (3 steps) does not.
    for buffer in (15, 13):
        validate_config(compose_cfg(overrides=["env.num_envs=4", "agent.batch_size=8", f"agent.buffer_size={buffer}"]))
    with pytest.raises(ConfigError, match=r"^agent.buffer_size: 12 holds 3 steps of the 4 env copies"):
        validate_config(compose_cfg(overrides=["env.num_envs=4", "agent.batch_size=8", "agent.buffer_size=12"]))
    validate_config(compose_cfg(overrides=["agent.batch_size=8", "agent.buffer_size=16"]))  # one batch exactly


# --- (c2) an override of a key the config does not have: one line before Hydra composes anything ---
def _refusal(check):
    """``refused(*argv)``: the one-line ConfigError message of the command-line ``check`` on ``argv``."""

    def refused(*argv: str) -> str:
        with pytest.raises(ConfigError) as info:
            check(list(argv), CONF)
        message = str(info.value)
        assert "\n" not in message, message
        return message

    return refused


def test_an_override_of_a_key_the_config_lacks_is_refused_naming_the_nearest():
    """Hydra refuses ``agent.lrr=0.1`` too, in seven lines with exit code 1; this is the one line."""
    from ss_drl.cli import check_override_keys

    refused = _refusal(check_override_keys)

    assert refused("+experiment=easy_ss_her", "agent.lrr=0.1") == (
        "agent.lrr: no such key in the config; did you mean agent.lr?"
    )
    # A key added with + or ++ is refused in every section: Hydra accepts it, and no run would read it (the audit of
    # session 47 found +trainer.total_env_step=500 running to the end with the default budget, exit 0).
    assert refused("+experiment=easy_ss_her", "+trainer.total_env_step=500") == (
        "trainer.total_env_step: no such key in the config; did you mean trainer.total_env_steps?"
    )
    for added in ("+env.foo=1", "++smart_start.foo=1", "+her.foo=1", "+logger.foo=1", "+agent.lrr=0.1"):
        assert refused("+experiment=easy_ss_her", added).startswith(f"{added.lstrip('+').split('=')[0]}: no such key")
    assert refused("+foo=1") == "foo: no such key in the config (the README's Configuration table lists them)"
    # +key for a key the config has: Hydra's "Could not append to config", in one line.
    assert refused("+experiment=easy_ss_her", "+trainer.total_env_steps=5") == (
        "trainer.total_env_steps: already in the config; set it without the +: trainer.total_env_steps=..."
    )
    assert refused("agentt.lr=0.1") == "agentt.lr: no such key in the config (agentt is not a section of it)"
    assert refused("+experiment=easy_ss_her", "trainer.eval_interva=5").startswith(
        "trainer.eval_interva: no such key in the config; did you mean trainer.eval_interval or "
    )
    # Checked against the config of the groups chosen: the tabular agent has alpha, the DQN none.
    assert refused("+experiment=easy_ss_her", "agent.alpha=0.5").startswith("agent.alpha: no such key in the config")
    # A sweep is checked once per combination of its groups' choices, whatever their order, naming the one that
    # lacks the key.
    for order in (["easy_ss_her", "easy_tabular_ss"], ["easy_tabular_ss", "easy_ss_her"]):
        assert refused("-m", f"+experiment={','.join(order)}", "agent.alpha=0.5") == (
            "agent.alpha: no such key in the config of the sweep's +experiment=easy_ss_her"
        )
    for ok in (
        ["-m", "+experiment=easy_ss_her,easy_ss", "agent.lr=0.1"],  # every choice has it
        ["experiment=easy_ss", "agent.lr=0.1"],  # not composable (a group chosen without +): Hydra's own report
        ["=x", "agent.lr=1"],
        ["-sc", "install=bash"],  # Hydra's shell completion
        ["+experiment=easy_ss_her", "agent=tabular", "agent.alpha=0.5", "seed=range(3)"],
        ["+experiment=easy_ss_her", "logger=wandb", "logger.mode=online", "agent.lr=0.01"],
        ["-m", "+experiment=easy_ss,easy_ss_her", "agent.hidden=[64,64]", "env.layout=x.txt"],
        ["+experiment=easy_ss_her", "++trainer.eval_interval=2", "~trainer.resume"],  # ++ of a key it has; removal
        ["hydra.run.dir=/tmp/x=y", "hydra.launcher.n_jobs=2"],  # Hydra's own keys
        ["+experiment@x=glob(*)", "agent.lrr=1"],  # a group chosen by a sweep function: Hydra expands it
        ["--config-dir", "/elsewhere", "agent.lrr=1"],  # another search path: Hydra's to check
    ):
        check_override_keys(ok, CONF)


# --- (d) a config group choice that names no file: one line before Hydra composes anything ---
def test_an_unknown_group_choice_is_refused_naming_the_group():
    from ss_drl.cli import check_group_choices

    refused = _refusal(check_group_choices)

    message = refused("+experiment=no_such_name", "seed=1")
    assert message.startswith("experiment: unknown value 'no_such_name' (no ") and str(CONF / "experiment") in message
    assert refused("agent=dqn_bound").endswith("did you mean dqn_bounded?")
    assert "'medum_ss'" in refused("-m", "+experiment=easy_ss,medum_ss")  # sweep lists: item by item
    assert "the choices: " in refused("+experiment=easy_ss", "her=sometimes")  # a small group lists its choices
    # Hydra's three-line reports (exit 1) for a group outside the defaults list chosen without +, and a group chosen
    # twice, in one line each.
    assert refused("experiment=easy_ss_her") == (
        "experiment: not in the default config; choose it with +experiment=easy_ss_her"
    )
    assert refused("+experiment=easy_ss_her", "+experiment=medium_ss_her") == (
        "experiment: chosen twice (+experiment=easy_ss_her and +experiment=medium_ss_her); give it once, or sweep "
        "both with -m +experiment=easy_ss_her,medium_ss_her"
    )
    assert refused("maze=easy").startswith("maze: not in the default config")
    for ok in (
        ["+experiment=easy_ss_her_bounded", "agent=dqn", "agent.lr=0.01", "env.layout=x.txt"],
        ["-m", "+experiment=easy_ss,easy_ss_her", "seed=range(3)", "+experiment@x=glob(*)"],
        ["hydra/launcher=submitit_local", "hydra.run.dir=/tmp/x=y"],  # Hydra's own groups are Hydra's to check
        ["--config-dir", "/elsewhere", "+experiment=only_there"],  # another search path: Hydra's to check
    ):
        check_group_choices(ok, CONF)


def test_an_override_hydra_cannot_read_is_refused_in_one_line():
    from ss_drl.cli import check_overrides_parse

    refused = _refusal(lambda argv, conf: check_overrides_parse(argv))
    assert refused("+experiment=easy_ss_her", "agent.hidden=[1,2") == (
        "agent.hidden=[1,2: not an override Hydra can read (no viable alternative at input '[1,2'; the grammar: "
        "https://hydra.cc/docs/advanced/override_grammar/basic/)"
    )
    assert refused("seed=range(3").startswith("seed=range(3: not an override Hydra can read (")
    for ok in (
        ["-m", "+experiment=easy_ss,easy_ss_her", "seed=range(3)", "agent.hidden=[64,64]", "~trainer.resume"],
        ["hydra.run.dir=/tmp/x=y", "-cd", "/elsewhere"],  # another search path: Hydra's to check
    ):
        check_overrides_parse(ok)


# --- the README's configuration reference -----------------------------------------------------------------------------
def _leaf_keys(node, prefix: str = "") -> set[str]:
    keys = set()
    for key in node:
        value = node._get_node(key)
        dotted = f"{prefix}{key}"
        keys |= _leaf_keys(value, f"{dotted}.") if OmegaConf.is_dict(value) else {dotted}
    return keys


def test_the_readme_configuration_reference_names_every_key():
    """Every key of every learner's, logger's and world's composed config has its own line in the README's
    Configuration table (a key added to a YAML without a line there fails here; a row naming two keys fails too), and
    the table names no key that does not exist."""
    keys = set()
    for overrides in (
        ["+experiment=easy_ss_her"], ["+experiment=easy_ss_her_bounded"], ["+experiment=easy_tabular_ss"],
        ["+experiment=easy_frontier"], ["+experiment=minigrid_ss_her"], ["+experiment=easy_ss_her", "logger=wandb"],
    ):  # fmt: skip
        keys |= {k for k in _leaf_keys(compose(*overrides)) if not k.startswith("hydra")}
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## Configuration\n") : readme.index("## Outputs\n")]
    table = [line for line in section.splitlines() if line.startswith("| `")]
    per_row = [re.findall(r"`([a-z_]+(?:\.[a-z_]+)+|seed|experiment)`", line.split(" | ")[0]) for line in table]
    assert [row for row in per_row if len(row) != 1] == [], "one line per key"
    named = {row[0] for row in per_row}
    assert len(named) == len(per_row), "a key has two lines"
    assert sorted(keys - named) == []
    assert sorted(named - keys) == []
