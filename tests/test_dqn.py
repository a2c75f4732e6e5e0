"""The goal-conditioned DQN: GoalDQNLoss equals TorchRL's DQNLoss, target updates reach the lean target network."""

from __future__ import annotations

import io
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

from ss_drl.agents.dqn import DQNAgent, PolyakUpdate
from ss_drl.envs.maze import load_maze
from ss_drl.her import HindsightReplayBuffer
from ss_drl.smart_start import CountModel

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


def make_agent(*overrides: str, counts: CountModel | None = None) -> DQNAgent:
    settings = dict(PLAIN, **dict(o.split("=", 1) for o in overrides))
    cfg = compose_cfg("+experiment=easy_small_dqn_her", *(f"{k}={v}" for k, v in settings.items()))
    maze = load_maze("easy_small")
    buffer = HindsightReplayBuffer(
        1000,
        1,
        cfg.agent.batch_size,
        k=0,
        goal_steps=cfg.agent.hindsight_bound,
        window_states=cfg.agent.n_step_max,
    )
    torch.manual_seed(0)
    return DQNAgent(cfg.agent, maze, buffer, counts=counts)


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
        reference.make_value_estimator(gamma=agent.loss.gamma)
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


def test_step_cost_is_subtracted_from_the_reward_the_loss_sees():
    plain, costly = make_agent("agent.step_cost=0"), make_agent("agent.step_cost=1")
    costly.q_network.load_state_dict(plain.q_network.state_dict())
    costly.loss.target_value_network.network.load_state_dict(plain.loss.target_value_network.network.state_dict())
    batch = random_batch(plain.maze.n_cells)
    shifted = batch.clone()
    shifted.set(("next", "reward"), batch.get(("next", "reward")) - 1)
    seen = []
    costly.loss.forward = lambda td: seen.append(td.get(("next", "reward")).clone()) or plain.loss(td)
    costly.replay_buffer.sample = lambda: batch.clone()
    costly.update()
    torch.testing.assert_close(seen[0], shifted.get(("next", "reward")))


def test_advantage_learning_target_by_hand():
    alpha = 0.75
    agent = make_agent(f"agent.advantage_learning={alpha}", "agent.double_dqn=false", "agent.loss=l2")
    with torch.no_grad():
        for p in agent.loss.target_value_network_params.values(True, True):
            p.add_(0.05 * torch.randn_like(p))
    batch = random_batch(agent.maze.n_cells)
    online, target, gamma = agent.q_network, agent.loss.target_value_network, agent.cfg.gamma
    with torch.no_grad():
        obs, goal, action = batch["observation"], batch["desired_goal"], batch["action"]
        q_t = target(obs, goal)
        gap = q_t.max(-1).values - q_t[torch.arange(64), action]
        nxt = batch["next"]
        bootstrap = target(nxt["observation"], nxt["desired_goal"]).max(-1).values
        y = nxt["reward"].squeeze(-1) + gamma * (~nxt["terminated"].squeeze(-1)) * bootstrap - alpha * gap
        expected = ((online(obs, goal)[torch.arange(64), action] - y) ** 2).mean()
    torch.testing.assert_close(agent.loss(batch.clone())["loss"], expected)
    # alpha = 0 is TorchRL's DQNLoss again
    agent.loss.advantage_learning = 0.0
    torch.testing.assert_close(agent.loss(batch.clone())["loss"], reference_loss(agent, batch))


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
    assert agent.loss.value_range == (0.0, 1.0)  # 0/1 rewards: no value below 0 or above 1
    with torch.no_grad():  # a target network whose values are far out of range
        agent.loss.target_value_network.network.advantage.bias.fill_(5.0)
        agent.loss.target_value_network.network.value.bias.fill_(5.0)
    batch = random_batch(agent.maze.n_cells)
    with torch.no_grad():
        pred = agent.q_network(batch["observation"], batch["desired_goal"])[torch.arange(64), batch["action"]]
    # Every bootstrapped target is clipped to 1, and a terminal one is its reward (1).
    expected = ((pred - 1.0) ** 2).mean()
    torch.testing.assert_close(agent.loss(batch.clone())["loss"], expected)


@pytest.mark.parametrize(("step_cost", "gamma", "max_steps", "low"), [(1.0, 1.0, 50, -50.0), (1.0, 0.5, 3, -1.75)])
def test_value_range_of_the_cost_form_by_hand(step_cost, gamma, max_steps, low):
    agent = make_agent(f"agent.step_cost={step_cost}", f"agent.gamma={gamma}")
    assert agent.value_range(max_steps) == (pytest.approx(low), 1.0 - step_cost)


