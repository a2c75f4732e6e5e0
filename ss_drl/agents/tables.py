"""Per-cell tables updated in proportion to the rows a batch touches (``agent.sparse_tables``, issue 49).

The ``embedding`` and ``hybrid`` encoders hold a learned vector per cell: on Extreme (2457 free cells of 6,000) these
tables are most of the network's parameters, and a batch of 128 touches a few hundred of their rows. Dense training
still costs a pass over every row at each update: the embedding's dense gradient (allocated, zeroed, scattered
into), Adam's step over every row, the gradient norm, and the Polyak step of the target network's copy.

With ``sparse_tables`` each of those costs the rows touched:

* the tables' gradients are sparse (``nn.Embedding(sparse=True)``); the gradient norm for clipping is taken over
  their values and the dense gradients together (:func:`clip_grad_norm`);
* the tables are stepped by a *lazy* Adam (:class:`LazyAdam`, what ``torch.optim.SparseAdam`` computes, in fewer
  operations): the moments and the rows of a table move only where the batch has a gradient. Dense Adam moves an
  untouched row too, by its decaying momentum, so this changes what the optimizer computes: it is off by default
  until runs show it does not hurt learning (docs/notebook/long_horizons.md);
* the target network's copy of a table is Polyak-averaged lazily (:class:`LazyPolyak`): while an online row does not
  move, ``k`` Polyak steps toward it are ``target <- online + (1 - tau)^k (target - online)``, applied when the row
  is read (the targets' bootstrap, evaluation) or is about to move (before the optimizer step). The same value as
  ``k`` steps of the dense lerp up to float rounding.
"""

from __future__ import annotations

import torch

#: Parameter-name suffixes of the per-cell tables in a :class:`~ss_drl.agents.network.GoalQNetwork`: the hybrid
#: encoder's table and the embedding encoder's.
TABLE_SUFFIXES = ("cells.weight", "net.weight")


def table_keys(network: torch.nn.Module) -> list[tuple[str, str]]:
    """``(parameter name, side)`` of each per-cell table (an ``nn.Embedding``'s weight) in ``network``; side is
    ``"state"`` or ``"goal"``: which input indexes it."""
    keys = []
    for name, module in network.named_modules():
        if isinstance(module, torch.nn.Embedding):
            side = "state" if name.startswith("state_encoder") else "goal"
            keys.append((f"{name}.weight", side))
    return keys


def clip_grad_norm(parameters: list[torch.Tensor], max_norm: float) -> torch.Tensor:
    """``torch.nn.utils.clip_grad_norm_`` over dense and sparse gradients alike (torch's refuses sparse ones): the
    total 2-norm of every gradient, each scaled by ``min(1, max_norm / (norm + 1e-6))``. A sparse gradient is
    coalesced first (its norm is that of its values) and replaced by the coalesced tensor. No host sync."""
    dense, sparse = [], []
    for p in parameters:
        if p.grad is None:
            continue
        if p.grad.is_sparse:
            p.grad = p.grad.coalesce()
            sparse.append(p.grad._values())
        else:
            dense.append(p.grad)
    norms = list(torch._foreach_norm(dense)) if dense else []
    norms += [v.norm() for v in sparse]
    total = torch.linalg.vector_norm(torch.stack(norms))
    coef = torch.clamp(max_norm / (total + 1e-6), max=1.0)
    if dense:
        torch._foreach_mul_(dense, coef)
    for v in sparse:
        v.mul_(coef)
    return total


