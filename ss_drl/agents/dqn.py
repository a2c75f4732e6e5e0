"""The goal-conditioned DQN learner: Q(s||g, a) (:mod:`.network`), its TorchRL loss with a target network, and the
epsilon-greedy collection policy. The TD target the loss regresses on is built from named parts in :mod:`.targets`;
the learner's settings are typed (:mod:`.settings`)."""

from __future__ import annotations

import copy
import warnings

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from torchrl.objectives import HardUpdate, LossModule, SoftUpdate
from torchrl.objectives.utils import distance_loss

from ss_drl.agents.network import GoalQNetwork
from ss_drl.agents.settings import DQNSettings
from ss_drl.agents.tables import LazyAdam, LazyPolyak, clip_grad_norm, table_keys
from ss_drl.agents.targets import MAZE, TDTarget, make_td_target
from ss_drl.envs.maze import Maze
from ss_drl.ops import epsilon_greedy

#: The discount that puts the undiscounted cost form's distances on the 0/1 scale (:meth:`DQNAgent.env_scale`).
UNDISCOUNTED_SCALE = 0.99


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
    #: Keys of parameters left out (the per-cell tables under ``agent.sparse_tables``: :class:`LazyPolyak` steps them).
    exclude: frozenset = frozenset()

    def step(self) -> None:
        if self._pairs is None:
            if not self.initialized:
                super().step()  # raises TorchRL's error
            targets, sources = [], []
            for key, source in self._sources.items(True, True):
                if key in self.exclude:
                    continue
                key = (f"target_{key[0]}", *key[1:]) if isinstance(key, tuple) else f"target_{key}"
                targets.append(self._targets.get(key).data)
                sources.append(source.data)
            self._pairs = (targets, sources)
        torch._foreach_lerp_(*self._pairs, 1 - self.eps)