def test_step_cost_counts_every_step_of_the_n_step_window():
    agent = make_agent("agent.step_cost=1", "agent.gamma=0.5")
    batch = random_batch(agent.maze.n_cells)
    batch.set("n_steps", torch.full((64, 1), 3))
    seen = []
    agent.loss.forward = lambda td: (
        seen.append(td.get(("next", "reward")).clone())
        or TensorDict(loss=torch.zeros((), requires_grad=True), q_mean=torch.zeros(()), td_abs=torch.zeros(()))
    )
    agent.replay_buffer.sample = lambda: batch.clone()
    agent.update()
    # r - 1 on each of 3 steps, discounted: r_sum - (1 + 0.5 + 0.25)
    torch.testing.assert_close(seen[0], batch["next", "reward"] - 1.75)


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


def test_evaluation_average_is_a_polyak_average_by_hand():
    """``agent.eval_network=average``: starting from the initial weights, after every update
    a_k = (1 - eval_tau) a_(k-1) + eval_tau o_k, with o_k the online weights after update k; the greedy answer is
    that network's, and the target network still moves at ``tau`` (the average changes no training)."""
    agent = make_agent("agent.target_update=soft", "agent.tau=0.5", "agent.eval_network=average", "agent.eval_tau=0.25")
    agent.replay_buffer.extend(random_batch(agent.maze.n_cells).unsqueeze(1).expand(64, 1).clone())
    expected = {k: v.clone() for k, v in agent.q_network.state_dict().items()}
    target = {k: v.clone() for k, v in agent.q_network.state_dict().items()}
    for _ in range(3):
        agent.update()
        online = agent.q_network.state_dict()
        for name in expected:
            if not name.endswith("encoder.scale"):  # constant buffers, not parameters
                expected[name] = 0.75 * expected[name] + 0.25 * online[name]
                target[name] = 0.5 * target[name] + 0.5 * online[name]
    average = agent.eval_average.state_dict()
    for name, value in expected.items():
        torch.testing.assert_close(average[name], value)
        torch.testing.assert_close(agent.loss.target_value_network.network.state_dict()[name], target[name])
    assert not torch.allclose(average["advantage.weight"], agent.q_network.state_dict()["advantage.weight"])
    cells, goals = torch.arange(agent.maze.n_cells), torch.tensor([agent.maze.goal_cell])
    by_hand = agent.eval_average(cells, goals.expand_as(cells))
    torch.testing.assert_close(agent.greedy_q_values(cells, goals)[0], agent.env_scale(by_hand))


def test_checkpoint_round_trip_keeps_the_evaluation_average():
    agent = make_agent("agent.eval_network=average", "agent.eval_tau=0.5")
    agent.replay_buffer.extend(random_batch(agent.maze.n_cells).unsqueeze(1).expand(64, 1).clone())
    for _ in range(2):
        agent.update()
    fresh = make_agent("agent.eval_network=average", "agent.eval_tau=0.5")
    saved = io.BytesIO()  # through bytes, as a checkpoint file: an in-memory state would share the optimizer's tensors
    torch.save(agent.state_dict(), saved)
    saved.seek(0)
    fresh.load_state_dict(torch.load(saved, weights_only=False))
    cells, goals = torch.arange(agent.maze.n_cells), torch.tensor([agent.maze.goal_cell])
    torch.testing.assert_close(fresh.greedy_q_values(cells, goals), agent.greedy_q_values(cells, goals))
    assert not torch.allclose(fresh.greedy_q_values(cells, goals), fresh.q_values(cells, goals))
    # The next update, on the same sample, moves both averages alike: averaging goes on from the restored weights.
    batch = random_batch(agent.maze.n_cells, seed=1)
    agent.replay_buffer.sample = fresh.replay_buffer.sample = lambda: batch.clone()
    agent.update()
    fresh.update()
    torch.testing.assert_close(fresh.greedy_q_values(cells, goals), agent.greedy_q_values(cells, goals))


