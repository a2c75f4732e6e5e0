"""Goal-conditioned DQN: Q(s||g, a) with separate state and goal embeddings, TorchRL's DQNLoss and a target network."""

from __future__ import annotations

import copy
import warnings

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Categorical
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate
from torchrl.objectives.utils import distance_loss

from ss_drl.envs.maze import Maze
from ss_drl.smart_start.selection import goal_q_values


class CellEncoder(nn.Module):
    """Embeds flat cell indices: a learned table (``embedding``) or an MLP over normalized (row, col) (``coords``)."""

    def __init__(self, maze: Maze, kind: str, dim: int):
        super().__init__()
        self.kind = kind
        self.width = maze.width
        if kind == "embedding":
            self.net = nn.Embedding(maze.n_cells, dim)
        elif kind == "coords":
            self.register_buffer("scale", torch.tensor([max(maze.height - 1, 1), max(maze.width - 1, 1)]).float())
            self.net = nn.Sequential(nn.Linear(2, dim), nn.ReLU(), nn.Linear(dim, dim))
        else:
            raise ValueError(f"unknown encoder {kind!r} (allowed: embedding, coords)")

    def forward(self, cell: torch.Tensor) -> torch.Tensor:
        if self.kind == "embedding":
            return self.net(cell)
        pos = torch.stack((cell // self.width, cell % self.width), dim=-1).float() / self.scale
        return self.net(pos)


class GoalQNetwork(nn.Module):
    """Q(s||g, .): state and goal each embedded, concatenated, then an MLP to one value per action.

    With ``dueling`` the MLP ends in a value stream V(s||g) and an advantage stream A(s||g, a), combined as
    ``Q = V + A - mean_a A``: in a maze with gamma = 0.99 the actions' values differ by ~1-2% of V, and the separate
    advantage stream learns those differences much faster than one head regressing all of Q.
    """

    def __init__(
        self,
        maze: Maze,
        encoder: str = "embedding",
        embed_dim: int = 64,
        hidden: tuple = (256, 256),
        dueling: bool = True,
    ):
        super().__init__()
        self.state_encoder = CellEncoder(maze, encoder, embed_dim)
        self.goal_encoder = CellEncoder(maze, encoder, embed_dim)
        layers, width = [], 2 * embed_dim
        for size in hidden:
            layers += [nn.Linear(width, size), nn.ReLU()]
            width = size
        self.trunk = nn.Sequential(*layers)
        self.dueling = dueling
        self.advantage = nn.Linear(width, 4)
        self.value = nn.Linear(width, 1) if dueling else None

    def forward(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        h = self.trunk(torch.cat((self.state_encoder(observation), self.goal_encoder(desired_goal)), dim=-1))
        adv = self.advantage(h)
        if not self.dueling:
            return adv
        return self.value(h) + adv - adv.mean(dim=-1, keepdim=True)


class GoalDQNLoss(DQNLoss):
    """TorchRL's ``DQNLoss`` for a :class:`GoalQNetwork`, with a lean forward.

    Same parameters, target parameters, value estimator (TD(0), ``gamma``), double-DQN rule, loss function and mean
    reduction as ``DQNLoss``, so ``HardUpdate``/``SoftUpdate``, ``state_dict`` and checkpoints are TorchRL's. Only
    :meth:`forward` differs: ``DQNLoss.forward`` swaps functional parameters into the actor and builds tensordicts
    for each of its three network passes, which on a CPU costs several times the passes themselves (see
    ``tests/test_dqn.py`` for the equality with ``DQNLoss.forward``, and ``scripts/benchmark.py --section train``).
    Here the online network is called directly (its parameters are the loss's ``value_network_params``) and the
    target network is a copy of it whose tensors *are* ``target_value_network_params``: TorchRL's target updaters
    write into them in place. No ``td_error`` is written (the HER buffer samples uniformly).

    ``advantage_learning = alpha > 0`` adds the advantage-learning term to the target (``alpha = 0``: DQNLoss).
    With 0/1 rewards and gamma < 1 the values of neighbouring actions differ by ~(1 - gamma) gamma^d, a few
    thousandths far from the goal, less than the network's error; the term multiplies those gaps by 1 / (1 - alpha).
    """

    def __init__(self, actor: QValueActor, q_network: GoalQNetwork, advantage_learning: float = 0.0, **kwargs):
        super().__init__(actor, delay_value=True, **kwargs)
        self.advantage_learning = float(advantage_learning)
        self.__dict__["q_network"] = q_network  # not registered: its parameters are already the loss's
        target = copy.deepcopy(actor)
        with warnings.catch_warnings():
            # The updater (HardUpdate/SoftUpdate) is attached right after construction, by DQNAgent; reading the
            # target parameters before that makes TorchRL warn that nobody will update them.
            warnings.filterwarnings("ignore", message="No target network updater", category=UserWarning)
            self.target_value_network_params.to_module(target)
        self.__dict__["target_q_network"] = target.module[0].module

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        action = tensordict.get("action").unsqueeze(-1)
        pred = self.q_network(tensordict.get("observation"), tensordict.get("desired_goal")).gather(-1, action)
        with torch.no_grad():
            next_obs, next_goal = tensordict.get(("next", "observation")), tensordict.get(("next", "desired_goal"))
            next_q = self.target_q_network(next_obs, next_goal)
            if self.double_dqn:
                next_value = next_q.gather(-1, self.q_network(next_obs, next_goal).argmax(-1, keepdim=True))
            else:
                next_value = next_q.amax(-1, keepdim=True)
            not_terminal = (~tensordict.get(("next", "terminated"))).to(next_value.dtype)
            gamma = self.value_estimator.gamma
            target = tensordict.get(("next", "reward")) + gamma * not_terminal * next_value
            if self.advantage_learning:
                # Advantage learning (Bellemare et al., 2016): the taken action's target drops by alpha times its
                # gap to the best action, which widens every action gap by 1 / (1 - alpha) at the fixed point and
                # leaves the greedy action's value as it is.
                q_now = self.target_q_network(tensordict.get("observation"), tensordict.get("desired_goal"))
                target = target - self.advantage_learning * (q_now.amax(-1, keepdim=True) - q_now.gather(-1, action))
        loss = distance_loss(pred.squeeze(-1), target.squeeze(-1), self.loss_function).mean()
        return TensorDict(loss=loss)


class DQNAgent:
    """The goal-conditioned DQN learner and its epsilon-greedy collection policy.

    Built from TorchRL parts: ``QValueActor`` (the greedy actor), ``DQNLoss`` (:class:`GoalDQNLoss`: TD(0) target
    from a delayed target network, optional double DQN) and ``HardUpdate``/``SoftUpdate``; epsilon-greedy acting is
    in :meth:`act`.
    """

    def __init__(self, cfg, maze: Maze, replay_buffer, seed: int = 0):
        self.cfg = cfg
        self.maze = maze
        self.replay_buffer = replay_buffer
        spec = Categorical(4, dtype=torch.int64)
        self.q_network = GoalQNetwork(maze, cfg.encoder, cfg.embed_dim, tuple(cfg.hidden), cfg.dueling)
        self.actor = QValueActor(
            TensorDictModule(self.q_network, in_keys=["observation", "desired_goal"], out_keys=["action_value"]),
            in_keys=["observation", "desired_goal"],
            spec=spec,
            action_space="categorical",
        )
        self.epsilon = float(cfg.eps_start)
        # The learner's reward is the env's minus this cost: 1 gives -1 per step and 0 on entering the goal.
        self.step_cost = float(cfg.get("step_cost", 0.0))
        self.loss = GoalDQNLoss(
            self.actor,
            self.q_network,
            advantage_learning=cfg.get("advantage_learning", 0.0),
            loss_function=cfg.loss,
            double_dqn=cfg.double_dqn,
        )
        self.loss.make_value_estimator(gamma=cfg.gamma)
        if cfg.target_update == "hard":
            self.target_updater = HardUpdate(self.loss, value_network_update_interval=cfg.target_update_interval)
        else:
            self.target_updater = SoftUpdate(self.loss, tau=cfg.tau)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=cfg.lr, fused=True)
        # Read per update: plain attributes, not DictConfig lookups (tens of microseconds each).
        self.learning_starts, self.batch_size = int(cfg.learning_starts), int(cfg.batch_size)
        self.train_freq, self.gradient_steps = int(cfg.train_freq), int(cfg.gradient_steps)
        self.grad_clip = float(cfg.grad_clip)
        self.updates = 0
        self.last_loss = float("nan")

    # --- acting ------------------------------------------------------------------------------------------------
    @torch.no_grad()
    def act(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        """Epsilon-greedy actions for a batch of (state, goal) cells.

        The raw network is called directly: at one env copy this runs every env step, and the TensorDict module
        wrappers would cost several times the forward pass itself.
        """
        greedy = self.q_network(observation, desired_goal).argmax(dim=-1)
        explore = torch.rand(observation.shape) < self.epsilon
        return torch.where(explore, torch.randint(0, 4, observation.shape), greedy)

    def set_epsilon(self, value: float) -> None:
        """Set the exploration epsilon (the trainer anneals it linearly over ``eps_decay_steps`` env steps)."""
        self.epsilon = float(value)

    @torch.no_grad()
    def q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, 4): Q(s||g, .) on the env's reward scale of every state in ``states`` (n,) for each goal in
        ``goals`` (B,), in one batched pass (:func:`~ss_drl.smart_start.selection.goal_q_values`)."""
        return self.env_scale(goal_q_values(self.q_network, states, goals))

    def env_scale(self, q: torch.Tensor) -> torch.Tensor:
        """Map the learner's values (reward ``r - step_cost``) to the env's 0/1 reward scale.

        An episode that enters the goal on its d-th step is worth ``gamma^(d-1)`` with the env's reward and
        ``Q' = gamma^(d-1) (1 + c gamma / (1 - gamma)) - c / (1 - gamma)`` with the step cost c (an endless one:
        0 and ``-c / (1 - gamma)``). The map is affine, so it holds in expectation for any policy, keeps the greedy
        action, and gives Smart Start's UCB the scale of the paper's ``max_a Q`` whatever the step cost.
        """
        c, gamma = self.step_cost, float(self.cfg.gamma)
        if c == 0:
            return q
        return ((1 - gamma) * q + c) / ((1 - gamma) + c * gamma)

    # --- learning ----------------------------------------------------------------------------------------------
    def observe(self, batch: TensorDict, env_steps: int) -> None:
        """Store a collected batch (T, N) and run the update rounds it is due."""
        self.replay_buffer.extend(batch)
        if env_steps < self.learning_starts or len(self.replay_buffer) < self.batch_size:
            return
        rounds = max(1, round(batch.numel() / self.train_freq))
        for _ in range(rounds * self.gradient_steps):
            self.update()

    def update(self) -> float:
        sample = self.replay_buffer.sample()
        if self.step_cost:
            reward = sample.get(("next", "reward"))
            sample.set(("next", "reward"), reward - self.step_cost)
        loss = self.loss(sample)["loss"]
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite DQN loss ({float(loss)}) at update {self.updates}")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.grad_clip, foreach=True)
        self.optimizer.step()
        self.target_updater.step()
        self.updates += 1
        self.last_loss = float(loss.detach())
        return self.last_loss

    # --- persistence -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "loss": self.loss.state_dict(),
            "epsilon": self.epsilon,
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            "target_counter": getattr(self.target_updater, "counter", 0),
            "replay_buffer": self.replay_buffer.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.loss.load_state_dict(state["loss"])
        self.epsilon = state["epsilon"]
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = state["updates"]
        if hasattr(self.target_updater, "counter"):
            self.target_updater.counter = state["target_counter"]
        self.replay_buffer.load_state_dict(state["replay_buffer"])
