"""The goal-conditioned DQN: GoalDQNLoss equals TorchRL's DQNLoss, target updates reach the lean target network, and
the TD target's parts (``ss_drl/agents/targets.py``), as the agent builds them, give the targets computed by hand.

The target tests build a batch, read the targets through the agent's own parts (``agent.td_target.taken`` and
``.others`` with ``agent.loss.bootstrap``, each bound's ``lower``/``upper``/``lower_all``/``upper_all``) and compare
them with numbers written out or computed here from the maze's geometry, then compare ``agent.loss(batch)`` with the
loss composed by hand from those numbers. Where a target network's values are needed they are a hand table
(:func:`use_table`): that is input, not a reading of the code.
"""

from __future__ import annotations

import warnings
from functools import partial

import pytest
import torch
from helpers import NO_COUNT_MODEL, compose_cfg
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import Categorical
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate

from ss_drl.agents.dqn import DQNAgent, PolyakUpdate, value_range
from ss_drl.agents.network import CellEncoder
from ss_drl.agents.settings import DQNSettings
from ss_drl.agents.targets import (
    DistanceCeiling,
    DistanceFloor,
    HindsightBound,
    NStepMax,
    environment_assumptions,
    make_td_target,
)
from ss_drl.envs.maze import load_maze
from ss_drl.her import HindsightReplayBuffer
from ss_drl.smart_start import CountModel
from ss_drl.training.greedy import greedy_accuracy, greedy_policy

#: The plain DQN these tests compute by hand (0/1 rewards, gamma < 1, TD(0), no clipping); each test adds its own.
PLAIN = {  # TD(0) on 0/1 rewards with hard target copies: the setting the hand computations below are written for
    "agent.gamma": "0.95",
    "agent.step_cost": "0",
    "agent.n_step": "1",
    "agent.clip_targets": "false",
    "agent.target_update": "hard",
    "agent.hindsight_bound": "false",
    "agent.n_step_max": "false",
    **dict(o.split("=", 1) for o in NO_COUNT_MODEL),
}
#: The shortest-path form (-1 per step, 0 on entering the goal, no discount) with the target network's max.
SHORTEST_PATH = ("agent.step_cost=1", "agent.gamma=1", "agent.double_dqn=false")
INF = float("inf")


def agent_settings(*overrides: str):
    """The composed config and the typed settings of ``+experiment=easy_small_dqn_her`` with :data:`PLAIN` and
    ``overrides``."""
    settings = dict(PLAIN, **dict(o.split("=", 1) for o in overrides))
    cfg = compose_cfg("+experiment=easy_small_dqn_her", *(f"{k}={v}" for k, v in settings.items()))
    return cfg, DQNSettings.from_config(cfg.agent)


def make_agent(*overrides: str, counts: CountModel | None = None) -> DQNAgent:
    """The agent as the trainer builds it (``ss_drl.training.trainer.make_agent``): typed settings, a HER buffer
    that records what the bounds need, and the TD target with the count model ``counts``."""
    cfg, settings = agent_settings(*overrides)
    maze = load_maze("easy_small")
    buffer = HindsightReplayBuffer(
        1000,
        1,
        settings.batch_size,
        k=0,
        n_step=settings.n_step,
        gamma=settings.gamma,
        goal_steps=settings.hindsight_bound,
        window_states=settings.n_step_max,
    )
    max_steps = cfg.env.max_steps
    clip = value_range(settings.gamma, settings.step_cost, max_steps) if settings.clip_targets else None
    td_target = make_td_target(settings, maze, counts, clip or None, holds=environment_assumptions(cfg.env))
    torch.manual_seed(0)
    return DQNAgent(settings, maze, buffer, td_target, max_steps=max_steps)


def bound(agent: DQNAgent, kind: type):
    """The agent's one bound of type ``kind``."""
    (found,) = [b for b in agent.td_target.bounds if type(b) is kind]
    return found


def use_table(agent: DQNAgent, v: torch.Tensor) -> None:
    """Make the target network a table: V(s) for every action of s (so its max, and any action's value, is V)."""
    agent.loss.target_value_network = lambda obs, goal: v[obs].unsqueeze(-1).expand(*obs.shape, 4)


def cell_table(n_cells: int, values: dict[int, float], default: float = 0.0) -> torch.Tensor:
    table = torch.full((n_cells,), default)
    for cell, value in values.items():
        table[cell] = value
    return table


def hand_batch(obs, action, goal, next_obs, reward=None, terminated=None, n_steps=1, **extra) -> TensorDict:
    """A batch written out sample by sample (the next goal is the goal; reward 0 and live unless given; ``extra``:
    further keys, each a list with one entry per sample)."""
    size = len(obs)
    reward = torch.zeros(size, 1) if reward is None else torch.tensor(reward, dtype=torch.float32).unsqueeze(-1)
    terminated = (
        torch.zeros(size, 1, dtype=torch.bool) if terminated is None else torch.tensor(terminated).unsqueeze(-1)
    )
    steps = torch.as_tensor(n_steps).expand(size).reshape(size, 1).clone()
    return TensorDict(
        {
            "observation": torch.tensor(obs),
            "desired_goal": torch.tensor(goal),
            "action": torch.tensor(action),
            "relabeled": torch.zeros(size, dtype=torch.bool),
            "n_steps": steps,
            **{key: torch.tensor(value) for key, value in extra.items()},
            "next": {
                "observation": torch.tensor(next_obs),
                "desired_goal": torch.tensor(goal),
                "reward": reward,
                "terminated": terminated,
                "truncated": torch.zeros_like(terminated),
                "done": terminated.clone(),
            },
        },
        batch_size=(size,),
    )


