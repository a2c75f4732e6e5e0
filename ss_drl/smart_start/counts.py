"""The count model: visitation counts and a learned transition model over discrete maze states.

It keeps N(s) (departures from s), C(s, a), C(s, a, s') and the reward sums R(s, a), shared across env copies.
C(s, a, s') is sparse: one entry per *observed* successor, held as a sorted key array ``key = (s * A + a) * S + s'``
with a count per key. In a deterministic maze each (s, a) has one successor, so the model of Extreme (2457 free
cells) or a 100x100 maze takes a few hundred KB, never a dense |S| x |S| x |A| array.

The learned model is ``P(s' | s, a) = C(s, a, s') / C(s, a)`` over tried (s, a).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from ss_drl.envs.maze import Maze


@dataclasses.dataclass
class ModelStructure:
    """Which transitions the model has observed, in the compact layout the planner works on.

    It depends only on the set of observed keys (not on the counts), so :meth:`CountModel.structure` builds it once
    and reuses it until a new (s, a, s') key is inserted. Visited states are numbered by their *slot*
    ``0 .. n_v - 1``; slot ``n_v`` is a dummy standing for every unvisited state (no tried action: value 0).
    """

    keys: torch.Tensor  # the key array it was built from (the cache is valid while the model holds this very tensor)
    states: torch.Tensor  # (n_v,) visited states (N(s) > 0), ascending
    slot: torch.Tensor  # (S,) slot of each state; n_v for unvisited states
    state: torch.Tensor  # per key: s
    action: torch.Tensor  # per key: a
    next_state: torch.Tensor  # per key: s'
    row: torch.Tensor  # per key: slot of s
    col: torch.Tensor  # per key: slot of s' (n_v if s' was never departed from)
    sa: torch.Tensor  # per key: s * A + a (the model's flat (s, a) index)
    layer: torch.Tensor  # per key: its rank among the observed successors of its (s, a)
    n_layers: int  # most observed successors of one (s, a); 1 in a deterministic maze
    successor: torch.Tensor  # (n_layers, A, n_v) slot of the k-th successor of (slot, a); n_v where there is none
    derived: dict = dataclasses.field(default_factory=dict)  # users' own caches of data derived from the structure

    @property
    def deterministic(self) -> bool:
        """Every tried (s, a) has been seen to lead to one successor only."""
        return self.n_layers == 1

    def predecessors(self) -> tuple[dict[int, tuple[int, ...]], list[tuple[int, ...]]]:
        """Predecessor lists for a breadth-first search backwards along observed transitions (the planner's
        distances, the TD target's distance floor), cached in :attr:`derived`: the slots with a tried action into
        each state (a dict by state) and into each slot (a list by slot; the dummy slot has none)."""
        if "predecessors" not in self.derived:
            n_v = self.states.numel()
            edge = self.next_state != self.state
            pairs = torch.unique(torch.stack((self.next_state[edge], self.row[edge]), dim=1), dim=0)  # by next state
            targets, sources = pairs[:, 0].tolist(), pairs[:, 1].tolist()
            into_state: dict[int, list[int]] = {}
            for t, s in zip(targets, sources):
                into_state.setdefault(t, []).append(s)
            into_state = {t: tuple(s) for t, s in into_state.items()}
            preds = [into_state.get(s, ()) for s in self.states.tolist()] + [()]
            self.derived["predecessors"] = (into_state, preds)
            self.derived["slot"] = self.slot.tolist()
            self.derived["reward_index"] = self.action * n_v + self.row
            self.derived["successor"] = self.successor.reshape(-1)
        return self.derived["predecessors"]


class CountModel:
    """Visit counts and a sparse learned transition model.

    Args:
        n_states: number of discrete states (maze cells, walls included: cell index ``row * width + col``).
        n_actions: number of actions.
    """

    def __init__(self, n_states: int, n_actions: int = 4):
        self.n_states = int(n_states)
        self.n_actions = int(n_actions)
        self.state_counts = torch.zeros(self.n_states, dtype=torch.int64)  # N(s): departures from s
        self.sa_counts = torch.zeros(self.n_states * self.n_actions, dtype=torch.int64)  # C(s, a), flat s * A + a
        self.reward_sums = torch.zeros(self.n_states * self.n_actions, dtype=torch.float64)  # sum of r over (s, a)
        self.keys = torch.zeros(0, dtype=torch.int64)  # sorted (s * A + a) * S + s'
        self.sas_counts = torch.zeros(0, dtype=torch.int64)  # C(s, a, s') for each key
        self._structure: ModelStructure | None = None

    # --- updates -----------------------------------------------------------------------------------------------
    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor, reward: torch.Tensor):
        """Count a batch of transitions (any shape; flattened)."""
        s, a, s2 = state.reshape(-1), action.reshape(-1), next_state.reshape(-1)
        if s.numel() == 0:
            return
        sa = s * self.n_actions + a
        self.state_counts.index_add_(0, s, torch.ones_like(s))
        self.sa_counts.index_add_(0, sa, torch.ones_like(sa))
        self.reward_sums.index_add_(0, sa, reward.reshape(-1).to(torch.float64))
        keys = sa * self.n_states + s2
        pos = torch.searchsorted(self.keys, keys)
        n = self.keys.numel()
        # pos == n means "after every key": clamped, it points at a smaller key, so the comparison is False.
        known = self.keys[pos.clamp(max=n - 1)] == keys if n else torch.zeros_like(keys, dtype=torch.bool)
        if not bool(known.all()):
            self._insert(torch.unique(keys[~known]))
            pos = torch.searchsorted(self.keys, keys)
        self.sas_counts.index_add_(0, pos, torch.ones_like(pos))

    def _insert(self, new_keys: torch.Tensor) -> None:
        keys = torch.cat((self.keys, new_keys))
        counts = torch.cat((self.sas_counts, torch.zeros_like(new_keys)))
        keys, order = torch.sort(keys)
        self.keys, self.sas_counts = keys, counts[order]
        self._structure = None

    # --- queries -----------------------------------------------------------------------------------------------
    @property
    def total_visits(self) -> int:
        """sum_s N(s): transitions counted."""
        return int(self.state_counts.sum())

    def visited_states(self) -> torch.Tensor:
        """States with N(s) > 0, ascending."""
        return torch.nonzero(self.state_counts > 0).squeeze(-1)

    def transitions(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The learned model as sparse entries ``(s, a, s', P(s'|s,a))`` over observed transitions."""
        sa = self.keys // self.n_states
        next_state = self.keys % self.n_states
        prob = self.sas_counts.to(torch.float64) / self.sa_counts[sa].to(torch.float64)
        return sa // self.n_actions, sa % self.n_actions, next_state, prob

    def successors(self) -> torch.Tensor:
        """(S * A,) int64, flat ``s * A + a``: the successor observed for each tried (s, a), -1 for an untried one
        (cached with the structure). Refused if some (s, a) was seen to lead to two cells: it is one cell only in a
        deterministic maze."""
        st = self.structure()
        if "observed_successor" not in st.derived:
            if not st.deterministic:
                raise ValueError(
                    "agent.model_targets needs a deterministic maze: some (s, a) was seen to lead to two cells"
                )
            succ = torch.full((self.n_states * self.n_actions,), -1, dtype=torch.int64)
            succ[st.sa] = st.next_state
            st.derived["observed_successor"] = succ
        return st.derived["observed_successor"]

    def structure(self) -> ModelStructure:
        """The observed transitions in the planner's layout (cached until a new key is inserted)."""
        if self._structure is None or self._structure.keys is not self.keys:
            self._structure = self._build_structure()
        return self._structure

    def _build_structure(self) -> ModelStructure:
        n_s, n_a = self.n_states, self.n_actions
        sa = self.keys // n_s
        s, a, s2 = sa // n_a, sa % n_a, self.keys % n_s
        states = self.visited_states()
        n_v = states.numel()
        slot = torch.full((n_s,), n_v, dtype=torch.int64)
        slot[states] = torch.arange(n_v)
        row, col = slot[s], slot[s2]
        # Keys are sorted by (s, a, s'): a key's rank among the successors of its (s, a) is its layer.
        layer = torch.arange(sa.numel()) - torch.searchsorted(sa, sa)
        n_layers = int(layer.max()) + 1 if sa.numel() else 1
        successor = torch.full((n_layers, n_a, n_v), n_v, dtype=torch.int64)
        successor[layer, a, row] = col
        return ModelStructure(self.keys, states, slot, s, a, s2, row, col, sa, layer, n_layers, successor)

    def count(self, state: int, action: int | None = None, next_state: int | None = None) -> int:
        """N(s), C(s, a) or C(s, a, s')."""
        if action is None:
            return int(self.state_counts[state])
        sa = state * self.n_actions + action
        if next_state is None:
            return int(self.sa_counts[sa])
        key = sa * self.n_states + next_state
        pos = int(torch.searchsorted(self.keys, torch.tensor(key)))
        return int(self.sas_counts[pos]) if pos < self.keys.numel() and int(self.keys[pos]) == key else 0

    def nbytes(self) -> int:
        """Memory held by the model's tensors."""
        tensors = (self.state_counts, self.sa_counts, self.reward_sums, self.keys, self.sas_counts)
        return sum(t.numel() * t.element_size() for t in tensors)

    # --- persistence -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "n_states": self.n_states,
            "n_actions": self.n_actions,
            "state_counts": self.state_counts.clone(),
            "sa_counts": self.sa_counts.clone(),
            "reward_sums": self.reward_sums.clone(),
            "keys": self.keys.clone(),
            "sas_counts": self.sas_counts.clone(),
        }

    def load_state_dict(self, state: dict) -> None:
        if (state["n_states"], state["n_actions"]) != (self.n_states, self.n_actions):
            raise ValueError("count model checkpoint is for a different maze")
        for name in ("state_counts", "sa_counts", "reward_sums", "keys", "sas_counts"):
            setattr(self, name, state[name].clone())
        self._structure = None


def fully_explored_model(maze: Maze) -> CountModel:
    """A count model that has seen every transition of ``maze`` once: each free cell x each action, with its
    (deterministic) successor from ``maze.transition_table()`` and reward 1 exactly when that successor is the goal.

    Wall cells are never departed from. The model of what Smart Start knows once exploration is complete; the planner
    benchmark and tests plan on it.
    """
    table = maze.transition_table()
    n_actions = table.shape[1]
    free = np.flatnonzero(~maze.walls.reshape(-1))
    s = np.repeat(free, n_actions)
    a = np.tile(np.arange(n_actions), free.size)
    s2 = table[s, a]
    from ss_drl.envs.maze import goal_reward

    r = goal_reward(torch.from_numpy(s2), maze.goal_cell).to(torch.float32)
    model = CountModel(maze.n_cells, n_actions)
    model.update(torch.from_numpy(s), torch.from_numpy(a), torch.from_numpy(s2), r)
    return model
