"""Goal-conditioned DQN: Q(s||g, a) with separate state and goal embeddings, a TorchRL loss and a target network."""

from __future__ import annotations

import copy
import warnings

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from torch import nn
from torchrl.objectives import HardUpdate, LossModule, SoftUpdate
from torchrl.objectives.utils import distance_loss

from ss_drl.envs.maze import ACTIONS, Maze
from ss_drl.ops import epsilon_greedy
from ss_drl.smart_start.ceiling import DistanceCeiling, DistanceFloor
from ss_drl.smart_start.counts import CountModel
from ss_drl.smart_start.selection import goal_q_values

#: The discount that puts the undiscounted cost form's distances on the 0/1 scale (:meth:`DQNAgent.env_scale`).
UNDISCOUNTED_SCALE = 0.99


ENCODERS = ("embedding", "coords", "hybrid")


class CellEncoder(nn.Module):
    """Embeds flat cell indices.

    ``embedding``: a learned vector per cell. ``coords``: an MLP over the normalized (row, col), which generalises
    across neighbouring cells. ``hybrid``: the coords MLP plus a learned vector per cell that starts at zero, so the
    encoder begins as ``coords`` and each cell can then move away from its neighbours' code, as the two sides of a
    wall must (their distances to a goal can differ by a hundred steps).
    """

    def __init__(self, maze: Maze, kind: str, dim: int):
        super().__init__()
        if kind not in ENCODERS:
            raise ValueError(f"unknown encoder {kind!r} (allowed: {', '.join(ENCODERS)})")
        self.kind = kind
        self.width = maze.width
        self.cells = None  # hybrid's per-cell table
        if kind == "embedding":
            self.net = nn.Embedding(maze.n_cells, dim)
            return
        self.register_buffer("scale", torch.tensor([max(maze.height - 1, 1), max(maze.width - 1, 1)]).float())
        self.net = nn.Sequential(nn.Linear(2, dim), nn.ReLU(), nn.Linear(dim, dim))
        if kind == "hybrid":
            self.cells = nn.Embedding(maze.n_cells, dim)
            nn.init.zeros_(self.cells.weight)

    def forward(self, cell: torch.Tensor) -> torch.Tensor:
        if self.kind == "embedding":
            return self.net(cell)
        pos = torch.stack((cell // self.width, cell % self.width), dim=-1).float() / self.scale
        code = self.net(pos)
        return code if self.cells is None else code + self.cells(cell)


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


class _BoundTarget:
    """The target network: a copy of the Q-network whose tensors *are* the loss's ``target_value_network_params``.

    ``TensorDictParams.to_module`` binds them once, so TorchRL's ``HardUpdate``/``SoftUpdate``, which write the
    target parameters in place, move this network too, and calling it costs one plain forward pass. It is not an
    ``nn.Module`` attribute of the loss because its tensors are already registered there, as the target parameters.
    """

    def __init__(self, q_network: GoalQNetwork, target_params: TensorDictParams):
        self.network = copy.deepcopy(q_network).requires_grad_(False)
        target_params.to_module(self.network)

    def __call__(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        return self.network(observation, desired_goal)


class PolyakUpdate(SoftUpdate):
    """TorchRL's ``SoftUpdate`` (target <- target lerped toward online by tau = 1 - eps), stepped with one fused
    ``torch._foreach_lerp_`` over the parameter tensors, gathered once.

    ``SoftUpdate.step`` walks the loss's parameter tensordicts and lerps through ``TensorDict.data`` on every call,
    about 1.1 ms of Python per update on Extreme's network against 0.3 ms for the lerp itself. The arithmetic is
    the same kernel with the same weight ``1 - eps``, so a run is unchanged bit for bit (``tests/test_dqn.py``
    checks it against ``SoftUpdate``). The tensors are the loss's own: the optimizer and ``load_state_dict`` write
    them in place, so the gathered lists stay valid.
    """

    _pairs: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None

    def step(self) -> None:
        if self._pairs is None:
            if not self.initialized:
                super().step()  # raises TorchRL's error
            targets, sources = [], []
            for key, source in self._sources.items(True, True):
                key = (f"target_{key[0]}", *key[1:]) if isinstance(key, tuple) else f"target_{key}"
                targets.append(self._targets.get(key).data)
                sources.append(source.data)
            self._pairs = (targets, sources)
        torch._foreach_lerp_(*self._pairs, 1 - self.eps)


class GoalDQNLoss(LossModule):
    """The DQN loss of a :class:`GoalQNetwork`: TD(0) target from a target network, optional double DQN.

    What is TorchRL's: the :class:`~torchrl.objectives.LossModule` base and its ``convert_to_functional``, which
    makes the network's parameters ``value_network_params`` and a detached copy ``target_value_network_params``,
    so that ``HardUpdate``/``SoftUpdate``, ``parameters()`` and ``state_dict()`` are TorchRL's; and
    ``distance_loss`` (``l2``/``smooth_l1``) with mean reduction. What is ours: :meth:`forward`. For the same
    parameters it computes what ``torchrl.objectives.DQNLoss`` computes (``tests/test_dqn.py`` checks the loss
    and its gradients against ``DQNLoss.forward``), but calls the networks directly: ``DQNLoss`` swaps functional
    parameters into a ``QValueActor`` and builds tensordicts for each of its network passes, which on a CPU costs
    several times the passes themselves (``scripts/benchmark.py --section train``). No ``td_error`` is written
    (the HER buffer samples uniformly).

    The sample's ``n_steps`` (m, from the HER buffer) sets the bootstrap discount gamma^m: m = 1 is TD(0).
    A sample that holds ``window_observation`` (the state after each of its window's steps) and ``window_reward``
    (the learner's return over its first k steps, k = 1..n-1) gets the largest of its k-step targets, k = 1..m
    (``DQNAgent``, ``agent.n_step_max``). ``target_floor`` and ``target_ceiling``, where the sample holds them, bound
    the target from below and above (``agent.hindsight_bound``, ``agent.distance_ceiling``). ``action_floor`` and
    ``action_ceiling`` (B, A), where the sample holds them, bound every action of the sampled state: each action but
    the taken one adds the loss of its prediction against that prediction clipped into its bounds, zero inside them
    (``agent.bound_all_actions``). ``model_next_observation`` (B, A; -1 for an untried action), with
    ``model_reward`` and ``model_terminated``, gives each other action the one-step target through that successor
    first (``agent.model_targets``).
    ``value_range = (low, high)`` clips the targets to the values a policy can have (a bootstrapped value outside it
    is the network's error, and with gamma near 1 such errors can feed on themselves until Q diverges).

    ``advantage_learning = alpha > 0`` adds the advantage-learning term to the target (``alpha = 0``: DQN).
    With 0/1 rewards and gamma < 1 the values of neighbouring actions differ by ~(1 - gamma) gamma^d, a few
    thousandths far from the goal, less than the network's error; the term multiplies those gaps by 1 / (1 - alpha).

    Its output also holds ``q_mean`` (mean Q of the batch's actions) and ``td_abs`` (mean |TD error|), detached.
    """

    value_network: GoalQNetwork
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(
        self,
        q_network: GoalQNetwork,
        gamma: float,
        double_dqn: bool = True,
        loss_function: str = "l2",
        advantage_learning: float = 0.0,
        value_range: tuple[float, float] | None = None,
    ):
        super().__init__()
        self.convert_to_functional(q_network, "value_network", create_target_params=True)
        self.gamma = float(gamma)
        self.double_dqn = bool(double_dqn)
        self.loss_function = loss_function
        self.advantage_learning = float(advantage_learning)
        self.value_range = value_range
        with warnings.catch_warnings():
            # The updater (HardUpdate/SoftUpdate) is attached right after construction, by DQNAgent; reading the
            # target parameters before that makes TorchRL warn that nobody will update them.
            warnings.filterwarnings("ignore", message="No target network updater", category=UserWarning)
            self.target_value_network = _BoundTarget(q_network, self.target_value_network_params)

    def _bootstrap(self, obs: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """(..., 1) the target network's value of (obs, goal): of the online network's greedy action (double DQN)
        or its own max."""
        q = self.target_value_network(obs, goal)
        if self.double_dqn:
            return q.gather(-1, self.value_network(obs, goal).argmax(-1, keepdim=True))
        return q.amax(-1, keepdim=True)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        online, target_network = self.value_network, self.target_value_network
        obs, goal = tensordict.get("observation"), tensordict.get("desired_goal")
        action = tensordict.get("action").unsqueeze(-1)
        q_all = online(obs, goal)
        pred = q_all.gather(-1, action)
        with torch.no_grad():
            next_obs, next_goal = tensordict.get(("next", "observation")), tensordict.get(("next", "desired_goal"))
            window_reward = tensordict.get("window_reward", None)  # set by the agent with n_step_max only
            window = None if window_reward is None else tensordict.get("window_observation")
            inner = None if window is None or window.shape[-1] < 2 else window[:, :-1]  # after k = 1..n-1 steps
            if inner is not None:  # one pass over the next states and the window's inner states
                states = torch.cat((next_obs.unsqueeze(1), inner), dim=1)
                values = self._bootstrap(states.flatten(), next_goal.unsqueeze(1).expand_as(states).flatten())
                values = values.view(states.shape)
                next_value, inner_value = values[:, :1], values[:, 1:]
            else:
                next_value = self._bootstrap(next_obs, next_goal)
            not_terminal = (~tensordict.get(("next", "terminated"))).to(next_value.dtype)
            m = tensordict.get("n_steps")
            discount = self.gamma ** m.to(next_value.dtype)  # gamma^m after m steps
            target = tensordict.get(("next", "reward")) + discount * not_terminal * next_value
            if inner is not None:
                # n_step_max: each k-step target, k < m (no goal entered, no episode end before step m), is also a
                # lower bound on Q*(s_t, a_t||g) in a deterministic maze; the target is the largest of them.
                k = torch.arange(1, window.shape[-1], device=m.device)
                shorter = window_reward + self.gamma ** k.to(inner_value.dtype) * inner_value
                shorter = torch.where(k < m, shorter, torch.full_like(shorter, -torch.inf))
                target = torch.maximum(target, shorter.amax(-1, keepdim=True))
            if self.advantage_learning:
                # Advantage learning (Bellemare et al., 2016): the taken action's target drops by alpha times its
                # gap to the best action, which widens every action gap by 1 / (1 - alpha) at the fixed point and
                # leaves the greedy action's value as it is.
                q_now = target_network(obs, goal)
                target = target - self.advantage_learning * (q_now.amax(-1, keepdim=True) - q_now.gather(-1, action))
            floor = tensordict.get("target_floor", None)
            if floor is not None:  # the hindsight bound (DQNAgent, agent.hindsight_bound): no target below it
                target = torch.maximum(target, floor)
            ceiling = tensordict.get("target_ceiling", None)
            if ceiling is not None:  # the distance ceiling (DQNAgent, agent.distance_ceiling): no target above it
                target = torch.minimum(target, ceiling)
            if self.value_range is not None:
                target = target.clamp(*self.value_range)
        loss = distance_loss(pred.squeeze(-1), target.squeeze(-1), self.loss_function).mean()
        action_floor = tensordict.get("action_floor", None)
        action_ceiling = tensordict.get("action_ceiling", None)
        model_next = tensordict.get("model_next_observation", None)
        if action_floor is not None or action_ceiling is not None or model_next is not None:
            # Every action of a sampled state but the taken one (which has its target above): with model_targets,
            # one that the count model has seen from this state gets the one-step target through the successor
            # observed for it; with bound_all_actions, each is then held to its bounds. An action with neither
            # keeps its own prediction (no loss).
            with torch.no_grad():
                held = q_all.detach()
                if model_next is not None:
                    known = model_next >= 0
                    values = self._bootstrap(
                        model_next.clamp(min=0).flatten(), goal.repeat_interleave(held.shape[-1])
                    ).view(held.shape)
                    entered = tensordict.get("model_terminated")
                    model_target = tensordict.get("model_reward") + self.gamma * (~entered).to(values.dtype) * values
                    held = torch.where(known, model_target, held)
                if action_floor is not None:
                    held = torch.maximum(held, action_floor)
                if action_ceiling is not None:
                    held = torch.minimum(held, action_ceiling)
                if self.value_range is not None:
                    held = held.clamp(*self.value_range)
                others = torch.ones_like(held, dtype=torch.bool).scatter_(-1, action, False)
            outside = distance_loss(q_all, held, self.loss_function) * others
            loss = loss + outside.sum(-1).mean()
        detached = pred.detach()
        return TensorDict(loss=loss, q_mean=detached.mean(), td_abs=(detached - target).abs().mean())


class DQNAgent:
    """The goal-conditioned DQN learner and its epsilon-greedy collection policy (an :class:`~ss_drl.agents.Agent`).

    Built from TorchRL parts: the HER replay buffer is a TorchRL ``TensorDictReplayBuffer``, the loss a TorchRL
    ``LossModule`` (:class:`GoalDQNLoss`), the target network moved by ``HardUpdate``/``SoftUpdate``.
    """

    def __init__(
        self, cfg, maze: Maze, replay_buffer, seed: int = 0, max_steps: int = 1000, counts: CountModel | None = None
    ):
        self.cfg = cfg
        self.maze = maze
        self.replay_buffer = replay_buffer
        self.q_network = GoalQNetwork(maze, cfg.encoder, cfg.embed_dim, tuple(cfg.hidden), cfg.dueling)
        self.epsilon = float(cfg.eps_start)
        # The learner's reward is the env's minus this cost: 1 gives -1 per step and 0 on entering the goal.
        self.step_cost = float(cfg.get("step_cost", 0.0))
        self.loss = GoalDQNLoss(
            self.q_network,
            gamma=cfg.gamma,
            double_dqn=cfg.double_dqn,
            loss_function=cfg.loss,
            advantage_learning=cfg.get("advantage_learning", 0.0),
            value_range=self.value_range(max_steps) if cfg.get("clip_targets", False) else None,
        )
        if cfg.target_update == "hard":
            self.target_updater = HardUpdate(self.loss, value_network_update_interval=cfg.target_update_interval)
        else:
            self.target_updater = PolyakUpdate(self.loss, tau=cfg.tau)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=cfg.lr, fused=True)
        # Read per update: plain attributes, not DictConfig lookups (tens of microseconds each).
        self.learning_starts, self.batch_size = int(cfg.learning_starts), int(cfg.batch_size)
        self.train_freq, self.gradient_steps = int(cfg.train_freq), int(cfg.gradient_steps)
        self.grad_clip = float(cfg.grad_clip)
        self.hindsight_bound = bool(cfg.get("hindsight_bound", False))
        if self.hindsight_bound and not getattr(replay_buffer, "goal_steps", False):
            raise ValueError("agent.hindsight_bound needs a replay buffer built with goal_steps=True")
        self.n_step_max = bool(cfg.get("n_step_max", False))
        if self.n_step_max and not getattr(replay_buffer, "window_states", False):
            raise ValueError("agent.n_step_max needs a replay buffer built with window_states=True")
        # The learner's return over the first k = 1..n-1 steps of a window that enters no goal before its end.
        k = torch.arange(1, int(cfg.get("n_step", 1)), dtype=torch.float32)
        self._window_reward = -self.step_cost * self._discounted_steps(k)
        self.goal_cell = maze.goal_cell
        # distance_ceiling: G's targets capped by the fewest steps to G the count model cannot rule out.
        self.distance_ceiling: DistanceCeiling | None = None
        # distance_floor: G's targets raised to the value of the fewest steps to G along the count model's transitions.
        self.distance_floor: DistanceFloor | None = None
        for key in ("distance_ceiling", "distance_floor"):
            if cfg.get(key, False) and counts is None:
                raise ValueError(f"agent.{key} needs the count model (DQNAgent(..., counts=...))")
        if cfg.get("distance_ceiling", False):
            self.distance_ceiling = DistanceCeiling(counts, maze.height, maze.width, maze.goal_cell)
        if cfg.get("distance_floor", False):
            self.distance_floor = DistanceFloor(counts, maze.goal_cell)
        # bound_all_actions: the floor and ceiling hold every action of a sampled state for G, not the taken one alone.
        self.bound_all_actions = bool(cfg.get("bound_all_actions", False))
        # model_targets: every other action of a sampled state that the count model has seen gets a one-step target.
        self.model_targets = bool(cfg.get("model_targets", False))
        if self.model_targets and counts is None:
            raise ValueError("agent.model_targets needs the count model (DQNAgent(..., counts=...))")
        self.counts = counts
        if self.bound_all_actions and self.distance_floor is None and self.distance_ceiling is None:
            raise ValueError("agent.bound_all_actions needs agent.distance_floor or agent.distance_ceiling")
        # optimistic_floor: where the count model knows no route into G, the floor is the ceiling (see floor()).
        self.optimistic_floor = bool(cfg.get("optimistic_floor", False))
        if self.optimistic_floor and (self.distance_floor is None or self.distance_ceiling is None):
            raise ValueError("agent.optimistic_floor needs agent.distance_floor and agent.distance_ceiling")
        self._optimistic: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # (floor, ceiling, merged)
        self.eval_network = cfg.get("eval_network", "online")
        # eval_network: average. A Polyak average of the online network at rate eval_tau for the greedy policy alone,
        # average <- (1 - eval_tau) average + eval_tau online after every optimizer step, from the initial weights
        # (as the soft target network). An in-place lerp per parameter: ~0.1 ms an update, a tenth of torch's
        # AveragedModel with an EMA function, which checks and copies each parameter on every call.
        self.eval_average: GoalQNetwork | None = None
        self._averaged: list[tuple[torch.Tensor, torch.Tensor]] = []  # (average, online) parameter pairs
        if self.eval_network == "average":
            self.eval_tau = float(cfg.eval_tau)
            self.eval_average = copy.deepcopy(self.q_network).requires_grad_(False)
            self._averaged = [
                (average, online.detach())
                for average, online in zip(self.eval_average.parameters(), self.q_network.parameters())
            ]
        self.updates = 0

    # --- acting ------------------------------------------------------------------------------------------------
    @torch.no_grad()
    def act(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        """Epsilon-greedy actions for a batch of (state, goal) cells.

        The raw network is called directly: at one env copy this runs every env step, and the TensorDict module
        wrappers would cost several times the forward pass itself.
        """
        return epsilon_greedy(self.q_network(observation, desired_goal).argmax(dim=-1), self.epsilon)

    @torch.no_grad()
    def q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, 4): Q(s||g, .) on the env's reward scale of every state in ``states`` (n,) for each goal in
        ``goals`` (B,), in one batched pass (:func:`~ss_drl.smart_start.selection.goal_q_values`)."""
        return self.env_scale(goal_q_values(self.q_network, states, goals))

    @torch.no_grad()
    def greedy_q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """:meth:`q_values` of the network whose greedy policy is evaluated: the online network; with
        ``eval_network: target`` the target network (with Polyak updates, the online network's weights averaged
        over the last ~1/tau updates); with ``eval_network: average`` a Polyak average at its own rate ``eval_tau``
        that nothing else reads. Collection, the TD targets and Smart Start read the online and target networks
        either way, so the choice changes no training."""
        if self.eval_network == "target":
            network = self.loss.target_value_network.network
        elif self.eval_network == "average":
            network = self.eval_average
        else:
            network = self.q_network
        return self.env_scale(goal_q_values(network, states, goals))

    def value_range(self, max_steps: int) -> tuple[float, float]:
        """The values the learner's Q can take: between an episode that never reaches the goal (``max_steps``
        steps of reward ``-step_cost``) and one that enters it on the first step (``1 - step_cost``)."""
        c, gamma = self.step_cost, float(self.cfg.gamma)
        never = -c * (max_steps if gamma == 1 else (1 - gamma**max_steps) / (1 - gamma))
        return never, 1.0 - c

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
        if gamma == 1:
            # Undiscounted cost form: Q = 1 - c d for a goal d steps away. With no discount of its own to map to,
            # the distance is put on the 0/1 scale with the planner's default discount: 0.99^(d - 1).
            return UNDISCOUNTED_SCALE ** ((1 - q) / c - 1)
        return ((1 - gamma) * q + c) / ((1 - gamma) + c * gamma)

    # --- learning ----------------------------------------------------------------------------------------------
    def _discounted_steps(self, steps: torch.Tensor) -> torch.Tensor:
        """sum_{j<m} gamma^j for m = ``steps``: what a cost of 1 per step adds up to over m steps."""
        gamma = self.loss.gamma
        return steps if gamma == 1 else (1 - gamma**steps) / (1 - gamma)

    def hindsight_floor(self, goal_steps: torch.Tensor) -> torch.Tensor:
        """The hindsight bound on Q(s_t, a_t||g) for a sample whose goal the stored episode reached k = ``goal_steps``
        steps on (k - 1 steps, then entering g), -inf where k = 0 (not known to be reached).

        In a deterministic maze the same k actions reach g again, so the optimal value is at least their return,
        ``gamma^(k-1) - step_cost * sum_{j<k} gamma^j`` on the learner's reward: ``gamma^(k-1)`` with 0/1 rewards,
        ``-(k - 1)`` in the shortest-path form (He et al. 2017's lower bound, "Learning to play in a day")."""
        k = goal_steps.to(torch.float32)
        floor = self.loss.gamma ** (k - 1) - self.step_cost * self._discounted_steps(k)
        return torch.where(goal_steps > 0, floor, torch.full_like(floor, -torch.inf))

    def _bound_for_g(
        self, sample: TensorDictBase, steps: torch.Tensor, other: float, all_actions: bool = False
    ) -> torch.Tensor:
        """(B, 1) for samples whose goal is the real G, the value of entering it k = ``steps[s_t * A + a_t]`` steps
        on, the same function of k as the hindsight bound (``-(k - 1)`` in the shortest-path form; -inf for k = 0);
        ``other`` for every other goal. With ``all_actions``, (B, A): the same for every action a of s_t."""
        obs = sample.get("observation")
        if all_actions:
            k = steps.view(-1, len(ACTIONS))[obs]
        else:
            k = steps[obs * len(ACTIONS) + sample.get("action")]
        bound = self.hindsight_floor(k).reshape(obs.shape[0], -1)
        real = (sample.get("desired_goal") == self.goal_cell).reshape(-1, 1)
        return torch.where(real, bound, torch.full_like(bound, other))

    def ceiling(self, sample: TensorDictBase, all_actions: bool = False) -> torch.Tensor:
        """(B, 1) the distance ceiling on each sample's target: for the real goal G, the value of entering it after
        the fewest steps from (s_t, a_t) that the count model cannot rule out (:class:`DistanceCeiling`); +inf for
        other goals. With ``all_actions``, (B, A): the ceiling of every action of s_t."""
        return self._bound_for_g(sample, self.distance_ceiling.steps(), torch.inf, all_actions)

    def floor(self, sample: TensorDictBase, all_actions: bool = False) -> torch.Tensor:
        """(B, 1) the distance floor on each sample's target: for the real goal G, the value of entering it after the
        fewest steps from (s_t, a_t) along transitions the count model has observed (:class:`DistanceFloor`); -inf
        for other goals and where no observed route leads to G. With ``all_actions``, (B, A): the floor of every
        action of s_t.

        With ``agent.optimistic_floor``, where no observed route leads from (s_t, a_t) to G the floor is the
        ceiling's value instead of -inf, so the target for G there *is* the ceiling: the value of the fewest steps
        the count model cannot rule out (optimism in the face of uncertainty, with every cell not yet seen to be a
        wall taken as free). Before the first goal the greedy policy for G then heads for G through the cells
        not yet known, and an action not yet tried keeps that optimistic value until it is."""
        steps = self.distance_floor.steps()
        if self.optimistic_floor:
            ceiling, cached = self.distance_ceiling.steps(), self._optimistic
            if cached is None or cached[0] is not steps or cached[1] is not ceiling:  # both cached until a new key
                self._optimistic = cached = (steps, ceiling, torch.where(steps > 0, steps, ceiling))
            steps = cached[2]
        return self._bound_for_g(sample, steps, -torch.inf, all_actions)

    @property
    def learning_rate(self) -> float:
        return self.optimizer.param_groups[0]["lr"]

    @learning_rate.setter
    def learning_rate(self, lr: float) -> None:
        """Set by the trainer each batch when ``agent.lr_end`` schedules a decay; checkpointed with the optimizer."""
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def store(self, batch: TensorDictBase) -> None:
        """Write a collected (T, N) batch to the HER replay buffer."""
        self.replay_buffer.extend(batch)

    def updates_due(self, env_steps: int, new_steps: int) -> int:
        """``gradient_steps`` updates per ``train_freq`` env steps, from ``learning_starts`` on (and once the buffer
        holds a batch); at the defaults, one update per env step."""
        if env_steps < self.learning_starts or len(self.replay_buffer) < self.batch_size:
            return 0
        rounds = env_steps // self.train_freq - (env_steps - new_steps) // self.train_freq
        return rounds * self.gradient_steps

    def update(self) -> torch.Tensor:
        """One gradient step on a HER-relabeled sample; returns :data:`~ss_drl.agents.UPDATE_METRICS`.

        Nothing here reads a value back to the host: the loop checks the loss for NaN at its logging cadence.
        """
        sample = self.replay_buffer.sample()
        if self.step_cost:
            # The learner's reward is r - step_cost on every step of the sample's m-step window.
            window = self._discounted_steps(sample.get("n_steps").to(torch.float32))
            sample.set(("next", "reward"), sample.get(("next", "reward")) - self.step_cost * window)
        if self.hindsight_bound:
            sample.set("target_floor", self.hindsight_floor(sample.get("goal_steps")))
        if self.distance_floor is not None:
            floor = self.floor(sample)
            if self.hindsight_bound:
                floor = torch.maximum(floor, sample.get("target_floor"))
            sample.set("target_floor", floor)
        if self.distance_ceiling is not None:
            sample.set("target_ceiling", self.ceiling(sample))
        if self.model_targets:
            # The successor the count model observed for each action of s_t (-1: untried), entering the goal ends.
            succ = self.counts.successors().view(-1, len(ACTIONS))[sample.get("observation")]
            entered = succ == sample.get("desired_goal").reshape(-1, 1)
            sample.set("model_next_observation", succ)
            sample.set("model_terminated", entered)
            sample.set("model_reward", entered.to(torch.float32) - self.step_cost)
        if self.bound_all_actions:
            if self.distance_floor is not None:
                sample.set("action_floor", self.floor(sample, all_actions=True))
            if self.distance_ceiling is not None:
                sample.set("action_ceiling", self.ceiling(sample, all_actions=True))
        if self.n_step_max:
            sample.set("window_reward", self._window_reward.expand(sample.batch_size[0], -1))
        out = self.loss(sample)
        loss = out.get("loss")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.grad_clip, foreach=True)
        self.optimizer.step()
        self.target_updater.step()
        for average, online in self._averaged:
            average.lerp_(online, self.eval_tau)
        self.updates += 1
        her_share = sample.get("relabeled").float().mean()
        goal_share = (sample.get("desired_goal") == self.goal_cell).float().mean()
        return torch.stack((loss.detach(), out.get("q_mean"), out.get("td_abs"), her_share, goal_share))

    # --- persistence -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "loss": self.loss.state_dict(),
            "epsilon": self.epsilon,
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            "target_counter": getattr(self.target_updater, "counter", 0),
            "replay_buffer": self.replay_buffer.state_dict(),
            "eval_average": None if self.eval_average is None else self.eval_average.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        # Checkpoints written before the loss held the network itself (up to 92d551c) name its tensors through the
        # QValueActor that wrapped it then.
        loss_state = {k.replace("params.module.0.module.", "params."): v for k, v in state["loss"].items()}
        self.loss.load_state_dict(loss_state)
        self.epsilon = state["epsilon"]
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = state["updates"]
        if hasattr(self.target_updater, "counter"):
            self.target_updater.counter = state["target_counter"]
        self.replay_buffer.load_state_dict(state["replay_buffer"])
        if self.eval_average is not None:
            self.eval_average.load_state_dict(state["eval_average"])