def random_batch(n_cells: int, size: int = 64, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    terminated = torch.rand(size, 1, generator=g) < 0.3
    return TensorDict(
        {
            "observation": torch.randint(n_cells, (size,), generator=g),
            "desired_goal": torch.randint(n_cells, (size,), generator=g),
            "action": torch.randint(4, (size,), generator=g),
            "next": {
                "observation": torch.randint(n_cells, (size,), generator=g),
                "desired_goal": torch.randint(n_cells, (size,), generator=g),
                "reward": terminated.float(),
                "terminated": terminated,
                "truncated": torch.zeros_like(terminated),
                "done": terminated,
            },
            "relabeled": torch.zeros(size, dtype=torch.bool),
            "n_steps": torch.ones(size, 1, dtype=torch.int64),
        },
        batch_size=(size,),
    )


def taken(agent: DQNAgent, batch: TensorDict) -> torch.Tensor:
    """(B,) the taken action's target, through the agent's own parts."""
    with torch.no_grad():
        return agent.td_target.taken(batch, agent.loss.bootstrap).squeeze(-1)


def predictions(agent: DQNAgent, batch: TensorDict) -> torch.Tensor:
    """(B, 4) the online network's Q of the batch's states and goals."""
    with torch.no_grad():
        return agent.q_network(batch["observation"], batch["desired_goal"])


def td_loss(agent: DQNAgent, batch: TensorDict, y: torch.Tensor) -> torch.Tensor:
    """The l2 loss of the taken actions' predictions against the targets ``y`` (B,), by hand."""
    q = predictions(agent, batch)
    return ((q[torch.arange(q.shape[0]), batch["action"]] - y) ** 2).mean()


def others_loss(q: torch.Tensor, held: torch.Tensor, taken_action: torch.Tensor) -> torch.Tensor:
    """The other actions' term by hand: the squared distance of every action but the taken one to what it is held
    to, summed over the actions, averaged over the batch."""
    others = torch.ones_like(q, dtype=torch.bool)
    others[torch.arange(q.shape[0]), taken_action] = False
    return ((q - held) ** 2 * others).sum(-1).mean()


def reference_loss(agent: DQNAgent, batch: TensorDict) -> torch.Tensor:
    """TorchRL's own ``DQNLoss`` on the agent's network: same parameters, a copy of the agent's target parameters."""
    keys = ["observation", "desired_goal"]
    module = TensorDictModule(agent.q_network, in_keys=keys, out_keys=["action_value"])
    actor = QValueActor(module, in_keys=keys, spec=Categorical(4, dtype=torch.int64), action_space="categorical")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="No target network updater", category=UserWarning)
        reference = DQNLoss(
            actor, delay_value=True, double_dqn=agent.loss.double_dqn, loss_function=agent.loss.loss_function
        )
        reference.make_value_estimator(gamma=agent.settings.gamma)
        theirs = reference.target_value_network_params
        for key, value in agent.loss.target_value_network_params.items(True, True):
            theirs.get(("module", "0", "module", *key)).data.copy_(value)
    return reference(batch.clone())["loss"]


@pytest.mark.parametrize("double_dqn", [True, False])
@pytest.mark.parametrize("loss", ["l2", "smooth_l1"])
def test_lean_loss_equals_torchrl_dqn_loss(double_dqn, loss):
    agent = make_agent(f"agent.double_dqn={double_dqn}", f"agent.loss={loss}")
    # Make the target network differ from the online one, as it does between hard updates.
    with torch.no_grad():
        for p in agent.loss.target_value_network_params.values(True, True):
            p.add_(0.05 * torch.randn_like(p))
    batch = random_batch(agent.maze.n_cells)
    ours = agent.loss(batch.clone())["loss"]
    theirs = reference_loss(agent, batch)
    torch.testing.assert_close(ours, theirs)
    params = list(agent.loss.parameters())
    grads_ours = torch.autograd.grad(ours, params, allow_unused=True)
    grads_theirs = torch.autograd.grad(reference_loss(agent, batch), params, allow_unused=True)
    for a, b in zip(grads_ours, grads_theirs):
        if a is None or b is None:
            assert a is None and b is None
        else:
            torch.testing.assert_close(a, b)


def test_hard_update_reaches_the_lean_target_network():
    agent = make_agent("agent.target_update=hard", "agent.target_update_interval=2")
    online, target = agent.q_network, agent.loss.target_value_network
    batch = random_batch(agent.maze.n_cells)
    obs, goal = batch["observation"], batch["desired_goal"]
    agent.replay_buffer.extend(batch.unsqueeze(1).expand(64, 1).clone())
    for _ in range(2):  # online weights move; the target is still the initial copy
        agent.update()
        assert not torch.allclose(online(obs, goal), target(obs, goal))
    agent.update()  # TorchRL's HardUpdate copies on the step after `interval` counted steps
    torch.testing.assert_close(online(obs, goal), target(obs, goal))


@pytest.mark.parametrize("target_update", ["hard", "soft"])
def test_building_the_agent_raises_no_warning(target_update):
    """The target updater is attached at construction: TorchRL must not warn that the target is never updated."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        agent = make_agent(f"agent.target_update={target_update}")
        agent.replay_buffer.extend(random_batch(agent.maze.n_cells).unsqueeze(1).expand(64, 1).clone())
        agent.update()


def test_soft_update_moves_the_lean_target_network_by_tau():
    agent = make_agent("agent.target_update=soft", "agent.tau=0.5")
    before = {k: v.clone() for k, v in agent.loss.target_value_network.network.state_dict().items()}
    batch = random_batch(agent.maze.n_cells)
    agent.replay_buffer.extend(batch.unsqueeze(1).expand(64, 1).clone())
    agent.update()
    after = agent.loss.target_value_network.network.state_dict()
    online = agent.q_network.state_dict()
    for name, old in before.items():
        torch.testing.assert_close(after[name], 0.5 * old + 0.5 * online[name])


def test_polyak_update_equals_torchrl_soft_update_bit_for_bit():
    """PolyakUpdate steps the target with one fused lerp; after the same updates on the same samples its target
    network and online network equal those of an agent stepped by TorchRL's SoftUpdate exactly (a run is unchanged
    by the faster updater), and a checkpoint restored into a fresh agent keeps stepping the restored tensors."""
    agents = []
    for updater in (None, SoftUpdate):
        agent = make_agent("agent.target_update=soft", "agent.tau=0.3")
        assert isinstance(agent.target_updater, PolyakUpdate)
        if updater is not None:
            agent.target_updater = updater(agent.loss, tau=0.3)
        agent.replay_buffer.extend(random_batch(agent.maze.n_cells).unsqueeze(1).expand(64, 1).clone())
        torch.manual_seed(1)
        for _ in range(5):
            agent.update()
        agents.append(agent)
    fast, reference = (dict(a.loss.named_parameters()) | dict(a.loss.named_buffers()) for a in agents)
    assert fast.keys() == reference.keys() and any("target" in k for k in fast)
    for name, value in fast.items():
        assert torch.equal(value, reference[name]), name
    # A restored agent: its updater lerps the loaded target toward the loaded online weights.
    restored = make_agent("agent.target_update=soft", "agent.tau=0.3")
    restored.target_updater.step()  # gathers its tensors before the load, which must write them in place
    restored.load_state_dict(agents[0].state_dict())
    target = restored.loss.target_value_network.network.state_dict()
    expected = {k: v.clone() for k, v in target.items()}
    restored.target_updater.step()
    online = restored.q_network.state_dict()
    for name, old in expected.items():
        assert torch.equal(target[name], old.lerp(online[name], 1 - (1 - 0.3))), name


def test_checkpoint_round_trip_keeps_the_target_network():
    agent = make_agent()
    with torch.no_grad():
        for p in agent.loss.target_value_network_params.values(True, True):
            p.add_(1.0)
    state = agent.state_dict()
    fresh = make_agent()
    fresh.load_state_dict(state)
    batch = random_batch(agent.maze.n_cells)
    obs, goal = batch["observation"], batch["desired_goal"]
    torch.testing.assert_close(fresh.loss.target_value_network(obs, goal), agent.loss.target_value_network(obs, goal))
    torch.testing.assert_close(fresh.loss(batch.clone())["loss"], agent.loss(batch.clone())["loss"])


@pytest.mark.parametrize("step_cost", [0.5, 1.0])
def test_env_scale_maps_step_cost_values_to_the_env_reward_scale(step_cost):
    """An episode entering G on step d is worth gamma^(d-1) with the env's reward; the map recovers that exactly."""
    agent = make_agent(f"agent.step_cost={step_cost}", "agent.gamma=0.9")
    gamma, c = 0.9, step_cost
    d = torch.arange(1, 40, dtype=torch.float64)
    learner = gamma ** (d - 1) - c * (1 - gamma**d) / (1 - gamma)  # r - c on every step, r = 1 on the last
    torch.testing.assert_close(agent.env_scale(learner), gamma ** (d - 1))
    never = torch.tensor([-c / (1 - gamma)], dtype=torch.float64)  # never reaches the goal: 0
    torch.testing.assert_close(agent.env_scale(never), torch.zeros(1, dtype=torch.float64))