def test_hybrid_encoder_starts_as_coords_and_learns_a_vector_per_cell():
    # At the start the per-cell table is zero, so the hybrid code is the coords MLP's. A gradient step on a loss at
    # some cells moves the table's rows of exactly those cells, by Adam's first step (lr times the gradient's sign).
    from ss_drl.agents.dqn import CellEncoder

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
    [(1.0, 1.0, [-float("inf"), 0.0, -1.0, -4.0]), (0.0, 0.9, [-float("inf"), 1.0, 0.9, 0.6561])],
)
def test_hindsight_floor_by_hand(step_cost, gamma, floors):
    """Reaching the goal k steps on: k - 1 steps of -1, then 0 on entering it (shortest-path form), or gamma^(k-1)
    with 0/1 rewards; nothing where the goal is not known to be reached."""
    agent = make_agent(f"agent.step_cost={step_cost}", f"agent.gamma={gamma}", "agent.hindsight_bound=true")
    floor = agent.hindsight_floor(torch.tensor([[0], [1], [2], [5]]))
    torch.testing.assert_close(floor, torch.tensor([floors]).T)


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


def route_batch(maze, cells: torch.Tensor, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor]:
    """A batch of 64 non-terminal samples at ``cells`` taking ``actions``, three in four for G (the rest keep the
    random goal of :func:`random_batch`); the batch and the mask of G's samples."""
    batch = random_batch(maze.n_cells)
    batch.set(("next", "terminated"), torch.zeros(64, 1, dtype=torch.bool))
    batch.set("observation", cells)
    batch.set("action", actions)
    for_g = torch.arange(64) % 4 != 3
    batch.set("desired_goal", torch.where(for_g, maze.goal_cell, batch["desired_goal"]))
    batch.set(("next", "desired_goal"), batch["desired_goal"])
    return batch, for_g


def bounded_loss(q, y, floors, ceilings, taken) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``agent.bound_all_actions``'s loss by hand: the TD loss of the taken action against its target ``y`` held
    into its bounds, and the squared distance of every other action to its prediction held into its bounds. Returns
    the TD loss, the other actions' term and their mask."""
    rows = torch.arange(q.shape[0])
    y = torch.minimum(torch.maximum(y, floors[rows, taken]), ceilings[rows, taken])
    td = ((q[rows, taken] - y) ** 2).mean()
    others = torch.ones_like(q, dtype=torch.bool)
    others[rows, taken] = False
    outside = ((q - torch.minimum(torch.maximum(q, floors), ceilings)) ** 2 * others).sum(-1).mean()
    return td, outside, others


def update_on(agent, batch: TensorDict) -> tuple[list[TensorDict], object]:
    """One agent update on ``batch`` as its sample; returns what its loss saw and the loss's own forward."""
    seen, forward = capture_loss_input(agent)
    agent.replay_buffer.sample = lambda: batch.clone()
    agent.update()
    return seen, forward


def capture_loss_input(agent) -> tuple[list[TensorDict], object]:
    """Record each tensordict the agent's update hands its loss; returns the list and the loss's own forward."""
    seen, forward = [], agent.loss.forward
    agent.loss.forward = lambda td: seen.append(td.clone()) or forward(td)
    return seen, forward


def test_hindsight_bound_lifts_only_the_targets_below_it():
    """With the bound, the loss's target is max(n-step target, floor): here the floor is -2 (k = 3) on half the
    batch, above the network's bootstrapped targets (its value bias pushed to -10), and -inf on the other half."""
    agent = make_agent("agent.step_cost=1", "agent.gamma=1", "agent.hindsight_bound=true", "agent.double_dqn=false")
    with torch.no_grad():
        agent.loss.target_value_network.network.value.bias.fill_(-10.0)
    batch = random_batch(agent.maze.n_cells)
    batch.set(("next", "terminated"), torch.zeros(64, 1, dtype=torch.bool))
    goal_steps = torch.tensor([[3], [0]]).repeat(32, 1)
    batch.set("goal_steps", goal_steps)
    seen, forward = update_on(agent, batch)
    torch.testing.assert_close(seen[0]["target_floor"], agent.hindsight_floor(goal_steps))
    with torch.no_grad():
        nxt = batch["next"]
        bootstrap = agent.loss.target_value_network(nxt["observation"], nxt["desired_goal"]).max(-1).values
        y = nxt["reward"].squeeze(-1) - 1 + bootstrap  # reward - step cost, gamma 1, one step
        assert bool((y < -2).all())  # every bootstrapped target lies below the floor
        y = torch.where(goal_steps.squeeze(-1) > 0, torch.tensor(-2.0), y)
        pred = agent.q_network(batch["observation"], batch["desired_goal"])[torch.arange(64), batch["action"]]
    torch.testing.assert_close(forward(seen[0])["loss"], ((pred - y) ** 2).mean())


