"""The planner: value iteration on the count model's learned transition model, towards the smart start state.

For a target S_ss the planning problem is: reward 1 on every observed transition into S_ss (with a distance
threshold theta > 0: into any state within Manhattan distance theta of S_ss), those states terminal, discount
gamma, untried actions valued 0. Value iteration runs synchronous (Jacobi) sweeps

    Q(s, a) = sum_s' P(s'|s,a) [ r(s,a,s') + gamma * V(s') * (1 - terminal(s')) ],   V(s) = max_a Q(s, a)

from V = 0 until the largest change of V is below ``tol`` or after ``max_sweeps`` sweeps. With V held at 0 on the
terminal states, one sweep is ``Q = b + gamma * sum_k P_k * V[succ_k]`` where ``b(s,a)`` is the probability that
(s, a) leads into the terminal set and ``succ_k``/``P_k`` hold the k-th observed successor of each (s, a) (one layer
in a deterministic maze). Several targets (one per env copy) are planned at once as the columns of V.

When every tried (s, a) has one observed successor (a deterministic maze), the sweeps' result is a function of each
state's graph distance to the terminal set, so the planner computes it from a breadth-first search instead of
sweeping (:meth:`Planner._deterministic_sweeps`); the result, sweep count included, is the same bit for bit.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ss_drl.graph import breadth_first
from ss_drl.ops import manhattan, random_argmax
from ss_drl.smart_start.counts import CountModel, ModelStructure


@dataclasses.dataclass
class Plan:
    """The result of planning towards ``targets`` (one column per target)."""

    targets: torch.Tensor  # (B,) target states (-1 where a row plans towards a set of states)
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
        cells: a state's cell (None: states are cells, as in a maze); in a MiniGrid task the target is reached in
            any state of the target's cell (and theta measures between cells).
    """

    def __init__(
        self,
        width: int,
        gamma: float = 0.99,
        theta: int = 0,
        tol: float = 1e-3,
        max_sweeps: int = 1000,
        cells=None,
    ):
        self.width = int(width)
        self.cells = cells
        self.gamma = float(gamma)
        self.theta = int(theta)
        self.tol = float(tol)
        self.max_sweeps = int(max_sweeps)

    def terminal_mask(self, n_states: int, targets: torch.Tensor) -> torch.Tensor:
        """(S, B) bool: states within ``theta`` (Manhattan) of each target."""
        cells = torch.arange(n_states)
        if self.cells is not None:
            cells, targets = self.cells(cells), self.cells(targets)
        if self.theta == 0:
            return cells.unsqueeze(1) == targets.unsqueeze(0)
        return manhattan(cells.unsqueeze(1), targets.unsqueeze(0), self.width) <= self.theta

    def plan(self, model: CountModel, targets: torch.Tensor | int, generator: torch.Generator | None = None) -> Plan:
        """Plan towards each of ``targets`` (a state or a (B,) tensor of states) on the model's current counts."""
        targets = torch.as_tensor(targets, dtype=torch.int64).reshape(-1)
        return self.plan_to(model, self.terminal_mask(model.n_states, targets).T, generator, targets)

    def plan_to(
        self,
        model: CountModel,
        terminal: torch.Tensor,
        generator: torch.Generator | None = None,
        targets: torch.Tensor | None = None,
    ) -> Plan:
        """Plan towards each row of ``terminal`` ((B, S) bool: a set of states to reach, as the nearest frontier state
        for Smart Start's exploration phase) on the model's current counts: reward 1 on entering the set."""
        st = model.structure()
        # Compact the problem to the states with tried actions (the structure's slots). Every other state has all
        # actions untried, so its value is 0 for good: it maps to one extra "dummy" slot whose value stays 0.
        if targets is None:
            targets = torch.full((terminal.shape[0],), -1, dtype=torch.int64)
        if st.deterministic:
            q, values, sweeps, converged = self._deterministic_sweeps(st, model.n_actions, terminal)
        else:
            q, values, sweeps, converged = self._sweeps(st, model, terminal)
        n_b = targets.numel()
        # Back to full state indexing. States without tried actions: value 0, every action tied.
        full_q = torch.zeros(model.n_states, model.n_actions, n_b, dtype=torch.float32)
        full_q[st.states] = q.permute(2, 1, 0)  # (n_v, A, B)
        full_v = torch.zeros(model.n_states, n_b, dtype=torch.float32)
        full_v[st.states] = values[:, : st.states.numel()].T
        return Plan(targets, full_v, full_q, self.greedy(full_q, generator), sweeps, converged)

    def _sweeps(self, st: ModelStructure, model: CountModel, terminal: torch.Tensor):
        """Value iteration on any learned model: synchronous sweeps until the largest change is below ``tol``.

        Returns q (B, A, n_v) of the last sweep, values (B, n_v + 1) after it, the sweeps run and whether it converged.
        """
        n_a, n_b, n_v, n_k = model.n_actions, terminal.shape[0], st.states.numel(), st.n_layers
        prob = model.sas_counts.to(torch.float64) / model.sa_counts[st.sa].to(torch.float64)
        gamma_prob = torch.zeros(n_k, n_a, n_v, dtype=torch.float32)  # untried: the dummy slot, P = 0
        gamma_prob[st.layer, st.action, st.row] = (self.gamma * prob).to(torch.float32)
        # r(s, a) = P(terminal set | s, a): reward 1 on transitions into the target (region).
        reward = torch.zeros(n_b, n_a * n_v, dtype=torch.float32)
        reward.index_add_(1, st.action * n_v + st.row, prob.to(torch.float32) * terminal[:, st.next_state])
        reward = reward.view(n_b, n_a, n_v)
        keep = (~terminal[:, st.states]).to(torch.float32)  # V is held at 0 on terminal states

        # Values are laid out (B, n_v + 1), which makes the gather along the last dim fast. values[:, n_v] is the
        # dummy slot, always 0. Two buffers, swapped each sweep.
        values, new_values = torch.zeros(n_b, n_v + 1), torch.zeros(n_b, n_v + 1)
        index = st.successor.reshape(-1)
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
        return q, values, sweeps, converged

    def _deterministic_sweeps(self, st: ModelStructure, n_a: int, terminal: torch.Tensor):
        """What :meth:`_sweeps` computes, without sweeping, on a model where each tried (s, a) has one successor.

        Reward 1 on entering the terminal set, V = 0 on it and successors that are certain make the values after
        sweep k a function of the graph distance d(s) (fewest tried steps from s into the terminal set):
        V_k(s) = p[d(s)] if d(s) <= k else 0, where p[1] = 1 and p[d] = gamma * p[d - 1], rounded to float32 at each
        step exactly as the sweeps' multiply-adds round. The largest change of sweep k is thus p[k] while some state
        lies at distance k, then 0. A breadth-first search from the terminal set, level k standing for sweep k, finds
        the distances and where the sweeps stop; q and V are then rebuilt from the last two sweeps' values.
        """
        n_b, n_v = terminal.shape[0], st.states.numel()
        into_state, preds = st.predecessors()
        p, k_tol = self._powers()
        # Sweep k changes V by p[k] >= tol while k <= depth (the deepest distance), so the sweeps stop at
        # min(depth + 1, k_tol, max_sweeps), k_tol the first k with p[k] < tol: levels past that are never needed.
        limit = min(k_tol, self.max_sweeps)
        slot = st.derived["slot"]
        levels, depth = [], 0
        for cells in terminal.tolist() if n_b > 1 else [terminal[0]]:
            cells = torch.nonzero(torch.as_tensor(cells)).squeeze(-1).tolist()
            dist = [-1] * (n_v + 1)
            dist[n_v] = 0  # the dummy slot, and the terminal slots, never get a distance
            for c in cells:
                if slot[c] < n_v:
                    dist[slot[c]] = 0
            # Level 1: non-terminal slots with a tried action into the terminal set.
            front = []
            for c in cells if limit > 0 else ():
                for y in into_state.get(c, ()):
                    if dist[y] < 0:
                        dist[y] = 1
                        front.append(y)
            depth = max(depth, breadth_first(front, dist, preds, limit))
            levels.append(np.fromiter(dist, np.int64, n_v + 1))
        sweeps = min(depth + 1, k_tol, self.max_sweeps)
        converged = min(depth + 1, k_tol) <= self.max_sweeps
        d = torch.from_numpy(np.stack(levels)).clamp_(min=0)  # (B, n_v + 1), 0 for "no distance"
        table = torch.tensor([0.0, *p[1 : sweeps + 1]], dtype=torch.float32)  # table[d] = p[d], table[0] = 0
        values = table.take(d)
        # q of the last sweep bootstraps from the values of the one before: distances < sweeps.
        before = values.masked_fill(d == sweeps, 0.0)
        reward = torch.zeros(n_b, n_a * n_v, dtype=torch.float32)
        reward.index_copy_(1, st.derived["reward_index"], terminal.index_select(1, st.next_state).to(torch.float32))
        bootstrap = before.index_select(1, st.derived["successor"])
        q = reward.add_(bootstrap, alpha=float(np.float32(self.gamma)))
        return q.view(n_b, n_a, n_v), values, sweeps, converged

    def _powers(self) -> tuple[list[float], int]:
        """p[k] for k = 1 .. max_sweeps (p[0] = 0 unused), p[1] = 1, p[k] = float32(gamma) * p[k - 1] in float32;
        and k_tol, the first k with p[k] < tol (max_sweeps + 1 if none)."""
        key = (self.gamma, self.max_sweeps, self.tol)
        if getattr(self, "_powers_key", None) != key:
            g = np.float32(self.gamma)
            p, x = [0.0], np.float32(1.0)
            for _ in range(self.max_sweeps):
                p.append(float(x))
                x = np.float32(g * x)
            k_tol = next((k for k in range(1, len(p)) if p[k] < self.tol), len(p))
            self._powers_key, self._powers_cache = key, (p, k_tol)
        return self._powers_cache

    @staticmethod
    def route_length(values: torch.Tensor, gamma: float) -> torch.Tensor:
        """The number of steps to the terminal set that planner values stand for, in float64 (-1 where unreachable).

        Reward 1 on entering the terminal set and discount gamma make the value of a state ``steps`` steps away on
        a deterministic route gamma^(steps - 1), so steps = log V / log gamma + 1 (an estimate on a stochastic
        model). A value of 0 means that the model knows no route: -1.
        """
        values = values.double()
        gamma = torch.tensor(gamma, dtype=torch.float64)
        return torch.where(values > 0, torch.log(values) / torch.log(gamma) + 1, -1.0)

    @staticmethod
    def greedy(q: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, S) argmax_a of q (S, A, B), ties broken uniformly at random."""
        return random_argmax(q, dim=1, generator=generator).T.contiguous()