#: Target-network values V(s) per cell for the hand computations (every action the same, so max = V); 0 elsewhere.
V = {1: -10.0, 2: -4.0, 3: -9.0, 4: -5.0, 5: 0.0, 6: -1.0, 7: -20.0}


@pytest.mark.parametrize(("step_cost", "expected"), [(0, [-9.5, -3.8, 1.0, -4.75]), (1, [-10.5, -4.8, 0.0, -5.75])])
def test_step_cost_is_subtracted_from_the_reward_the_target_sees(step_cost, expected):
    """TD(0), gamma 0.95: the target is r - step_cost + 0.95 V(s') on a live step and r - step_cost on the terminal
    one (which entered the goal, r = 1): with V(1) = -10, V(2) = -4, V(4) = -5."""
    agent = make_agent(f"agent.step_cost={step_cost}", "agent.double_dqn=false")
    use_table(agent, cell_table(agent.maze.n_cells, V))
    batch = hand_batch(
        obs=[0, 1, 11, 3],
        action=[0, 1, 2, 3],
        goal=[10] * 4,
        next_obs=[1, 2, 10, 4],
        reward=[0, 0, 1, 0],
        terminated=[False, False, True, False],
    )
    torch.testing.assert_close(taken(agent, batch), torch.tensor(expected))
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, torch.tensor(expected)))


def test_step_cost_counts_every_step_of_the_n_step_window():
    """Three-step windows, gamma 0.5, step cost 1: the learner's return is the env's discounted return R minus
    1 + 0.5 + 0.25 = 1.75, and a live window bootstraps with 0.5^3 = 0.125:

    a. R = 0, live, V(s_(t+3)) = V(1) = -10: -1.75 - 1.25 = -3.0
    b. the goal entered on the third step, R = 0.25, terminal: 0.25 - 1.75 = -1.5
    c. R = 0, live, V(5) = 0: -1.75
    d. R = 0, live, V(2) = -4: -1.75 - 0.5 = -2.25
    """
    agent = make_agent("agent.step_cost=1", "agent.gamma=0.5", "agent.n_step=3", "agent.double_dqn=false")
    use_table(agent, cell_table(agent.maze.n_cells, V))
    batch = hand_batch(
        obs=[0, 8, 9, 11],
        action=[0, 1, 2, 3],
        goal=[10] * 4,
        next_obs=[1, 10, 5, 2],
        reward=[0, 0.25, 0, 0],
        terminated=[False, True, False, False],
        n_steps=3,
    )
    expected = torch.tensor([-3.0, -1.5, -1.75, -2.25])
    torch.testing.assert_close(taken(agent, batch), expected)
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, expected))


def test_n_step_target_discounts_by_gamma_to_the_window_length_by_hand():
    agent = make_agent("agent.double_dqn=false", "agent.loss=l2", "agent.gamma=0.9")
    batch = random_batch(agent.maze.n_cells)
    steps = torch.randint(1, 5, (64, 1), generator=torch.Generator().manual_seed(1))
    batch.set("n_steps", steps)
    target_net, online = agent.loss.target_value_network, agent.q_network
    with torch.no_grad():
        nxt = batch["next"]
        bootstrap = target_net(nxt["observation"], nxt["desired_goal"]).max(-1).values
        live = (~nxt["terminated"].squeeze(-1)).float()
        y = nxt["reward"].squeeze(-1) + 0.9 ** steps.squeeze(-1).float() * live * bootstrap
        pred = online(batch["observation"], batch["desired_goal"])[torch.arange(64), batch["action"]]
        expected = ((pred - y) ** 2).mean()
    torch.testing.assert_close(agent.loss(batch.clone())["loss"], expected)


def test_clip_targets_keeps_targets_in_the_feasible_range():
    agent = make_agent("agent.clip_targets=true", "agent.double_dqn=false", "agent.loss=l2")
    assert agent.td_target.value_range == (0.0, 1.0)  # 0/1 rewards: no value below 0 or above 1
    with torch.no_grad():  # a target network whose values are far out of range
        agent.loss.target_value_network.network.advantage.bias.fill_(5.0)
        agent.loss.target_value_network.network.value.bias.fill_(5.0)
    batch = random_batch(agent.maze.n_cells)
    # Every bootstrapped target is clipped to 1, and a terminal one is its reward (1).
    torch.testing.assert_close(taken(agent, batch), torch.ones(64))
    torch.testing.assert_close(agent.loss(batch.clone())["loss"], td_loss(agent, batch, torch.ones(64)))


@pytest.mark.parametrize(("step_cost", "gamma", "max_steps", "low"), [(1.0, 1.0, 50, -50.0), (1.0, 0.5, 3, -1.75)])
def test_value_range_of_the_cost_form_by_hand(step_cost, gamma, max_steps, low):
    assert value_range(gamma, step_cost, max_steps) == (pytest.approx(low), 1.0 - step_cost)


def test_an_agent_built_without_a_target_clips_to_its_own_episode_cut():
    """``DQNAgent(..., td_target=None)`` builds the target from its settings: with ``clip_targets`` in the
    shortest-path form the values of an episode cut at 50 steps, [-50, 0]: a target of -101 becomes -50, the step
    that enters the goal keeps its 0."""
    _, settings = agent_settings(*SHORTEST_PATH, "agent.clip_targets=true")
    maze = load_maze("easy_small")
    agent = DQNAgent(settings, maze, HindsightReplayBuffer(1000, 1, settings.batch_size), max_steps=50)
    assert agent.td_target.value_range == (-50.0, 0.0)
    use_table(agent, torch.full((maze.n_cells,), -100.0))
    batch = hand_batch(
        obs=[0, 1], action=[0, 1], goal=[10, 10], next_obs=[1, 10], reward=[0, 1], terminated=[False, True]
    )
    torch.testing.assert_close(taken(agent, batch), torch.tensor([-50.0, 0.0]))


def test_count_model_bounds_refuse_an_agent_without_the_count_model():
    _, settings = agent_settings("agent.distance_floor=true")
    with pytest.raises(ValueError, match="count model"):
        DQNAgent(settings, load_maze("easy_small"), HindsightReplayBuffer(1000, 1, settings.batch_size))
    for switch in ("distance_floor", "distance_ceiling", "model_targets"):
        with pytest.raises(ValueError, match="count model"):
            make_agent(f"agent.{switch}=true")