def test_hindsight_bound_refuses_a_buffer_without_goal_steps():
    cfg = compose_cfg("+experiment=easy_small_dqn_her", "agent.hindsight_bound=true", *NO_COUNT_MODEL)
    buffer = HindsightReplayBuffer(1000, 1, cfg.agent.batch_size)
    with pytest.raises(ValueError, match="goal_steps"):
        DQNAgent(cfg.agent, load_maze("easy_small"), buffer)


# --- the distance ceiling (agent.distance_ceiling) -------------------------------------------------------------------
def test_distance_ceiling_caps_only_the_targets_for_g_above_it():
    """With an empty count model no wall is known, so the fewest steps from (s, a) to entering G that cannot be
    ruled out are 1 + min(|s' - G|_1, |s - G|_1), s' the grid neighbour a points to (the move may yet bump): the
    target for G is min(n-step target, -(steps - 1)); a sample for another goal keeps its target. The network's
    value bias is pushed to +10 so that every bootstrapped target lies above the ceiling."""
    maze = load_maze("easy_small")
    counts = CountModel(maze.n_cells)
    agent = make_agent(
        "agent.step_cost=1", "agent.gamma=1", "agent.distance_ceiling=true", "agent.double_dqn=false", counts=counts
    )
    with torch.no_grad():
        agent.loss.target_value_network.network.value.bias.fill_(10.0)
    batch = random_batch(maze.n_cells)
    batch.set(("next", "terminated"), torch.zeros(64, 1, dtype=torch.bool))
    for_g = torch.arange(64) % 2 == 0
    batch.set("desired_goal", torch.where(for_g, maze.goal_cell, batch["desired_goal"]))
    batch.set(("next", "desired_goal"), batch["desired_goal"])
    seen, forward = update_on(agent, batch)

    manhattan = partial(manhattan_to_goal, maze)

    expected = []
    for s, a, g in zip(batch["observation"].tolist(), batch["action"].tolist(), for_g.tolist()):
        r, c = divmod(s, maze.width)
        dr, dc = ((0, 1), (1, 0), (0, -1), (-1, 0))[a]
        inside = 0 <= r + dr < maze.height and 0 <= c + dc < maze.width
        nearer = min(manhattan(s), manhattan((r + dr) * maze.width + c + dc)) if inside else manhattan(s)
        expected.append(-float(nearer) if g else float("inf"))  # 1 + nearer steps: -(1 + nearer - 1)
    torch.testing.assert_close(seen[0]["target_ceiling"], torch.tensor(expected).unsqueeze(-1))
    with torch.no_grad():
        nxt = batch["next"]
        bootstrap = agent.loss.target_value_network(nxt["observation"], nxt["desired_goal"]).max(-1).values
        y = nxt["reward"].squeeze(-1) - 1 + bootstrap  # reward - step cost, gamma 1, one step (no value clip)
        assert bool((y[for_g] > torch.tensor(expected)[for_g]).all())  # every target for G lies above its ceiling
        y = torch.minimum(y, torch.tensor(expected))
        pred = agent.q_network(batch["observation"], batch["desired_goal"])[torch.arange(64), batch["action"]]
    torch.testing.assert_close(forward(seen[0])["loss"], ((pred - y) ** 2).mean())


def test_distance_ceiling_refuses_an_agent_without_the_count_model():
    with pytest.raises(ValueError, match="count model"):
        make_agent("agent.distance_ceiling=true")


# --- n_step_max: the largest of the window's k-step targets --------------------------------------------------------
def test_n_step_max_refuses_a_buffer_without_window_states():
    cfg = compose_cfg(
        "+experiment=easy_small_dqn_her", "agent.hindsight_bound=false", "agent.n_step_max=true", *NO_COUNT_MODEL
    )
    buffer = HindsightReplayBuffer(1000, 1, cfg.agent.batch_size)
    with pytest.raises(ValueError, match="window_states"):
        DQNAgent(cfg.agent, load_maze("easy_small"), buffer)


def capture_targets(monkeypatch) -> list[torch.Tensor]:
    """Record the target each loss computation compares its prediction with."""
    import ss_drl.agents.dqn as dqn

    targets, distance = [], dqn.distance_loss
    monkeypatch.setattr(
        dqn, "distance_loss", lambda pred, target, kind: targets.append(target) or distance(pred, target, kind)
    )
    return targets