class LazyAdam:
    """Lazy Adam: Adam's step on the rows where a table's (coalesced, sparse) gradient has entries, nothing elsewhere;
    what ``torch.optim.SparseAdam`` computes (a global step count for the bias corrections), in a few whole-tensor
    operations per table instead of its sparse-tensor bookkeeping.

    Args:
        params: the tables (leaf tensors whose ``.grad`` is sparse).
        lr, betas, eps: Adam's.
    """

    def __init__(self, params: list[torch.Tensor], lr: float, betas=(0.9, 0.999), eps: float = 1e-8):
        self.params = params
        self.lr, (self.beta1, self.beta2), self.eps = float(lr), betas, float(eps)
        self.exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in params]
        self.exp_avg_sq = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in params]
        self.steps = 0

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        self.steps += 1
        b1, b2 = self.beta1, self.beta2
        step_size = self.lr * (1 - b2**self.steps) ** 0.5 / (1 - b1**self.steps)
        for p, m, v in zip(self.params, self.exp_avg, self.exp_avg_sq):
            if p.grad is None:
                continue
            grad = p.grad.coalesce()
            index, g = grad._indices()[0], grad._values()
            m_rows = m.index_select(0, index).lerp_(g, 1 - b1)
            v_rows = v.index_select(0, index).mul_(b2).addcmul_(g, g, value=1 - b2)
            m.index_copy_(0, index, m_rows)
            v.index_copy_(0, index, v_rows)
            p.index_add_(0, index, m_rows.div_(v_rows.sqrt_().add_(self.eps)), alpha=-step_size)

    def state_dict(self) -> dict:
        return {"steps": self.steps, "exp_avg": [m.clone() for m in self.exp_avg],
                "exp_avg_sq": [v.clone() for v in self.exp_avg_sq]}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        self.steps = state["steps"]
        for mine, saved in zip(self.exp_avg + self.exp_avg_sq, state["exp_avg"] + state["exp_avg_sq"]):
            mine.copy_(saved)


class LazyPolyak:
    """The target network's per-cell tables, Polyak-averaged toward the online tables only where they are read or
    about to move.

    Invariant: row ``r`` of a target table holds its value after ``synced[r]`` Polyak steps, and the online row has
    not moved since; the true value after ``steps`` steps is ``online + (1 - tau)^(steps - synced) (target -
    online)``, which :meth:`catch_up` writes.

    Args:
        pairs: ``(online table, target table, side)`` per table (the tensors themselves, written in place).
        tau: the Polyak rate.
    """

    def __init__(self, pairs: list[tuple[torch.Tensor, torch.Tensor, str]], tau: float):
        self.pairs = pairs
        self.decay = 1.0 - float(tau)
        self.tau = float(tau)
        self.steps = 0  # Polyak steps taken (one per update)
        self.synced = [torch.zeros(online.shape[0], dtype=torch.int64) for online, _, _ in pairs]

    def catch_up(self, rows: dict[str, torch.Tensor] | None = None) -> None:
        """Bring the target rows indexed by ``rows`` (``{"state": cells, "goal": cells}``; None: every row) up to
        the current step. A row already there is left as it is, bit for bit."""
        with torch.no_grad():
            for (online, target, side), synced in zip(self.pairs, self.synced):
                index = torch.arange(online.shape[0]) if rows is None else torch.unique(rows[side].reshape(-1))
                lag = self.steps - synced[index]
                o, t = online[index], target[index]
                factor = torch.pow(self.decay, lag.to(t.dtype)).unsqueeze(-1)
                target[index] = torch.where(lag.unsqueeze(-1) > 0, o + factor * (t - o), t)
                synced[index] = self.steps

    def step(self, touched: dict[str, torch.Tensor]) -> None:
        """One Polyak step after the optimizer moved the online rows ``touched`` (caught up before it moved them,
        :meth:`catch_up`): those target rows take the step; the others are left for later."""
        self.steps += 1
        with torch.no_grad():
            for (online, target, side), synced in zip(self.pairs, self.synced):
                index = touched[side]
                target[index] = torch.lerp(target[index], online[index], self.tau)
                synced[index] = self.steps

    def state_dict(self) -> dict:
        return {"steps": self.steps, "synced": [s.clone() for s in self.synced]}

    def load_state_dict(self, state: dict) -> None:
        self.steps = state["steps"]
        self.synced = [s.clone() for s in state["synced"]]