@pytest.mark.parametrize("eval_network", ["online", "target"])
def test_greedy_q_values_come_from_the_evaluated_network(eval_network):
    """``agent.eval_network``: the greedy answer (evaluation) reads the online or the Polyak-averaged target
    network; the values collection and Smart Start read stay the online network's either way."""
    agent = make_agent(
        "agent.target_update=soft",
        "agent.tau=0.5",
        "agent.step_cost=1",
        "agent.gamma=1",
        f"agent.eval_network={eval_network}",
    )
    agent.replay_buffer.extend(random_batch(agent.maze.n_cells).unsqueeze(1).expand(64, 1).clone())
    agent.update()  # online and target now differ
    cells, goals = torch.arange(agent.maze.n_cells), torch.tensor([agent.maze.goal_cell, 0])
    online = agent.q_network(cells.repeat(2), goals.repeat_interleave(cells.numel())).detach()
    target = agent.loss.target_value_network(cells.repeat(2), goals.repeat_interleave(cells.numel()))
    assert not torch.allclose(online, target)
    expected = {"online": online, "target": target}[eval_network]
    torch.testing.assert_close(agent.greedy_q_values(cells, goals), agent.env_scale(expected).view(2, -1, 4))
    torch.testing.assert_close(agent.q_values(cells, goals), agent.env_scale(online).view(2, -1, 4))


def test_hybrid_encoder_starts_as_coords_and_learns_a_vector_per_cell():
    # At the start the per-cell table is zero, so the hybrid code is the coords MLP's. A gradient step on a loss at
    # some cells moves the table's rows of exactly those cells, by Adam's first step (lr times the gradient's sign).
    maze = load_maze("easy_small")
    torch.manual_seed(0)
    encoder = CellEncoder(maze, "hybrid", 8)
    cells = torch.tensor([0, 5, 5, 17])
    pos = torch.stack((cells // maze.width, cells % maze.width), dim=-1).float() / torch.tensor(
        [maze.height - 1, maze.width - 1]
    )
    torch.testing.assert_close(encoder(cells), encoder.net(pos))
    optimizer = torch.optim.Adam(encoder.parameters(), lr=0.01)
    encoder(cells).sum().backward()
    optimizer.step()
    table = encoder.cells.weight.detach()
    moved = sorted(torch.nonzero(table.abs().sum(dim=1)).flatten().tolist())
    assert moved == [0, 5, 17]
    torch.testing.assert_close(table[[0, 5, 17]], torch.full((3, 8), -0.01))


# --- the hindsight bound (agent.hindsight_bound) ---------------------------------------------------------------------
@pytest.mark.parametrize(
    ("step_cost", "gamma", "floors"),
    # goal_steps 0 (not known to be reached), 1 (entered on this step), 2, 5
    [(1.0, 1.0, [-INF, 0.0, -1.0, -4.0]), (0.0, 0.9, [-INF, 1.0, 0.9, 0.6561])],
)
def test_hindsight_bound_by_hand(step_cost, gamma, floors):
    """Reaching the goal k steps on: k - 1 steps of -1, then 0 on entering it (shortest-path form), or gamma^(k-1)
    with 0/1 rewards; nothing where the goal is not known to be reached."""
    agent = make_agent(f"agent.step_cost={step_cost}", f"agent.gamma={gamma}", "agent.hindsight_bound=true")
    batch = hand_batch(obs=[0] * 4, action=[0] * 4, goal=[10] * 4, next_obs=[1] * 4, goal_steps=[[0], [1], [2], [5]])
    torch.testing.assert_close(bound(agent, HindsightBound).lower(batch, None), torch.tensor([floors]).T)


def test_hindsight_bound_lifts_only_the_targets_below_it():
    """Shortest-path form, V(s) = -s / 5: the one-step target is -1 - s' / 5. Where the stored episode reached the
    goal k = 3 steps on, the bound is -2 and the target max(-1 - s' / 5, -2); elsewhere the target is unbounded.

    ======  ==========  ===========  ======
    s'      goal_steps  -1 - s'/5    target
    ======  ==========  ===========  ======
    0       3           -1           -1
    3       3           -1.6         -1.6
    5       3           -2           -2
    10      3           -3           -2
    40      3           -9           -2
    40      0           -9           -9
    0       0           -1           -1
    10      0           -3           -3
    ======  ==========  ===========  ======
    """
    agent = make_agent(*SHORTEST_PATH, "agent.hindsight_bound=true")
    use_table(agent, -torch.arange(agent.maze.n_cells, dtype=torch.float32) / 5)
    batch = hand_batch(
        obs=[20, 21, 22, 23, 24, 25, 26, 27],
        action=[0, 1, 2, 3, 0, 1, 2, 3],
        goal=[10] * 8,
        next_obs=[0, 3, 5, 10, 40, 40, 0, 10],
        goal_steps=[[3]] * 5 + [[0]] * 3,
    )
    expected = torch.tensor([-1.0, -1.6, -2.0, -2.0, -2.0, -9.0, -1.0, -3.0])
    torch.testing.assert_close(taken(agent, batch), expected)
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, expected))


def test_without_the_option_the_goal_steps_bound_nothing():
    """The same kind of sample without ``agent.hindsight_bound``: a goal reached 3 steps on (bound -2) leaves the
    one-step target -1 + V(s') = -11 as it is."""
    agent = make_agent(*SHORTEST_PATH)
    assert agent.td_target.bounds == ()
    use_table(agent, torch.full((agent.maze.n_cells,), -10.0))
    batch = hand_batch(obs=[20, 21], action=[0, 1], goal=[10, 10], next_obs=[3, 4], goal_steps=[[3], [3]])
    torch.testing.assert_close(taken(agent, batch), torch.tensor([-11.0, -11.0]))


def test_hindsight_bound_refuses_a_buffer_without_goal_steps():
    _, settings = agent_settings("agent.hindsight_bound=true")
    buffer = HindsightReplayBuffer(1000, 1, settings.batch_size)
    with pytest.raises(ValueError, match="goal_steps"):
        DQNAgent(settings, load_maze("easy_small"), buffer)


# --- n_step_max: the largest of the window's k-step targets --------------------------------------------------------
def test_n_step_max_refuses_a_buffer_without_window_states():
    _, settings = agent_settings("agent.n_step_max=true")
    buffer = HindsightReplayBuffer(1000, 1, settings.batch_size)
    with pytest.raises(ValueError, match="window_states"):
        DQNAgent(settings, load_maze("easy_small"), buffer)


