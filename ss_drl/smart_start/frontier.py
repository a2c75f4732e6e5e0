"""The frontier of exploration: which moves have been tried, kept current at every env step (issue 49).

A state is *known* once it has been entered or departed from; a move ``(s, a)`` is *tried* once it has been taken (a
bump into a wall is a tried move, as in the count model). The *frontier* is the set of known states with an untried
move, less the goal: entering the goal ends the episode, so its moves are never tried and it is no place to explore.

The count model is updated once per collected batch; :class:`Frontier` also sees the moves of the batch being
collected (:meth:`Frontier.observe`, called at every env step), so "untried" is current at every step. Everything it
holds is a function of the count model and of the steps since the model's last update: at a batch boundary (where
checkpoints are written) it is rebuilt from the model alone (:meth:`Frontier.sync`), so it needs no checkpoint state.

Smart Start's exploration options (:mod:`ss_drl.smart_start.controller`) read it: S_ss chosen among frontier states,
and the exploration phase that tries untried moves after the guided phase. The collector counts the new moves of each
episode with it (``new_moves`` in episodes.csv), for every method.
"""

from __future__ import annotations

import torch

from ss_drl.smart_start.counts import CountModel


class Frontier:
    """Tried moves and known states, current at every env step.

    Args:
        counts: the count model (the moves of earlier batches).
        cells: a state's cell, to compare it with the goal (None: states are cells, as in a maze).
    """

    def __init__(self, counts: CountModel, cells=None):
        self.counts = counts
        self.cells = cells
        self.sync()

    def sync(self) -> None:
        """Rebuild from the count model alone (after a checkpoint is loaded; at a batch boundary it changes nothing)."""
        c = self.counts
        self.tried = (c.sa_counts > 0).view(c.n_states, c.n_actions).clone()  # (S, A)
        self.known = c.state_counts > 0  # (S,)
        self.known[c.keys % c.n_states] = True  # every state entered

    def observe(self, cells: torch.Tensor, actions: torch.Tensor, next_cells: torch.Tensor) -> torch.Tensor:
        """Record one env step of every copy (``(N,)`` each); returns which copies tried a move for the first time."""
        new = ~self.tried[cells, actions]
        self.tried[cells, actions] = True
        self.known[cells] = True
        self.known[next_cells] = True
        return new

    def untried(self, cells: torch.Tensor) -> torch.Tensor:
        """``(N, A)`` bool: the moves not tried yet in each cell."""
        return ~self.tried[cells]

    def states(self, goals: torch.Tensor) -> torch.Tensor:
        """``(B, S)`` bool: the frontier for each goal in ``goals`` (B,): known states with an untried move, the goal
        excluded."""
        open_ = self.known & ~self.tried.all(dim=1)
        mask = open_.unsqueeze(0).repeat(goals.numel(), 1)
        if self.cells is None:
            mask[torch.arange(goals.numel()), goals.reshape(-1)] = False
        else:  # every state in the goal's cell
            mask &= self.cells(torch.arange(open_.numel())).unsqueeze(0) != goals.reshape(-1, 1)
        return mask
