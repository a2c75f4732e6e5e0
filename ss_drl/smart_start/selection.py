"""Choosing the smart start state S_ss by an upper confidence bound over the visited states."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ss_drl.ops import random_argmax
from ss_drl.smart_start.counts import CountModel


def ucb_scores(max_q: torch.Tensor, visits: torch.Tensor, c_ss: float, w_q: float = 1.0) -> torch.Tensor:
    """UCB of each visited state: ``w_q * max_a Q(s||g, a) + sqrt(c_ss * ln(sum_s N(s)) / N(s))``.

    ``w_q = 1`` is the form of the issue/paper; Keulen's 2017 form weighs the two terms separately (``w_q``, ``c_ss``).
    """
    visits = visits.to(torch.float64)
    bonus = torch.sqrt(c_ss * torch.log(visits.sum()) / visits)
    return w_q * max_q.to(torch.float64) + bonus


def select_smart_start(
    counts: CountModel,
    max_q_fn,
    goals: torch.Tensor,
    c_ss: float,
    w_q: float = 1.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """S_ss for each goal in ``goals`` (B,): argmax over visited states (N(s) > 0) of the UCB, random tie-break.

    Args:
        counts: the count model.
        max_q_fn: ``f(states (n,), goals (B,)) -> (B, n)`` max_a Q(s||g, a), one batched evaluation; not called
            when ``w_q == 0`` (S_ss by counts alone, the paper's experiment), which then needs no network pass.
        goals: (B,) desired goal per env copy that starts an episode.
    Returns:
        (B,) smart start states.
    """
    states = counts.structure().states  # the visited states, cached until a new transition is seen
    if states.numel() == 0:
        raise ValueError("Smart Start needs at least one visited state")
    if w_q == 0:
        max_q = torch.zeros(goals.numel(), states.numel(), dtype=torch.float64)
    else:
        max_q = max_q_fn(states, goals)  # (B, n)
    scores = ucb_scores(max_q, counts.state_counts[states].unsqueeze(0), c_ss, w_q)
    return states[random_argmax(scores, dim=1, generator=generator)]


#: Rows (state, goal pairs) evaluated per block by :func:`goal_q_values`: a block's activations stay in cache.
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


@torch.no_grad()
def goal_q_values(q_network: nn.Module, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
    """(B, n, A): Q(s||g, .) of a ``GoalQNetwork`` for every state in ``states`` (n,) and goal in ``goals`` (B,).

    The same numbers as ``q_network(states.repeat(B), goals.repeat_interleave(n))`` up to float rounding, for less
    work: the first trunk layer acts on ``concat(e_s, e_g)``, so ``W [e_s; e_g] + b = W_s e_s + (W_g e_g + b)``: the
    state half is computed once per state and the goal half once per goal, instead of both for every (state, goal)
    pair. The dueling head ``Q = V + A - mean_a A`` is linear in the last hidden layer, so it is folded into one
    (A x H) matrix. The rows are evaluated in blocks of ``BLOCK_ROWS`` through reused scratch buffers.
    """
    trunk = list(q_network.trunk)
    first = trunk[0]
    e_s = q_network.state_encoder(states)  # (n, E)
    e_g = q_network.goal_encoder(goals)  # (B, E)
    d_s, n, n_b = e_s.shape[-1], states.numel(), goals.numel()
    w_s = first.weight[:, :d_s].T
    h_g = F.linear(e_g, first.weight[:, d_s:], first.bias)  # (B, H): the goal half and the bias, once per goal
    h_s = e_s @ w_s if n_b > 1 else None  # (n, H): the state half, once per state
    adv = q_network.advantage
    head_w, head_b = adv.weight, adv.bias
    if q_network.dueling:
        value = q_network.value
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