def n_step_max_batch() -> TensorDict:
    """Four samples of 3-step windows (shortest-path form, gamma 1: the learner's reward over k steps is -k, +1 on
    entering the goal), written out with the target network's table :data:`V`:

    a. m = 3, no goal: window 1, 2, 3. Targets: k=1 -1 + V(1) = -11, k=2 -2 + V(2) = -6, k=3 -3 + V(3) = -12 -> -6.
    b. m = 3, the goal entered at step 3 (terminal): k=3 gives -2, above k=1 (-11) and k=2 (-6) -> -2.
    c. m = 1, cut by the episode's end: -1 + V(4) = -6. The entries past m (cell 5, V 0) do not count -> -6.
    d. m = 2, no goal: window 6, 7. k=1 -1 + V(6) = -2; k=2 -2 + V(7) = -22; the third entry (7) does not count -> -2.
    """
    window = torch.tensor([[1, 2, 3], [1, 2, 3], [4, 5, 5], [6, 7, 7]])
    m = torch.tensor([[3], [3], [1], [2]])
    last = window.gather(1, m - 1).squeeze(1)
    terminated = torch.tensor([[False], [True], [False], [False]])
    return TensorDict(
        {
            "observation": torch.tensor([8, 8, 9, 9]),
            "desired_goal": torch.full((4,), 30),
            "action": torch.tensor([0, 1, 2, 3]),
            "relabeled": torch.zeros(4, dtype=torch.bool),
            "n_steps": m,
            "window_observation": window,
            "next": {
                "observation": last,
                "desired_goal": torch.full((4,), 30),
                "reward": terminated.float(),  # the env's: 1 on entering the goal
                "terminated": terminated,
                "truncated": torch.tensor([[False], [False], [True], [False]]),
                "done": torch.tensor([[False], [True], [True], [False]]),
            },
        },
        batch_size=[4],
    )


def test_k_step_max_bound_by_hand():
    """The bound alone is the largest k-step target for k < m (above): a -6 (k=2), b -6 (k=2; the 3-step target
    that enters the goal is the base target, not the bound), c none (m = 1), d -2 (k=1)."""
    agent = make_agent(*SHORTEST_PATH, "agent.n_step=3", "agent.n_step_max=true")
    batch = n_step_max_batch()
    values = cell_table(agent.maze.n_cells, V)[batch["window_observation"][:, :-1]]  # V after k = 1, 2 steps
    lower = bound(agent, NStepMax).lower(batch, values)
    torch.testing.assert_close(lower, torch.tensor([[-6.0], [-6.0], [-INF], [-2.0]]))


@pytest.mark.parametrize("n_step_max", [True, False])
def test_n_step_max_target_by_hand(n_step_max):
    """With the option the target is the largest k-step target of each window (-6, -2, -6, -2 above); without it,
    the m-step target alone (-12, -2, -6, -22)."""
    agent = make_agent(*SHORTEST_PATH, "agent.n_step=3", f"agent.n_step_max={n_step_max}")
    use_table(agent, cell_table(agent.maze.n_cells, V))
    batch = n_step_max_batch()
    expected = torch.tensor([-6.0, -2.0, -6.0, -2.0] if n_step_max else [-12.0, -2.0, -6.0, -22.0])
    torch.testing.assert_close(taken(agent, batch), expected)
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, expected))


# --- the count model's bounds: hand-drawn geometry -------------------------------------------------------------------
def manhattan_to_goal(maze, cell: int) -> int:
    """|cell - G|_1 on ``maze``'s grid: the steps to G in a grid with no wall."""
    (r, c), (gr, gc) = divmod(cell, maze.width), maze.goal
    return abs(r - gr) + abs(c - gc)


def untried_ceilings(maze, cell: int) -> list[float]:
    """Per action, the distance ceiling's value of an untried move from ``cell`` when no wall is known: entering G
    after 1 + min(|cell - G|_1, |neighbour - G|_1) steps (the move's cell itself if it leaves the grid)."""
    r, c = divmod(cell, maze.width)
    values = []
    for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        inside = 0 <= r + dr < maze.height and 0 <= c + dc < maze.width
        near = manhattan_to_goal(maze, cell)
        if inside:
            near = min(near, manhattan_to_goal(maze, (r + dr) * maze.width + c + dc))
        values.append(-float(near))
    return values


def route_counts(maze) -> tuple[CountModel, list[int], list[int]]:
    """A count model that has seen one shortest route S ... G on ``maze`` and nothing else; the route's cells and
    moves."""
    counts = CountModel(maze.n_cells)
    table = maze.transition_table()
    dist = maze.distances_from(maze.goal).reshape(-1)
    route = [maze.start_cell]
    while route[-1] != maze.goal_cell:
        route.append(min(table[route[-1]], key=lambda c: dist[c]))
    route = [int(c) for c in route]
    moves = [next(a for a in range(4) if table[s, a] == s2) for s, s2 in zip(route[:-1], route[1:])]
    counts.update(torch.tensor(route[:-1]), torch.tensor(moves), torch.tensor(route[1:]), torch.zeros(len(moves)))
    return counts, route, moves


def route_batch(maze, cells: torch.Tensor, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor]:
    """A batch of 64 live samples with reward 0 at ``cells`` taking ``actions``, three in four for G (the rest keep
    the random goal of :func:`random_batch`); the batch and the mask of G's samples."""
    batch = random_batch(maze.n_cells)
    batch.set(("next", "terminated"), torch.zeros(64, 1, dtype=torch.bool))
    batch.set(("next", "done"), torch.zeros(64, 1, dtype=torch.bool))
    batch.set(("next", "reward"), torch.zeros(64, 1))
    batch.set("observation", cells)
    batch.set("action", actions)
    for_g = torch.arange(64) % 4 != 3
    batch.set("desired_goal", torch.where(for_g, maze.goal_cell, batch["desired_goal"]))
    batch.set(("next", "desired_goal"), batch["desired_goal"])
    return batch, for_g


def one_step_targets(batch: TensorDict, v: torch.Tensor) -> torch.Tensor:
    """(B,) the shortest-path form's one-step target of a live sample with reward 0 and the table ``v``: -1 + V(s')."""
    return -1.0 + v[batch["next", "observation"]]


# --- the distance ceiling (agent.distance_ceiling) -------------------------------------------------------------------
def test_distance_ceiling_caps_only_the_targets_for_g_above_it():
    """With an empty count model no wall is known, so the fewest steps from (s, a) to entering G that cannot be
    ruled out are 1 + min(|s' - G|_1, |s - G|_1), s' the grid neighbour a points to (the move may yet bump): the
    ceiling is -min(...), for G only. V is +10 at even cells and -100 at odd ones, so the one-step targets are 9
    (above every ceiling, capped for G) or -101 (below every ceiling, kept); a sample for another goal keeps its
    target."""
    maze = load_maze("easy_small")
    agent = make_agent(*SHORTEST_PATH, "agent.distance_ceiling=true", counts=CountModel(maze.n_cells))
    v = torch.where(torch.arange(maze.n_cells) % 2 == 0, 10.0, -100.0)
    use_table(agent, v)
    batch = random_batch(maze.n_cells)
    batch.set(("next", "terminated"), torch.zeros(64, 1, dtype=torch.bool))
    batch.set(("next", "reward"), torch.zeros(64, 1))
    for_g = torch.arange(64) % 2 == 0
    batch.set("desired_goal", torch.where(for_g, maze.goal_cell, batch["desired_goal"]))
    batch.set(("next", "desired_goal"), batch["desired_goal"])

    manhattan = partial(manhattan_to_goal, maze)
    ceilings = []
    for s, a, g in zip(batch["observation"].tolist(), batch["action"].tolist(), for_g.tolist()):
        r, c = divmod(s, maze.width)
        dr, dc = ((0, 1), (1, 0), (0, -1), (-1, 0))[a]
        inside = 0 <= r + dr < maze.height and 0 <= c + dc < maze.width
        nearer = min(manhattan(s), manhattan((r + dr) * maze.width + c + dc)) if inside else manhattan(s)
        ceilings.append(-float(nearer) if g else INF)  # 1 + nearer steps: -(1 + nearer - 1)
    ceilings = torch.tensor(ceilings)
    torch.testing.assert_close(bound(agent, DistanceCeiling).upper(batch), ceilings.unsqueeze(-1))
    y = one_step_targets(batch, v)
    assert bool((y[for_g] > ceilings[for_g]).any()) and bool((y[for_g] < ceilings[for_g]).any())
    expected = torch.minimum(y, ceilings)
    torch.testing.assert_close(taken(agent, batch), expected)
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, expected))


