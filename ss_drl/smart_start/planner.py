"""The planner: value iteration on the count model's learned transition model, towards the smart start state.

For a target S_ss the planning problem is: reward 1 on every observed transition into S_ss (with a distance
threshold theta > 0: into any state within Manhattan distance theta of S_ss), those states terminal, discount
gamma, untried actions valued 0. Value iteration runs synchronous (Jacobi) sweeps

    Q(s, a) = sum_s' P(s'|s,a) [ r(s,a,s') + gamma * V(s') * (1 - terminal(s')) ],   V(s) = max_a Q(s, a)

from V = 0 until the largest change of V is below ``tol`` or after ``max_sweeps`` sweeps. With V held at 0 on the
terminal states, one sweep is ``Q = b + gamma * sum_k P_k * V[succ_k]`` where ``b(s,a)`` is the probability that
(s, a) leads into the terminal set and ``succ_k``/``P_k`` hold the k-th observed successor of each (s, a) (one layer
in a deterministic maze). Several targets (one per env copy) are planned at once as the columns of V.
"""

from __future__ import annotations

import dataclasses

import torch

from ss_drl.smart_start.counts import CountModel


@dataclasses.dataclass
class Plan:
    """The result of planning towards ``targets`` (one column per target)."""

    targets: torch.Tensor  # (B,) target states
    values: torch.Tensor  # (S, B) V(s) per target
    q_values: torch.Tensor  # (S, A, B)
    policy: torch.Tensor  # (B, S) greedy action per state, ties broken at random
    sweeps: int  # sweeps run
    converged: bool  # largest change < tol before max_sweeps


class Planner:
    """Value iteration towards a target state on a :class:`CountModel`.

    Args:
        width: maze width, to measure Manhattan distances on the grid for ``theta``.
        gamma: discount of the planning problem.
        theta: distance threshold: states within ``theta`` of the target count as reaching it (0: only the target).
        tol: stop when the largest change of V in a sweep is below this.
        max_sweeps: stop after this many sweeps in any case.
    """

    def __init__(self, width: int, gamma: float = 0.99, theta: int = 0, tol: float = 1e-3, max_sweeps: int = 1000):
        self.width = int(width)
        self.gamma = float(gamma)
        self.theta = int(theta)
        self.tol = float(tol)
        self.max_sweeps = int(max_sweeps)

    def terminal_mask(self, n_states: int, targets: torch.Tensor) -> torch.Tensor:
        """(S, B) bool: states within ``theta`` (Manhattan) of each target."""
        cells = torch.arange(n_states)
        if self.theta == 0:
            return cells.unsqueeze(1) == targets.unsqueeze(0)
        r, c = cells // self.width, cells % self.width
        tr, tc = targets // self.width, targets % self.width
        dist = (r.unsqueeze(1) - tr.unsqueeze(0)).abs() + (c.unsqueeze(1) - tc.unsqueeze(0)).abs()
        return dist <= self.theta

    def plan(self, model: CountModel, targets: torch.Tensor | int, generator: torch.Generator | None = None) -> Plan:
        """Plan towards each of ``targets`` (a state or a (B,) tensor of states) on the model's current counts."""
        targets = torch.as_tensor(targets, dtype=torch.int64).reshape(-1)
        n_a, n_b = model.n_actions, targets.numel()
        s, a, s2, prob = model.transitions()
        # Compact the problem to the states with tried actions. Every other state has all actions untried, so its
        # value is 0 for good: it maps to one extra "dummy" slot whose value stays 0.
        states = model.visited_states()
        n_v = states.numel()
        slot = torch.full((model.n_states,), n_v, dtype=torch.int64)
        slot[states] = torch.arange(n_v)
        row, col = slot[s], slot[s2]
        # Entries are sorted by (s, a, s'): an entry's rank among the successors of its (s, a) picks its layer k.
        sa = s * n_a + a
        rank = torch.arange(sa.numel()) - torch.searchsorted(sa, sa)
        n_k = int(rank.max()) + 1 if sa.numel() else 1
        successor = torch.full((n_k, n_a, n_v), n_v, dtype=torch.int64)  # untried: the dummy slot, P = 0
        gamma_prob = torch.zeros(n_k, n_a, n_v, dtype=torch.float32)
        successor[rank, a, row] = col
        gamma_prob[rank, a, row] = (self.gamma * prob).to(torch.float32)
        terminal = self.terminal_mask(model.n_states, targets).T  # (B, S)
        # r(s, a) = P(terminal set | s, a): reward 1 on transitions into the target (region).
        reward = torch.zeros(n_b, n_a * n_v, dtype=torch.float32)
        reward.index_add_(1, a * n_v + row, prob.to(torch.float32) * terminal[:, s2])
        reward = reward.view(n_b, n_a, n_v)
        keep = (~terminal[:, states]).to(torch.float32)  # V is held at 0 on terminal states

        # Values are laid out (B, n_v + 1), which makes the gather along the last dim fast. values[:, n_v] is the
        # dummy slot, always 0. Two buffers, swapped each sweep.
        values, new_values = torch.zeros(n_b, n_v + 1), torch.zeros(n_b, n_v + 1)
        index = successor.reshape(-1)
        q = reward
        sweeps, converged = 0, False
        while sweeps < self.max_sweeps:
            bootstrap = values.index_select(1, index).view(n_b, n_k, n_a, n_v)
            if n_k == 1:
                q = torch.addcmul(reward, gamma_prob[0], bootstrap[:, 0])
            else:
                q = reward + (gamma_prob * bootstrap).sum(1)
            torch.mul(q.amax(dim=1), keep, out=new_values[:, :n_v])
            sweeps += 1
            delta = float((new_values - values).abs_().max())
            values, new_values = new_values, values
            if delta < self.tol:
                converged = True
                break
        q = q.permute(2, 1, 0)  # (n_v, A, B)
        values = values[:, :n_v].T  # (n_v, B)
        # Back to full state indexing. States without tried actions: value 0, every action tied.
        full_q = torch.zeros(model.n_states, n_a, n_b, dtype=torch.float32)
        full_q[states] = q
        full_v = torch.zeros(model.n_states, n_b, dtype=torch.float32)
        full_v[states] = values
        return Plan(targets, full_v, full_q, self.greedy(full_q, generator), sweeps, converged)

    @staticmethod
    def greedy(q: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, S) argmax_a of q (S, A, B), ties broken uniformly at random."""
        best = q.amax(dim=1, keepdim=True)
        noise = torch.rand(q.shape, generator=generator, dtype=q.dtype)
        return torch.where(q >= best, noise, -1.0).argmax(dim=1).T.contiguous()