#: Target-network values V(s) per cell for the hand computations (every action the same, so max = V).
V = {1: -10.0, 2: -4.0, 3: -9.0, 4: -5.0, 5: 0.0, 6: -1.0, 7: -20.0}


def n_step_max_batch() -> TensorDict:
    """Four samples of 3-step windows (shortest-path form, gamma 1: the learner's reward over k steps is -k, +1 on
    entering the goal), written out:

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


@pytest.mark.parametrize("n_step_max", [True, False])
def test_n_step_max_target_by_hand(monkeypatch, n_step_max):
    """With the option the target is the largest k-step target of each window (-6, -2, -6, -2 above); without it,
    the m-step target alone (-12, -2, -6, -22)."""
    agent = make_agent(
        "agent.step_cost=1",
        "agent.gamma=1",
        "agent.n_step=3",
        f"agent.n_step_max={n_step_max}",
        "agent.double_dqn=false",
    )
    table = torch.zeros(agent.maze.n_cells)
    for cell, value in V.items():
        table[cell] = value
    agent.loss.target_value_network = lambda obs, goal: table[obs].unsqueeze(-1).expand(*obs.shape, 4)
    agent.replay_buffer.sample = n_step_max_batch
    targets = capture_targets(monkeypatch)
    agent.update()
    expected = [-6.0, -2.0, -6.0, -2.0] if n_step_max else [-12.0, -2.0, -6.0, -22.0]
    assert targets[0].tolist() == expected


def test_without_the_option_no_floor_reaches_the_loss():
    agent = make_agent()
    batch = random_batch(agent.maze.n_cells)
    batch.set("goal_steps", torch.full((64, 1), 3))
    seen, _ = capture_loss_input(agent)
    agent.replay_buffer.sample = lambda: batch.clone()
    agent.update()
    assert "target_floor" not in seen[0].keys()


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


# --- the distance floor (agent.distance_floor) ----------------------------------------------------------------------
def test_distance_floor_lifts_the_targets_for_g_and_joins_the_hindsight_bound():
    """The count model has seen one route into G on easy_small; for a sample whose goal is G and whose (s, a) lies
    on it, the floor is -(steps - 1) with steps = 1 + the route's remaining length, and the target is the largest of
    the n-step target (pushed far down by a value bias of -100), the hindsight bound and the floor. Samples for
    other goals, or off the route, keep the hindsight bound alone."""
    maze = load_maze("easy_small")
    counts, route, moves = route_counts(maze)
    agent = make_agent(
        "agent.step_cost=1",
        "agent.gamma=1",
        "agent.hindsight_bound=true",
        "agent.distance_floor=true",
        "agent.double_dqn=false",
        counts=counts,
    )
    with torch.no_grad():
        agent.loss.target_value_network.network.value.bias.fill_(-100.0)
    batch = random_batch(maze.n_cells)
    batch.set(("next", "terminated"), torch.zeros(64, 1, dtype=torch.bool))
    on_route = torch.arange(64) % 2 == 0  # the even samples: (route[i], moves[i]) for the real goal G
    i = torch.arange(64) % len(moves)
    batch.set("observation", torch.where(on_route, torch.tensor(route[:-1])[i], batch["observation"]))
    batch.set("action", torch.where(on_route, torch.tensor(moves)[i], batch["action"]))
    for_g = on_route | (torch.arange(64) % 4 == 1)  # and a quarter of the batch for G off the route
    batch.set("desired_goal", torch.where(for_g, maze.goal_cell, batch["desired_goal"]))
    batch.set(("next", "desired_goal"), batch["desired_goal"])
    goal_steps = torch.where(torch.arange(64) % 8 == 0, 3, 0).unsqueeze(-1)  # the hindsight bound, k = 3
    batch.set("goal_steps", goal_steps)
    seen, forward = update_on(agent, batch)
    remaining = {(s, a): len(moves) - j for j, (s, a) in enumerate(zip(route, moves))}  # steps to entering G
    expected = []
    for j, (s, a) in enumerate(zip(batch["observation"].tolist(), batch["action"].tolist())):
        bound = -2.0 if goal_steps[j] > 0 else -float("inf")
        if for_g[j] and (s, a) in remaining:  # every even sample, and any random one that lands on the route
            bound = max(bound, -(remaining[s, a] - 1.0))
        expected.append(bound)
    expected = torch.tensor(expected)
    torch.testing.assert_close(seen[0]["target_floor"], expected.unsqueeze(-1))
    assert bool(torch.isfinite(expected[on_route]).all()) and not bool(
        torch.isfinite(expected[~for_g & (goal_steps.squeeze(-1) == 0)]).any()
    )
    with torch.no_grad():
        nxt = batch["next"]
        bootstrap = agent.loss.target_value_network(nxt["observation"], nxt["desired_goal"]).max(-1).values
        y = nxt["reward"].squeeze(-1) - 1 + bootstrap
        assert bool((y < expected[torch.isfinite(expected)].min()).all())  # every n-step target lies below the floors
        y = torch.maximum(y, expected)
        pred = agent.q_network(batch["observation"], batch["desired_goal"])[torch.arange(64), batch["action"]]
    torch.testing.assert_close(forward(seen[0])["loss"], ((pred - y) ** 2).mean())


def test_distance_floor_refuses_an_agent_without_the_count_model():
    with pytest.raises(ValueError, match="count model"):
        make_agent("agent.distance_floor=true")


# --- the bounds on every action (agent.bound_all_actions) -----------------------------------------------------------
@pytest.mark.parametrize("bias", [10.0, -100.0], ids=["above_the_ceilings", "below_the_floors"])
def test_bound_all_actions_holds_every_action_of_a_state_for_g_by_hand(bias):
    """The count model has seen one route into G on easy_small and no wall. For a sample for G at route cell s_j:
    the floor of the route's move is -(steps left - 1) and of the three untried moves -inf (no observed route); the
    ceiling of the route's move is -|s_{j+1} - G|_1 and of an untried move -min(|s - G|_1, |s' - G|_1) (s' the
    neighbour it points to, s itself if it leaves the grid; no wall is known). The loss is the TD loss plus, per
    sample, the squared distance of each action but the taken one to its prediction clipped into its bounds: with
    the online network's value bias at +10 every prediction lies above its ceiling, at -100 below every finite
    floor. Samples for other goals add nothing."""
    maze = load_maze("easy_small")
    counts, route, moves = route_counts(maze)
    agent = make_agent(
        "agent.step_cost=1",
        "agent.gamma=1",
        "agent.distance_floor=true",
        "agent.distance_ceiling=true",
        "agent.bound_all_actions=true",
        "agent.double_dqn=false",
        counts=counts,
    )
    with torch.no_grad():
        agent.q_network.value.bias.fill_(bias)
    i = torch.arange(64) % len(moves)
    actions = torch.randint(4, (64,), generator=torch.Generator().manual_seed(1))
    batch, for_g = route_batch(maze, torch.tensor(route[:-1])[i], actions)
    seen, forward = update_on(agent, batch)

    manhattan = partial(manhattan_to_goal, maze)

    inf = float("inf")
    floors, ceilings = [], []
    for j, g in zip(i.tolist(), for_g.tolist()):
        floor, ceiling = [-inf] * 4, untried_ceilings(maze, route[j])
        floor[moves[j]] = -(len(moves) - j - 1.0)
        ceiling[moves[j]] = -float(manhattan(route[j + 1]))
        floors.append(floor if g else [-inf] * 4)
        ceilings.append(ceiling if g else [inf] * 4)
    floors, ceilings = torch.tensor(floors), torch.tensor(ceilings)
    torch.testing.assert_close(seen[0]["action_floor"], floors)
    torch.testing.assert_close(seen[0]["action_ceiling"], ceilings)
    with torch.no_grad():
        nxt = batch["next"]
        bootstrap = agent.loss.target_value_network(nxt["observation"], nxt["desired_goal"]).max(-1).values
        y = nxt["reward"].squeeze(-1) - 1 + bootstrap
        q = agent.q_network(batch["observation"], batch["desired_goal"])
        td, outside, others = bounded_loss(q, y, floors, ceilings, batch["action"])
        if bias > 0:  # every prediction for G above its ceiling: each of the other actions adds its distance
            assert bool((q[for_g] > ceilings[for_g]).all())
        else:  # every prediction below its finite floors: only the route's moves have one
            finite = torch.isfinite(floors)
            assert bool((q[finite] < floors[finite]).all())
            assert int(torch.isfinite(floors[others]).sum()) > 0
        assert float(outside) > 1.0
    torch.testing.assert_close(forward(seen[0])["loss"], td + outside)


def test_bound_all_actions_off_leaves_the_loss_on_the_taken_action():
    maze = load_maze("easy_small")
    counts, _, _ = route_counts(maze)
    agent = make_agent("agent.distance_floor=true", "agent.distance_ceiling=true", counts=counts)
    batch = random_batch(maze.n_cells)
    batch.set("desired_goal", torch.full((64,), maze.goal_cell))
    seen, _ = capture_loss_input(agent)
    agent.replay_buffer.sample = lambda: batch.clone()
    agent.update()
    assert "action_floor" not in seen[0].keys() and "action_ceiling" not in seen[0].keys()


def test_bound_all_actions_refuses_an_agent_without_a_distance_bound():
    maze = load_maze("easy_small")
    with pytest.raises(ValueError, match="bound_all_actions needs"):
        make_agent("agent.bound_all_actions=true", counts=CountModel(maze.n_cells))


# --- one-step targets for the other actions through the count model (agent.model_targets) ---------------------------
def test_model_targets_give_every_seen_action_its_one_step_target_by_hand():
    """The count model has seen one route into G on easy_small and, at one route cell, a bump. The target network
    is a table V (the same value for all four actions, so its max is V). For a sample at route cell s_j with goal g,
    each action but the taken one that the model has seen from s_j gets r - 1 + V(s'), r = 1 and no bootstrap where
    s' = g (entering g ends): the route's move (s' = s_{j+1}) and the bump (s' = s_j). The untried ones add no loss.
    Half the samples ask for G, the other half for s_{j+1} itself (a relabeled goal, entered by the route's move)."""
    maze = load_maze("easy_small")
    counts, route, moves = route_counts(maze)
    table = maze.transition_table()
    j_bump, a_bump = next((j, a) for j, s in enumerate(route[:-1]) for a in range(4) if table[s, a] == s)
    counts.update(torch.tensor([route[j_bump]]), torch.tensor([a_bump]), torch.tensor([route[j_bump]]), torch.zeros(1))
    agent = make_agent(
        "agent.step_cost=1", "agent.gamma=1", "agent.model_targets=true", "agent.double_dqn=false", counts=counts
    )
    v = -torch.arange(maze.n_cells, dtype=torch.float32) / 7.0  # any distinct values
    agent.loss.target_value_network = lambda obs, goal: v[obs].unsqueeze(-1).expand(*obs.shape, 4)
    batch = random_batch(maze.n_cells)
    batch.set(("next", "terminated"), torch.zeros(64, 1, dtype=torch.bool))
    i = torch.arange(64) % len(moves)
    i[:8] = j_bump  # a few samples at the bump's cell
    cells = torch.tensor(route)
    batch.set("observation", cells[i])
    batch.set("action", torch.randint(4, (64,), generator=torch.Generator().manual_seed(2)))
    for_g = torch.arange(64) % 2 == 0
    batch.set("desired_goal", torch.where(for_g, maze.goal_cell, cells[i + 1]))
    batch.set(("next", "desired_goal"), batch["desired_goal"])
    seen, forward = update_on(agent, batch)
    with torch.no_grad():
        q = agent.q_network(batch["observation"], batch["desired_goal"])
    expected_next = torch.full((64, 4), -1)
    held = q.clone()
    for b, (j, g) in enumerate(zip(i.tolist(), batch["desired_goal"].tolist())):
        seen_moves = {moves[j]: route[j + 1]}
        if j == j_bump:
            seen_moves[a_bump] = route[j]
        for a, s2 in seen_moves.items():
            expected_next[b, a] = s2
            held[b, a] = 0.0 if s2 == g else -1.0 + float(v[s2])
    assert torch.equal(seen[0]["model_next_observation"], expected_next)
    rows, taken = torch.arange(64), batch["action"]
    nxt = batch["next"]
    y = nxt["reward"].squeeze(-1) - 1 + v[nxt["observation"]]
    td = ((q[rows, taken] - y) ** 2).mean()
    others = torch.ones(64, 4, dtype=torch.bool)
    others[rows, taken] = False
    outside = ((q - held) ** 2 * others).sum(-1).mean()
    assert int((others & (expected_next >= 0)).sum()) >= 32 and float(outside) > 0.1  # the term is not empty
    assert int((others & (expected_next >= 0) & (expected_next == batch["desired_goal"].unsqueeze(-1))).sum()) > 0
    torch.testing.assert_close(forward(seen[0])["loss"], td + outside)


def test_model_targets_refuse_a_stochastic_model():
    maze = load_maze("easy_small")
    counts = CountModel(maze.n_cells)
    s = maze.start_cell
    counts.update(torch.tensor([s, s]), torch.tensor([0, 0]), torch.tensor([s, s + 1]), torch.zeros(2))
    agent = make_agent("agent.model_targets=true", counts=counts)
    agent.replay_buffer.sample = lambda: random_batch(maze.n_cells)
    with pytest.raises(ValueError, match="deterministic"):
        agent.update()


# --- the ceiling where no route is known (agent.optimistic_floor) ----------------------------------------------------
@pytest.mark.parametrize("known", ["half_route", "whole_route"])
def test_optimistic_floor_makes_the_ceiling_the_target_where_no_route_is_known_by_hand(known):
    """The count model has seen the first half of a shortest route S ... G on easy_small (no route into G yet, and
    no wall), or the whole route. For a sample for G at route cell s_j, per action a: the ceiling is the value of
    entering G after 1 + |s' - G|_1 steps, -|s' - G|_1 (s' = s_{j+1} for the route's move; for an untried move the
    nearer of the neighbour and s itself, s alone where the move leaves the grid); the floor is the known route's
    -(steps left - 1) where the whole route has been seen and a is its move, and everywhere else (no observed
    route) the ceiling itself. So with every prediction and bootstrap pushed far below (value biases at -100) the
    taken action's target and every other action's held value are the ceiling, or the route's floor on the
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
        "agent.step_cost=1",
        "agent.gamma=1",
        "agent.distance_floor=true",
        "agent.distance_ceiling=true",
        "agent.bound_all_actions=true",
        "agent.optimistic_floor=true",
        "agent.double_dqn=false",
        counts=counts,
    )
    with torch.no_grad():
        agent.q_network.value.bias.fill_(-100.0)
        agent.loss.target_value_network.network.value.bias.fill_(-100.0)
    i = torch.arange(64) % half  # cells of the route's first half: seen in either model
    # the route's move, the one the model has seen
    batch, for_g = route_batch(maze, torch.tensor(route[:-1])[i], torch.tensor(moves)[i])
    batch.set(("next", "observation"), torch.tensor(route[1:])[i])
    seen, forward = update_on(agent, batch)

    manhattan = partial(manhattan_to_goal, maze)
    inf = float("inf")
    floors, ceilings = [], []
    for j, g in zip(i.tolist(), for_g.tolist()):
        ceiling = untried_ceilings(maze, route[j])
        ceiling[moves[j]] = -float(manhattan(route[j + 1]))
        floor = list(ceiling)  # no observed route from an untried move, nor from the route's before the whole is seen
        if known == "whole_route":
            floor[moves[j]] = -(len(moves) - j - 1.0)
        floors.append(floor if g else [-inf] * 4)
        ceilings.append(ceiling if g else [inf] * 4)
    floors, ceilings = torch.tensor(floors), torch.tensor(ceilings)
    rows, taken = torch.arange(64), batch["action"]
    torch.testing.assert_close(seen[0]["action_floor"], floors)
    torch.testing.assert_close(seen[0]["action_ceiling"], ceilings)
    torch.testing.assert_close(seen[0]["target_floor"], floors[rows, taken].unsqueeze(-1))
    if known == "half_route":  # no route into G: floor and ceiling meet on every action for G
        assert torch.equal(floors[for_g], ceilings[for_g])
    else:  # the route's floor lies below its ceiling (the route is longer than |s - G|_1 somewhere)
        assert bool((floors[rows, taken][for_g] < ceilings[rows, taken][for_g]).any())
    with torch.no_grad():
        q = agent.q_network(batch["observation"], batch["desired_goal"])
        bootstrap = agent.loss.target_value_network(batch["next", "observation"], batch["desired_goal"]).max(-1).values
        y = batch["next", "reward"].squeeze(-1) - 1 + bootstrap
        assert bool((y < -50).all())  # every TD target far below its bounds, so the bounds decide
        td, outside, _ = bounded_loss(q, y, floors, ceilings, taken)
    torch.testing.assert_close(forward(seen[0])["loss"], td + outside)


def test_optimistic_floor_refuses_an_agent_without_both_distance_bounds():
    maze = load_maze("easy_small")
    with pytest.raises(ValueError, match="optimistic_floor needs"):
        make_agent("agent.optimistic_floor=true", "agent.distance_floor=true", counts=CountModel(maze.n_cells))