def test_where_a_lower_and_an_upper_bound_cross_the_upper_wins():
    """The hindsight bound of a goal entered on this step (goal_steps 1: 0) and the empty model's ceiling for G
    from S = (10, 1) moving up to (9, 1), 8 steps from G = (1, 1): -8. Crossed (as no real sample would), the target
    is the ceiling, -8; for another goal the hindsight bound alone, 0; below both, the one-step target -1 + V = -101
    is lifted."""
    maze = load_maze("easy_small")
    assert maze.pos(maze.start_cell) == (10, 1) and maze.goal == (1, 1)
    agent = make_agent(
        *SHORTEST_PATH, "agent.hindsight_bound=true", "agent.distance_ceiling=true", counts=CountModel(maze.n_cells)
    )
    use_table(agent, torch.full((maze.n_cells,), -100.0))
    s = maze.start_cell
    batch = hand_batch(
        obs=[s, s], action=[3, 3], goal=[maze.goal_cell, 50], next_obs=[s - 9, s - 9], goal_steps=[[1], [1]]
    )
    torch.testing.assert_close(taken(agent, batch), torch.tensor([-8.0, 0.0]))


# --- the distance floor (agent.distance_floor) ----------------------------------------------------------------------
def test_distance_floor_lifts_the_targets_for_g_and_joins_the_hindsight_bound():
    """The count model has seen one route into G on easy_small; for a sample whose goal is G and whose (s, a) lies
    on it, the floor is -(steps - 1) with steps = the route's remaining length from (s, a), -inf elsewhere. The
    hindsight bound is -2 (k = 3) on every eighth sample. The target is the largest of the one-step target (-101:
    V = -100), the hindsight bound and the floor; samples for other goals, or off the route, keep the hindsight
    bound alone."""
    maze = load_maze("easy_small")
    counts, route, moves = route_counts(maze)
    agent = make_agent(*SHORTEST_PATH, "agent.hindsight_bound=true", "agent.distance_floor=true", counts=counts)
    v = torch.full((maze.n_cells,), -100.0)
    use_table(agent, v)
    i = torch.arange(64) % len(moves)
    on_route = torch.arange(64) % 2 == 0  # the even samples: (route[i], moves[i])
    random = random_batch(maze.n_cells)
    cells = torch.where(on_route, torch.tensor(route[:-1])[i], random["observation"])
    actions = torch.where(on_route, torch.tensor(moves)[i], random["action"])
    batch, _ = route_batch(maze, cells, actions)
    for_g = on_route | (torch.arange(64) % 4 == 1)  # and a quarter of the batch for G off the route
    batch.set("desired_goal", torch.where(for_g, maze.goal_cell, random["desired_goal"]))
    batch.set(("next", "desired_goal"), batch["desired_goal"])
    goal_steps = torch.where(torch.arange(64) % 8 == 0, 3, 0).unsqueeze(-1)
    batch.set("goal_steps", goal_steps)

    remaining = {(s, a): len(moves) - j for j, (s, a) in enumerate(zip(route, moves))}  # steps to entering G
    floors = []
    for j, (s, a) in enumerate(zip(cells.tolist(), actions.tolist())):
        floors.append(-(remaining[s, a] - 1.0) if for_g[j] and (s, a) in remaining else -INF)
    floors = torch.tensor(floors)
    hindsight = torch.where(goal_steps.squeeze(-1) > 0, -2.0, -INF)
    torch.testing.assert_close(bound(agent, DistanceFloor).lower(batch, None), floors.unsqueeze(-1))
    torch.testing.assert_close(bound(agent, HindsightBound).lower(batch, None), hindsight.unsqueeze(-1))
    assert bool(torch.isfinite(floors[on_route]).all()) and not bool(torch.isfinite(floors[~for_g]).any())
    assert bool(((floors > -2) & (goal_steps.squeeze(-1) > 0)).any())  # the floor above the hindsight bound ...
    assert bool(((floors < -2) & (goal_steps.squeeze(-1) > 0)).any())  # ... and below it
    y = one_step_targets(batch, v)
    expected = torch.maximum(torch.maximum(y, hindsight), floors)
    torch.testing.assert_close(taken(agent, batch), expected)
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, expected))


# --- the policy held to the bounds (agent.bounded_policy) ------------------------------------------------------------
def full_counts(maze) -> CountModel:
    """A count model that has tried every move from every free cell but G: its floor and ceiling are then exact."""
    table = maze.transition_table()
    dist = maze.distances_to_goal()
    cells = [c for c in range(maze.n_cells) if dist[c] > 0]
    s = torch.tensor(cells).repeat_interleave(4)
    a = torch.arange(4).repeat(len(cells))
    counts = CountModel(maze.n_cells)
    counts.update(s, a, torch.as_tensor(table[s.numpy(), a.numpy()]), torch.zeros(len(s)))
    return counts


@pytest.mark.parametrize("bounded_policy", [True, False], ids=["bounded_policy", "network_policy"])
def test_bounded_policy_acts_on_q_for_g_held_to_exact_bounds_by_hand(bounded_policy):
    """Every move of easy_small tried: the floor and the ceiling of every (s, a) are both 1 + d(s'), s' its
    successor (itself after a bump), so Q(s||G, a) held to them is -d(s') exactly. The online and target networks
    prefer "right" everywhere (advantage bias +50). With ``bounded_policy`` the greedy action for G (acting with
    epsilon 0, the evaluated policy, Smart Start's Q) is one step closer to G from every cell, and Q for G reads
    -d(s'); for another goal the network's own values stand. Without it, "right" everywhere."""
    maze = load_maze("easy_small")
    agent = make_agent(
        *SHORTEST_PATH,
        "agent.distance_floor=true",
        "agent.distance_ceiling=true",
        "agent.bound_all_actions=true",
        "agent.model_targets=true",
        f"agent.bounded_policy={bounded_policy}",
        counts=full_counts(maze),
    )
    assert agent.bounds_in_force[-1:] == (["bounded_policy"] if bounded_policy else ["bound_all_actions"])
    with torch.no_grad():
        for net in (agent.q_network, agent.loss.target_value_network.network):
            net.advantage.bias.copy_(torch.tensor([50.0, 0.0, 0.0, 0.0]))
    dist, table = maze.distances_to_goal(), maze.transition_table()
    cells = torch.tensor([c for c in range(maze.n_cells) if dist[c] > 0])
    goal = torch.full_like(cells, maze.goal_cell)
    agent.epsilon = 0.0
    actions = agent.act(cells, goal)
    closer = dist[table[cells.numpy(), actions.numpy()]] == dist[cells.numpy()] - 1
    q = agent.policy_q(agent.q_network(cells, goal).detach(), cells, goal)
    exact = -torch.as_tensor(dist[table[cells.numpy()]], dtype=torch.float32)  # (n, 4): -d(s')
    policy = greedy_policy(agent, maze)
    if bounded_policy:
        assert bool(closer.all())
        torch.testing.assert_close(q, exact)
        assert greedy_accuracy(policy, maze) == 1.0
        env_q = agent.greedy_q_values(cells, torch.tensor([maze.goal_cell]))[0]
        torch.testing.assert_close(env_q, agent.env_scale(exact))
    else:
        assert bool((actions == 0).all()) and not bool(closer.all())
        assert greedy_accuracy(policy, maze) < 0.5
    other = torch.full_like(cells, int(cells[0]))  # a goal that is not G: no bound, the network's values
    raw = agent.q_network(cells, other).detach()
    torch.testing.assert_close(agent.policy_q(raw, cells, other), raw)