class GoalDQNLoss(LossModule):
    """The DQN loss of a :class:`GoalQNetwork` on the TD target of a :class:`~ss_drl.agents.targets.TDTarget`.

    What is TorchRL's: the :class:`~torchrl.objectives.LossModule` base and its ``convert_to_functional``, which
    makes the network's parameters ``value_network_params`` and a detached copy ``target_value_network_params``,
    so that ``HardUpdate``/``SoftUpdate``, ``parameters()`` and ``state_dict()`` are TorchRL's; and
    ``distance_loss`` (``l2``/``smooth_l1``) with mean reduction. What is ours: :meth:`forward`. With no bound and
    no value-range clip it computes what ``torchrl.objectives.DQNLoss`` computes (``tests/test_dqn.py`` checks the
    loss and its gradients against ``DQNLoss.forward``), but calls the networks directly: ``DQNLoss`` swaps
    functional parameters into a ``QValueActor`` and builds tensordicts for each of its network passes, which on a
    CPU costs several times the passes themselves (``scripts/benchmark.py --section train``). No ``td_error`` is
    written (the HER buffer samples uniformly).

    The loss is the taken action's distance to its target, plus, where the target holds the other actions, each
    other action's distance to what it is held to (both from one call of :class:`TDTarget`). Both are averaged over
    the batch, and the other actions' distances are summed over the actions: each action of s_t weighs as much as
    the taken one, so with model targets most of the loss is on the actions not taken. Its output also holds
    ``q_mean`` (mean Q of the batch's actions) and ``td_abs`` (mean |TD error|), detached.
    """

    value_network: GoalQNetwork
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(
        self,
        q_network: GoalQNetwork,
        td_target: TDTarget,
        double_dqn: bool = True,
        loss_function: str = "l2",
        factored: bool = False,
    ):
        super().__init__()
        self.factored = bool(factored)  # the bootstrap passes by GoalQNetwork.factored_q
        self.convert_to_functional(q_network, "value_network", create_target_params=True)
        self.td_target = td_target
        self.double_dqn = bool(double_dqn)
        self.loss_function = loss_function
        with warnings.catch_warnings():
            # The updater (HardUpdate/SoftUpdate) is attached right after construction, by DQNAgent; reading the
            # target parameters before that makes TorchRL warn that nobody will update them.
            warnings.filterwarnings("ignore", message="No target network updater", category=UserWarning)
            self.target_value_network = _BoundTarget(q_network, self.target_value_network_params)
        #: Called with (obs, goal) before the target network reads them (LazyPolyak's catch-up), or None.
        self.before_target_read = None

    def bootstrap(self, obs: torch.Tensor, goal: torch.Tensor, double_rows: int | None = None) -> torch.Tensor:
        """(..., 1) the target network's value of (obs, goal): of the online network's greedy action (double DQN)
        or its own max. ``double_rows``: only the first that many rows take the online network's action, the others
        the target network's own max (``agent.successor_double_dqn: false``: no online pass for the model targets'
        successors)."""
        if self.before_target_read is not None:
            self.before_target_read(obs, goal)
        if self.factored:
            q = self.target_value_network.network.factored_q(obs, goal)
        else:
            q = self.target_value_network(obs, goal)
        if not self.double_dqn:
            return q.amax(-1, keepdim=True)
        if double_rows is None:
            return q.gather(-1, self._online(obs, goal).argmax(-1, keepdim=True))
        head = q[:double_rows].gather(-1, self._online(obs[:double_rows], goal[:double_rows]).argmax(-1, keepdim=True))
        return torch.cat((head, q[double_rows:].amax(-1, keepdim=True)))

    def _online(self, obs: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        return self.value_network.factored_q(obs, goal) if self.factored else self.value_network(obs, goal)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        obs, goal = tensordict.get("observation"), tensordict.get("desired_goal")
        action = tensordict.get("action").unsqueeze(-1)
        q_all = self.value_network(obs, goal)
        pred = q_all.gather(-1, action)
        with torch.no_grad():
            target, held = self.td_target(tensordict, q_all, self.bootstrap)
        loss = distance_loss(pred.squeeze(-1), target.squeeze(-1), self.loss_function).mean()
        if held is not None:  # every action but the taken one, against what the target holds it to
            others = torch.ones_like(held, dtype=torch.bool).scatter_(-1, action, False)
            outside = distance_loss(q_all, held, self.loss_function) * others
            loss = loss + outside.sum(-1).mean()
        detached = pred.detach()
        return TensorDict(loss=loss, q_mean=detached.mean(), td_abs=(detached - target).abs().mean())


def value_range(gamma: float, step_cost: float, max_steps: int) -> tuple[float, float]:
    """The values the learner's Q can take: between an episode that never reaches the goal (``max_steps`` steps of
    reward ``-step_cost``) and one that enters it on the first step (``1 - step_cost``)."""
    never = -step_cost * (max_steps if gamma == 1 else (1 - gamma**max_steps) / (1 - gamma))
    return never, 1.0 - step_cost


class DQNAgent:
    """The goal-conditioned DQN learner and its epsilon-greedy collection policy (an :class:`~ss_drl.agents.Agent`).

    Built from TorchRL parts: the HER replay buffer is a TorchRL ``TensorDictReplayBuffer``, the loss a TorchRL
    ``LossModule`` (:class:`GoalDQNLoss`), the target network moved by ``HardUpdate``/``SoftUpdate``.

    Args:
        settings: the typed settings (``DQNSettings.from_config(cfg.agent)``).
        maze: the maze (the network's grid; the goal G).
        replay_buffer: the HER replay buffer it samples from.
        td_target: the TD target (:func:`~ss_drl.agents.targets.make_td_target`); None builds it from ``settings``
            without a count model, which only a learner without the count model's bounds can do.
        max_steps: the episode cut, for the value range of ``clip_targets``.
    """

    def __init__(
        self,
        settings: DQNSettings,
        maze: Maze,
        replay_buffer,
        td_target: TDTarget | None = None,
        seed: int = 0,
        max_steps: int = 1000,
    ):
        s = self.settings = settings
        self.maze = maze
        self.replay_buffer = replay_buffer
        self.q_network = GoalQNetwork(maze, s.encoder, s.embed_dim, s.hidden, s.dueling, s.sparse_tables)
        self.epsilon = float(s.eps_start)
        # The learner's reward is the env's minus this cost: 1 gives -1 per step and 0 on entering the goal.
        self.step_cost, self.gamma = s.step_cost, s.gamma
        if td_target is None:
            clip = value_range(s.gamma, s.step_cost, max_steps) if s.clip_targets else None
            td_target = make_td_target(s, maze, None, clip, holds=MAZE)  # no count model: no ceiling to pick
        self.td_target = td_target
        if "hindsight_bound" in td_target.names and not getattr(replay_buffer, "goal_steps", False):
            raise ValueError("agent.hindsight_bound needs a replay buffer built with goal_steps=True")
        if "n_step_max" in td_target.names and not getattr(replay_buffer, "window_states", False):
            raise ValueError("agent.n_step_max needs a replay buffer built with window_states=True")
        if s.bounded_policy and not td_target.bounds_all_actions:
            raise ValueError(
                "agent.bounded_policy needs a TD target whose bounds hold every action (bound_all_actions)"
            )
        self.loss = GoalDQNLoss(
            self.q_network, td_target, double_dqn=s.double_dqn, loss_function=s.loss, factored=s.factored_bootstrap
        )
        if s.target_update == "hard":
            self.target_updater = HardUpdate(self.loss, value_network_update_interval=s.target_update_interval)
        else:
            self.target_updater = PolyakUpdate(self.loss, tau=s.tau)
        self.tables: LazyPolyak | None = None  # the per-cell tables' lazy Polyak step (sparse_tables)
        self.table_optimizer: LazyAdam | None = None
        params = list(self.loss.parameters())
        if s.sparse_tables:
            if s.target_update != "soft":
                raise ValueError("agent.sparse_tables: needs agent.target_update=soft (its Polyak step is lazy)")
            params = self._sparse_tables(params, s)
        self.optimizer = torch.optim.Adam(params, lr=s.lr, fused=True)
        self.goal_cell = maze.goal_cell
        self.updates = 0

    def _sparse_tables(self, params: list[torch.Tensor], s: DQNSettings) -> list[torch.Tensor]:
        """Split the per-cell tables from ``params``: a lazy Adam for them, :class:`LazyPolyak` for their target
        copies; returns the dense parameters."""
        pairs, keys = [], []
        for name, side in table_keys(self.q_network):
            key = tuple(name.split("."))
            online = self.loss.value_network_params.get(key)
            pairs.append((online, self.loss.target_value_network_params.get(key).data, side))
            keys.append(key)
        if not pairs:
            raise ValueError(f"agent.sparse_tables: the {s.encoder!r} encoder has no per-cell table")
        tables = {p.data_ptr() for p, _, _ in pairs}
        self.table_optimizer = LazyAdam([p for p, _, _ in pairs], lr=s.lr)
        self.tables = LazyPolyak([(p.data, t, side) for p, t, side in pairs], s.tau)
        self.target_updater.exclude = frozenset(("value_network_params", *key) for key in keys)
        self.loss.before_target_read = lambda obs, goal: self.tables.catch_up({"state": obs, "goal": goal})
        return [p for p in params if p.data_ptr() not in tables]

    @property
    def bounds_in_force(self) -> list[str]:
        """What ``summary.json`` lists as ``bounds_in_force``: the TD target's
        (:attr:`~ss_drl.agents.targets.TDTarget.in_force`), then ``bounded_policy`` when the policy reads them too."""
        return self.td_target.in_force + (["bounded_policy"] if self.settings.bounded_policy else [])

    # --- acting ------------------------------------------------------------------------------------------------
    @torch.no_grad()
    def act(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        """Epsilon-greedy actions for a batch of (state, goal) cells.

        The raw network is called directly: at one env copy this runs every env step, and the TensorDict module
        wrappers would cost several times the forward pass itself.
        """
        q = self.policy_q(self.q_network(observation, desired_goal), observation, desired_goal)
        return epsilon_greedy(q.argmax(dim=-1), self.epsilon, n_actions=self.maze.n_actions)

    def policy_q(self, q: torch.Tensor, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(R, A) the values the policy takes its greedy action from, for the network's (R, A) ``q`` of the rows
        (``states``, ``goals``) (R,): ``q`` itself, or with ``agent.bounded_policy`` ``q`` held to the same
        all-action bounds as the targets (:meth:`~ss_drl.agents.targets.TDTarget.hold`). Where the bounds are valid
        they contain Q*, so holding an estimate to them never moves it away from Q*: where the count model knows every
        action's steps to G exactly, the greedy action is a shortest path's whatever the network's error."""
        if not self.settings.bounded_policy:
            return q
        return self.td_target.hold({"observation": states, "desired_goal": goals}, q)

    def _policy_goal_q(self, network, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, A) :meth:`policy_q` of ``network`` for every state (n,) and goal (B,), on the learner's scale."""
        q = network.goal_q_values(states, goals)
        if not self.settings.bounded_policy:
            return q
        rows = (states.repeat(goals.numel()), goals.repeat_interleave(states.numel()))
        return self.policy_q(q.reshape(-1, q.shape[-1]), *rows).view(q.shape)

    @torch.no_grad()
    def q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, 4): Q(s||g, .) on the env's reward scale of every state in ``states`` (n,) for each goal in
        ``goals`` (B,), in one batched pass (:meth:`GoalQNetwork.goal_q_values`)."""
        return self.env_scale(self._policy_goal_q(self.q_network, states, goals))

    @torch.no_grad()
    def greedy_q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """:meth:`q_values` of the network whose greedy policy is evaluated: the online network, or with
        ``eval_network: target`` the target network (with Polyak updates, the online network's weights averaged
        over the last ~1/tau updates). Collection and the TD targets read the online and target networks either
        way; Smart Start's greedy-path walk (``smart_start.greedy_path``) reads this one, so with that option the
        choice also decides S_ss (and with ``sparse_tables`` the target's lagging rows catch up at each episode
        start, which moves their float rounding). Without it the choice changes no training."""
        network = self.loss.target_value_network.network if self.settings.eval_network == "target" else self.q_network
        if network is not self.q_network and self.tables is not None:
            self.tables.catch_up()
        return self.env_scale(self._policy_goal_q(network, states, goals))

    def env_scale(self, q: torch.Tensor) -> torch.Tensor:
        """Map the learner's values (reward ``r - step_cost``) to the env's 0/1 reward scale.

        An episode that enters the goal on its d-th step is worth ``gamma^(d-1)`` with the env's reward and
        ``Q' = gamma^(d-1) (1 + c gamma / (1 - gamma)) - c / (1 - gamma)`` with the step cost c (an endless one:
        0 and ``-c / (1 - gamma)``). The map is affine, so it holds in expectation for any policy, keeps the greedy
        action, and gives Smart Start's UCB the scale of the paper's ``max_a Q`` whatever the step cost.
        """
        c, gamma = self.step_cost, self.gamma
        if c == 0:
            return q
        if gamma == 1:
            # Undiscounted cost form: Q = 1 - c d for a goal d steps away. With no discount of its own to map to,
            # the distance is put on the 0/1 scale with the planner's default discount: 0.99^(d - 1).
            return UNDISCOUNTED_SCALE ** ((1 - q) / c - 1)
        return ((1 - gamma) * q + c) / ((1 - gamma) + c * gamma)

    # --- learning ----------------------------------------------------------------------------------------------
    def store(self, batch: TensorDictBase) -> None:
        """Write a collected (T, N) batch to the HER replay buffer."""
        self.replay_buffer.extend(batch)

    def updates_due(self, env_steps: int, new_steps: int) -> int:
        """``gradient_steps`` updates per ``train_freq`` env steps, from ``learning_starts`` on (and once the buffer
        holds a batch); at the defaults, one update per env step."""
        s = self.settings
        if env_steps < s.learning_starts or len(self.replay_buffer) < s.batch_size:
            return 0
        rounds = env_steps // s.train_freq - (env_steps - new_steps) // s.train_freq
        return rounds * s.gradient_steps

    def update(self) -> torch.Tensor:
        """One gradient step on a HER-relabeled sample; returns :data:`~ss_drl.agents.UPDATE_METRICS`.

        Nothing here reads a value back to the host: the loop checks the loss for NaN at its logging cadence.
        """
        sample = self.replay_buffer.sample()
        out = self.loss(sample)
        loss = out.get("loss")
        self.optimizer.zero_grad(set_to_none=True)
        if self.tables is None:
            loss.backward()
            if self.settings.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.settings.grad_clip, foreach=True)
            self.optimizer.step()
            self.target_updater.step()
        else:
            self.table_optimizer.zero_grad()
            loss.backward()
            if self.settings.grad_clip > 0:
                clip_grad_norm(list(self.loss.parameters()), self.settings.grad_clip)
            # The rows the batch touched: caught up before the optimizer moves them, then one Polyak step each.
            touched = {side: online.grad.coalesce()._indices()[0] for online, (_, _, side) in self._table_params()}
            self.tables.catch_up(touched)
            self.optimizer.step()
            self.table_optimizer.step()
            self.target_updater.step()
            self.tables.step(touched)
        self.updates += 1
        her_share = sample.get("relabeled").float().mean()
        goal_share = (sample.get("desired_goal") == self.goal_cell).float().mean()
        return torch.stack((loss.detach(), out.get("q_mean"), out.get("td_abs"), her_share, goal_share))

    def _table_params(self):
        """(online parameter, LazyPolyak pair) of each per-cell table."""
        return zip(self.table_optimizer.params, self.tables.pairs)

    # --- persistence -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "loss": self.loss.state_dict(),
            "epsilon": self.epsilon,
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            "target_counter": getattr(self.target_updater, "counter", 0),
            "replay_buffer": self.replay_buffer.state_dict(),
            **(
                {}
                if self.tables is None
                else {"table_optimizer": self.table_optimizer.state_dict(), "tables": self.tables.state_dict()}
            ),
        }

    def load_state_dict(self, state: dict) -> None:
        self.loss.load_state_dict(state["loss"])
        self.epsilon = state["epsilon"]
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = state["updates"]
        if hasattr(self.target_updater, "counter"):
            self.target_updater.counter = state["target_counter"]
        self.replay_buffer.load_state_dict(state["replay_buffer"])
        if self.tables is not None:
            self.table_optimizer.load_state_dict(state["table_optimizer"])
            self.tables.load_state_dict(state["tables"])
