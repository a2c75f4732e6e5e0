"""The goal-conditioned Q-network Q(s||g, .): separate state and goal encoders, an MLP trunk, a dueling head."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ss_drl.agents.settings import ENCODERS
from ss_drl.envs.maze import Maze

#: Rows (state, goal pairs) evaluated per block by :meth:`GoalQNetwork.goal_q_values` (a block stays in cache).
BLOCK_ROWS = 1024
_scratch: dict[int, torch.Tensor] = {}  # one per trunk layer


def _buffer(key: int, rows: int, like: torch.Tensor, width: int) -> torch.Tensor:
    """A reusable (rows, width) scratch tensor (dtype and device of ``like``). Fresh multi-MB activations are
    faulted in page by page on every evaluation, which cost up to a third of its time; reused ones are not."""
    buf = _scratch.get(key)
    if (
        buf is None
        or buf.shape[0] < rows
        or buf.shape[1] != width
        or (buf.dtype, buf.device) != (like.dtype, like.device)
    ):
        buf = _scratch[key] = torch.empty(rows, width, dtype=like.dtype, device=like.device)
    return buf[:rows]


def _linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, out: torch.Tensor) -> torch.Tensor:
    if bias is None:
        return torch.mm(x, weight.T, out=out)
    return torch.addmm(bias, x, weight.T, out=out)


class CellEncoder(nn.Module):
    """Embeds flat cell indices.

    ``embedding``: a learned vector per cell. ``coords``: an MLP over the normalized (row, col), which generalises
    across neighbouring cells. ``hybrid``: the coords MLP plus a learned vector per cell that starts at zero, so the
    encoder begins as ``coords`` and each cell can then move away from its neighbours' code, as the two sides of a
    wall must (their distances to a goal can differ by a hundred steps).

    ``sparse``: the per-cell table's gradient is sparse (``agent.sparse_tables``, :mod:`ss_drl.agents.tables`).
    """

    def __init__(self, maze: Maze, kind: str, dim: int, sparse: bool = False):
        super().__init__()
        if kind not in ENCODERS:
            raise ValueError(f"unknown encoder {kind!r} (allowed: {', '.join(ENCODERS)})")
        self.kind = kind
        self.width = maze.width
        self.cells = None  # hybrid's per-cell table
        if kind == "embedding":
            self.net = nn.Embedding(maze.n_cells, dim, sparse=sparse)
            return
        self.register_buffer("scale", torch.tensor([max(maze.height - 1, 1), max(maze.width - 1, 1)]).float())
        self.net = nn.Sequential(nn.Linear(2, dim), nn.ReLU(), nn.Linear(dim, dim))
        if kind == "hybrid":
            self.cells = nn.Embedding(maze.n_cells, dim, sparse=sparse)
            nn.init.zeros_(self.cells.weight)

    def forward(self, cell: torch.Tensor) -> torch.Tensor:
        if self.kind == "embedding":
            return self.net(cell)
        pos = torch.stack((cell // self.width, cell % self.width), dim=-1).float() / self.scale
        code = self.net(pos)
        return code if self.cells is None else code + self.cells(cell)


class MiniGridStateEncoder(nn.Module):
    """Embeds the state ids of a MiniGrid task (:class:`~ss_drl.envs.minigrid.MiniGridTask`).

    ``coords``: the coords MLP over the agent's cell (as :class:`CellEncoder`'s), plus learned vectors of its
    direction, of each door's state (open, closed, locked; one vector per door and state, summed over the doors) and
    of the carried object. ``hybrid``: those plus a learned vector per state id that starts at zero. ``embedding``: a
    learned vector per state id only. The per-id table has a row for every state the task can reach (the task
    enumerates them before training).
    """

    def __init__(self, task, kind: str, dim: int, sparse: bool = False):
        super().__init__()
        if kind not in ENCODERS:
            raise ValueError(f"unknown encoder {kind!r} (allowed: {', '.join(ENCODERS)})")
        self.kind = kind
        self.register_buffer("features", torch.from_numpy(task.features).clone(), persistent=False)
        self.cells = None  # the per-state-id table
        if kind in ("embedding", "hybrid"):
            self.cells = nn.Embedding(task.n_states, dim, sparse=sparse)
            if kind == "hybrid":
                nn.init.zeros_(self.cells.weight)
        self.net = None
        if kind != "embedding":
            self.net = CellEncoder(task, "coords", dim)
            self.direction = nn.Embedding(4, dim)
            self.carrying = nn.Embedding(task.n_pickables + 1, dim)
            self.doors = nn.Embedding(max(3 * task.n_doors, 1), dim)
            self.register_buffer("door_offset", 3 * torch.arange(task.n_doors), persistent=False)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        if self.net is None:
            return self.cells(state)
        f = self.features[state]
        code = self.net(f[..., 0]) + self.direction(f[..., 1]) + self.carrying(f[..., 2])
        if self.door_offset.numel():
            code = code + self.doors(f[..., 3:] + self.door_offset).sum(dim=-2)
        return code if self.cells is None else code + self.cells(state)


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
        sparse_tables: bool = False,
    ):
        super().__init__()
        if getattr(maze, "features", None) is not None:  # a MiniGrid task: states are ids, goals are cells
            self.state_encoder = MiniGridStateEncoder(maze, encoder, embed_dim, sparse_tables)
        else:
            self.state_encoder = CellEncoder(maze, encoder, embed_dim, sparse_tables)
        self.goal_encoder = CellEncoder(maze, encoder, embed_dim, sparse_tables)
        layers, width = [], 2 * embed_dim
        for size in hidden:
            layers += [nn.Linear(width, size), nn.ReLU()]
            width = size
        self.trunk = nn.Sequential(*layers)
        self.dueling = dueling
        self.advantage = nn.Linear(width, maze.n_actions)
        self.value = nn.Linear(width, 1) if dueling else None

    def forward(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        h = self.trunk(torch.cat((self.state_encoder(observation), self.goal_encoder(desired_goal)), dim=-1))
        adv = self.advantage(h)
        if not self.dueling:
            return adv
        return self.value(h) + adv - adv.mean(dim=-1, keepdim=True)

    @torch.no_grad()
    def factored_q(self, observation: torch.Tensor, desired_goal: torch.Tensor) -> torch.Tensor:
        """``self(observation, desired_goal)`` for many rows without gradient (the TD target's bootstrap passes),
        with the encoders and each half of the first layer computed once per distinct cell instead of once per row.

        The first layer acts on ``concat(e_s, e_g)``: ``W [e_s; e_g] + b = W_s e_s + (W_g e_g + b)``. A bootstrap
        batch holds each state and each goal many times (the window's states and the successors share the sample's
        goal; neighbouring samples share states), so the state half is computed for the distinct states and the goal
        half for the distinct goals, and each row adds the two. The same numbers as :meth:`forward` up to float
        rounding (``agent.factored_bootstrap``).
        """
        states, s_row = torch.unique(observation.reshape(-1), return_inverse=True)
        goals, g_row = torch.unique(desired_goal.reshape(-1), return_inverse=True)
        first = self.trunk[0]
        d_s = first.in_features // 2
        h_s = F.linear(self.state_encoder(states), first.weight[:, :d_s])
        h_g = F.linear(self.goal_encoder(goals), first.weight[:, d_s:], first.bias)
        h = self.trunk[1:](h_s.index_select(0, s_row).add_(h_g.index_select(0, g_row)))
        adv = self.advantage(h)
        if self.dueling:
            adv = self.value(h) + adv - adv.mean(dim=-1, keepdim=True)
        return adv.view(*observation.shape, -1)

    @torch.no_grad()
    def goal_q_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """(B, n, A): Q(s||g, .) for every state in ``states`` (n,) and goal in ``goals`` (B,).

        The same numbers as ``self(states.repeat(B), goals.repeat_interleave(n))`` up to float rounding, for less
        work: the first trunk layer acts on ``concat(e_s, e_g)``, so ``W [e_s; e_g] + b = W_s e_s + (W_g e_g + b)``: the
        state half is computed once per state and the goal half once per goal, instead of both for every (state, goal)
        pair. The dueling head ``Q = V + A - mean_a A`` is linear in the last hidden layer, so it is folded into one
        (A x H) matrix. The rows are evaluated in blocks of ``BLOCK_ROWS`` through reused scratch buffers.
        """
        trunk = list(self.trunk)
        first = trunk[0]
        e_s = self.state_encoder(states)  # (n, E)
        e_g = self.goal_encoder(goals)  # (B, E)
        d_s, n, n_b = e_s.shape[-1], states.numel(), goals.numel()
        w_s = first.weight[:, :d_s].T
        h_g = F.linear(e_g, first.weight[:, d_s:], first.bias)  # (B, H): the goal half and the bias, once per goal
        h_s = e_s @ w_s if n_b > 1 else None  # (n, H): the state half, once per state
        adv = self.advantage
        head_w, head_b = adv.weight, adv.bias
        if self.dueling:
            value = self.value
            head_w = value.weight + adv.weight - adv.weight.mean(dim=0, keepdim=True)
            head_b = value.bias + adv.bias - adv.bias.mean()
        q = torch.empty(n_b, n, head_w.shape[0], dtype=h_g.dtype, device=h_g.device)
        block = min(BLOCK_ROWS, n)
        for b in range(n_b):
            for start in range(0, n, block):
                stop = min(start + block, n)
                out = _buffer(0, block, h_g, first.out_features)[: stop - start]
                if h_s is None:
                    h = torch.addmm(h_g[b], e_s[start:stop], w_s, out=out)
                else:
                    h = torch.add(h_s[start:stop], h_g[b], out=out)
                for k, layer in enumerate(trunk[1:], start=1):
                    if isinstance(layer, nn.ReLU):
                        h = h.relu_()
                    else:
                        out = _buffer(k, block, h, layer.out_features)[: stop - start]
                        h = _linear(h, layer.weight, layer.bias, out)
                _linear(h, head_w, head_b, q[b, start:stop])
        return q