# --- the bounds on every action (agent.bound_all_actions) -----------------------------------------------------------
@pytest.mark.parametrize("all_actions", [True, False], ids=["all_actions", "taken_action_only"])
@pytest.mark.parametrize("bias", [10.0, -100.0], ids=["above_the_ceilings", "below_the_floors"])
def test_bound_all_actions_holds_every_action_of_a_state_for_g_by_hand(bias, all_actions):
    """The count model has seen one route into G on easy_small and no wall. For a sample for G at route cell s_j:
    the floor of the route's move is -(steps left - 1) and of the three untried moves -inf (no observed route); the
    ceiling of the route's move is -|s_{j+1} - G|_1 and of an untried move -min(|s - G|_1, |s' - G|_1) (s' the
    neighbour it points to, s itself if it leaves the grid; no wall is known). The taken action's target is the
    one-step target -1 + V(s') (V(s) = -s / 5) held into its bounds. With ``bound_all_actions`` every other action is
    held to its own prediction clipped into its bounds: with the online network's value bias at +10 every
    prediction lies above its ceiling, at -100 below every finite floor; samples for other goals hold nothing.
    Without it, nothing holds the other actions and the loss is the taken action's alone."""
    maze = load_maze("easy_small")
    counts, route, moves = route_counts(maze)
    agent = make_agent(
        *SHORTEST_PATH,
        "agent.distance_floor=true",
        "agent.distance_ceiling=true",
        f"agent.bound_all_actions={all_actions}",
        counts=counts,
    )
    with torch.no_grad():
        agent.q_network.value.bias.fill_(bias)
    v = -torch.arange(maze.n_cells, dtype=torch.float32) / 5
    use_table(agent, v)
    i = torch.arange(64) % len(moves)
    actions = torch.randint(4, (64,), generator=torch.Generator().manual_seed(1))
    batch, for_g = route_batch(maze, torch.tensor(route[:-1])[i], actions)

    manhattan = partial(manhattan_to_goal, maze)
    floors, ceilings = [], []
    for j, g in zip(i.tolist(), for_g.tolist()):
        floor, ceiling = [-INF] * 4, untried_ceilings(maze, route[j])
        floor[moves[j]] = -(len(moves) - j - 1.0)
        ceiling[moves[j]] = -float(manhattan(route[j + 1]))
        floors.append(floor if g else [-INF] * 4)
        ceilings.append(ceiling if g else [INF] * 4)
    floors, ceilings = torch.tensor(floors), torch.tensor(ceilings)
    rows = torch.arange(64)
    floor, ceiling = bound(agent, DistanceFloor), bound(agent, DistanceCeiling)
    torch.testing.assert_close(floor.lower(batch, None), floors[rows, actions].unsqueeze(-1))
    torch.testing.assert_close(ceiling.upper(batch), ceilings[rows, actions].unsqueeze(-1))
    y = torch.minimum(torch.maximum(one_step_targets(batch, v), floors[rows, actions]), ceilings[rows, actions])
    torch.testing.assert_close(taken(agent, batch), y)
    q = predictions(agent, batch)
    others = agent.td_target.others(batch, q, agent.loss.bootstrap)
    if not all_actions:
        assert floor.lower_all(batch) is None and ceiling.upper_all(batch) is None and others is None
        torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, y))
        return
    torch.testing.assert_close(floor.lower_all(batch), floors)
    torch.testing.assert_close(ceiling.upper_all(batch), ceilings)
    held = torch.minimum(torch.maximum(q, floors), ceilings)
    torch.testing.assert_close(others, held)
    if bias > 0:  # every prediction for G above its ceiling: held at the ceiling
        assert bool((q[for_g] > ceilings[for_g]).all())
        torch.testing.assert_close(others[for_g], ceilings[for_g])
    else:  # every prediction below its finite floors: only the route's moves have one
        finite = torch.isfinite(floors)
        assert bool((q[finite] < floors[finite]).all())
        torch.testing.assert_close(others[finite], floors[finite])
    torch.testing.assert_close(others[~for_g], q[~for_g])  # other goals: held to their own prediction
    outside = others_loss(q, held, actions)
    assert float(outside) > 1.0
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, y) + outside)


# --- one-step targets for the other actions through the count model (agent.model_targets) ---------------------------
def test_model_targets_give_every_seen_action_its_one_step_target_by_hand():
    """The count model has seen one route into G on easy_small and, at one route cell, a bump. The target network
    is a table V. For a sample at route cell s_j with goal g, each action that the model has seen from s_j is held
    to r - 1 + V(s'), r = 1 and no bootstrap where s' = g (entering g ends): the route's move (s' = s_{j+1}) and the
    bump (s' = s_j). An untried one, and the taken one, are held to their own prediction (add no loss). Half the
    samples ask for G, the other half for s_{j+1} itself (a relabeled goal, entered by the route's move)."""
    maze = load_maze("easy_small")
    counts, route, moves = route_counts(maze)
    table = maze.transition_table()
    j_bump, a_bump = next((j, a) for j, s in enumerate(route[:-1]) for a in range(4) if table[s, a] == s)
    counts.update(torch.tensor([route[j_bump]]), torch.tensor([a_bump]), torch.tensor([route[j_bump]]), torch.zeros(1))
    agent = make_agent(*SHORTEST_PATH, "agent.model_targets=true", counts=counts)
    v = -torch.arange(maze.n_cells, dtype=torch.float32) / 7.0  # any distinct values
    use_table(agent, v)
    i = torch.arange(64) % len(moves)
    i[:8] = j_bump  # a few samples at the bump's cell
    cells = torch.tensor(route)
    actions = torch.randint(4, (64,), generator=torch.Generator().manual_seed(2))
    batch, _ = route_batch(maze, cells[i], actions)
    for_g = torch.arange(64) % 2 == 0
    batch.set("desired_goal", torch.where(for_g, maze.goal_cell, cells[i + 1]))
    batch.set(("next", "desired_goal"), batch["desired_goal"])
    q = predictions(agent, batch)
    held, seen = q.clone(), torch.zeros(64, 4, dtype=torch.bool)
    for b, (j, g) in enumerate(zip(i.tolist(), batch["desired_goal"].tolist())):
        seen_moves = {moves[j]: route[j + 1]}
        if j == j_bump:
            seen_moves[a_bump] = route[j]
        for a, s2 in seen_moves.items():
            seen[b, a] = True
            if a != int(actions[b]):  # the taken action holds its prediction: the loss regresses it on y instead
                held[b, a] = 0.0 if s2 == g else -1.0 + float(v[s2])
    torch.testing.assert_close(agent.td_target.others(batch, q, agent.loss.bootstrap), held)
    y = one_step_targets(batch, v)
    torch.testing.assert_close(taken(agent, batch), y)  # the taken action's own target is the TD one
    rows = torch.arange(64)
    not_taken = torch.ones(64, 4, dtype=torch.bool)
    not_taken[rows, actions] = False
    assert int((not_taken & seen).sum()) >= 32  # the term is not empty ...
    assert bool((not_taken & seen & (held == 0)).any())  # ... and holds a relabeled goal entered (0)
    outside = others_loss(q, held, actions)
    assert float(outside) > 0.1
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, y) + outside)


def test_model_targets_refuse_a_stochastic_model():
    maze = load_maze("easy_small")
    counts = CountModel(maze.n_cells)
    s = maze.start_cell
    counts.update(torch.tensor([s, s]), torch.tensor([0, 0]), torch.tensor([s, s + 1]), torch.zeros(2))
    agent = make_agent("agent.model_targets=true", counts=counts)
    with pytest.raises(ValueError, match="deterministic"):
        agent.loss(random_batch(maze.n_cells))


# --- the ceiling where no route is known (agent.optimistic_floor) ----------------------------------------------------
@pytest.mark.parametrize("known", ["half_route", "whole_route"])
def test_optimistic_floor_makes_the_ceiling_the_target_where_no_route_is_known_by_hand(known):
    """The count model has seen the first half of a shortest route S ... G on easy_small (no route into G yet, and
    no wall), or the whole route. For a sample for G at route cell s_j, per action a: the ceiling is the value of
    entering G after 1 + |s' - G|_1 steps, -|s' - G|_1 (s' = s_{j+1} for the route's move; for an untried move the
    nearer of the neighbour and s itself, s alone where the move leaves the grid); the floor is the known route's
    -(steps left - 1) where the whole route has been seen and a is its move, and everywhere else (no observed
    route) the ceiling itself. So with every prediction and bootstrap pushed far below (value bias -100, V = -100)
    the taken action's target and every other action's held value are the ceiling, or the route's floor on the
    route. Samples for other goals get neither bound."""
    maze = load_maze("easy_small")
    counts, route, moves = route_counts(maze)
    half = len(moves) // 2
    if known == "half_route":
        counts = CountModel(maze.n_cells)
        counts.update(
            torch.tensor(route[:half]), torch.tensor(moves[:half]), torch.tensor(route[1 : half + 1]), torch.zeros(half)
        )
    agent = make_agent(
        *SHORTEST_PATH,
        "agent.distance_floor=true",
        "agent.distance_ceiling=true",
        "agent.bound_all_actions=true",
        "agent.optimistic_floor=true",
        counts=counts,
    )
    with torch.no_grad():
        agent.q_network.value.bias.fill_(-100.0)
    v = torch.full((maze.n_cells,), -100.0)
    use_table(agent, v)
    i = torch.arange(64) % half  # cells of the route's first half: seen in either model
    # the route's move, the one the model has seen
    batch, for_g = route_batch(maze, torch.tensor(route[:-1])[i], torch.tensor(moves)[i])
    batch.set(("next", "observation"), torch.tensor(route[1:])[i])

    manhattan = partial(manhattan_to_goal, maze)
    floors, ceilings = [], []
    for j, g in zip(i.tolist(), for_g.tolist()):
        ceiling = untried_ceilings(maze, route[j])
        ceiling[moves[j]] = -float(manhattan(route[j + 1]))
        floor = list(ceiling)  # no observed route from an untried move, nor from the route's before the whole is seen
        if known == "whole_route":
            floor[moves[j]] = -(len(moves) - j - 1.0)
        floors.append(floor if g else [-INF] * 4)
        ceilings.append(ceiling if g else [INF] * 4)
    floors, ceilings = torch.tensor(floors), torch.tensor(ceilings)
    rows, actions = torch.arange(64), batch["action"]
    floor, ceiling = bound(agent, DistanceFloor), bound(agent, DistanceCeiling)
    torch.testing.assert_close(floor.lower_all(batch), floors)
    torch.testing.assert_close(ceiling.upper_all(batch), ceilings)
    torch.testing.assert_close(floor.lower(batch, None), floors[rows, actions].unsqueeze(-1))
    if known == "half_route":  # no route into G: floor and ceiling meet on every action for G
        assert torch.equal(floors[for_g], ceilings[for_g])
    else:  # the route's floor lies below its ceiling (the route is longer than |s - G|_1 somewhere)
        assert bool((floors[rows, actions][for_g] < ceilings[rows, actions][for_g]).any())
    y = one_step_targets(batch, v)
    assert bool((y < -50).all())  # every TD target far below its bounds, so the bounds decide
    expected = torch.where(for_g, floors[rows, actions], y)
    torch.testing.assert_close(taken(agent, batch), expected)
    q = predictions(agent, batch)
    held = torch.where(for_g.unsqueeze(-1), floors, q)  # every prediction for G below its floor: held at the floor
    torch.testing.assert_close(agent.td_target.others(batch, q, agent.loss.bootstrap), held)
    outside = others_loss(q, held, actions)
    torch.testing.assert_close(agent.loss(batch)["loss"], td_loss(agent, batch, expected) + outside)


@pytest.mark.parametrize(("train_freq", "gradient_steps"), [(1, 1), (2, 1), (2, 3), (5, 2)])
def test_updates_due_gives_gradient_steps_per_train_freq_env_steps_across_batches(train_freq, gradient_steps):
    """``gradient_steps`` updates per ``train_freq`` env steps counted over the run, not per collection batch: with
    batches of 3 env steps (not a multiple of 2 or 5) the updates come out exact, and none before
    ``learning_starts``. The model-bounded learner runs at ``train_freq`` 2 (the notebook, session 51)."""
    agent = make_agent(
        f"agent.train_freq={train_freq}", f"agent.gradient_steps={gradient_steps}", "agent.learning_starts=30"
    )
    for _ in range(3):  # a batch (128) stored
        agent.replay_buffer.extend(random_batch(agent.maze.n_cells).unsqueeze(1).expand(64, 1).clone())
    due, env_steps = [], 0
    while env_steps < 600:
        env_steps += 3
        due.append(agent.updates_due(env_steps, 3))
    assert sum(due[:9]) == 0  # env steps 3..27: before learning_starts
    # From the batch that reaches learning_starts (env steps 28-30) on, one round per train_freq env steps.
    assert sum(due) == (600 // train_freq - 27 // train_freq) * gradient_steps
    assert max(due) <= gradient_steps * (3 // train_freq + 1)
