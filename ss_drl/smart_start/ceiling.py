"""Distance bounds from the count model: the ceiling (the fewest steps to a goal it cannot rule out) and the floor
(the fewest steps along transitions it has observed).

In a grid maze a wall is a cell, and a move into it is seen as a bump: a tried (s, a) that stayed at s although
the cell it points to lies inside the grid. The *optimistic maze* has as walls only the cells the count model has
seen bumped into; every other cell, visited or not, is taken to be free. The true maze is the optimistic one with
more walls, so its distances are never shorter: d_opt(s, g) <= d(s, g) for every cell, at every point of training.

Per (s, a) the ceiling counts the steps from s via a to entering the goal, ``1 + d_opt(s')``, with s' the
successor the count model has observed for a tried (s, a), and for an untried one the nearer of its two possible
successors (the neighbour, or s itself if the neighbour turns out to be a wall). It is a lower bound on the true
steps, so the value of reaching the goal in that many steps is an upper bound on Q*(s, a||g)
(``DQNAgent``, ``agent.distance_ceiling``): the counterpart from above of the hindsight bound from below.

The *floor* (:class:`DistanceFloor`) is the other side: the fewest steps from s via a to entering the goal along
transitions the count model has observed, ``1 + d_known(s')``. Those steps are walked again by repeating their
actions, so in a deterministic maze they are an upper bound on the true steps, and their value a lower bound on
Q*(s, a||g) (``agent.distance_floor``): the hindsight bound with every stored episode stitched into one graph.

Both are deterministic functions of the count model's observed keys, so a resumed run computes what an
uninterrupted one does. The ceiling's distances are recomputed (one BFS) only when a new wall is seen, the floor's
when a new transition is.
"""

from __future__ import annotations

from collections import deque

import numpy as np
import torch

from ss_drl.envs.maze import ACTIONS
from ss_drl.smart_start.counts import CountModel
from ss_drl.smart_start.planner import Planner, _bfs


class DistanceCeiling:
    """Lower bounds on the steps to ``goal`` from every (s, a), kept in step with a :class:`CountModel`.

    Args:
        counts: the count model (read, never written).
        height, width: the grid; cell ``row * width + col``, actions ``ACTIONS`` (right, down, left, up).
        goal: the goal cell.
    """

    def __init__(self, counts: CountModel, height: int, width: int, goal: int):
        self.counts, self.height, self.width, self.goal = counts, int(height), int(width), int(goal)
        n = self.height * self.width
        if counts.n_states != n or counts.n_actions != len(ACTIONS):
            raise ValueError(f"count model has {counts.n_states} states x {counts.n_actions} actions, grid {n} x 4")
        rows, cols = np.divmod(np.arange(n), self.width)
        #: (S, A) the cell each move points to, -1 off the grid
        self.neighbour = np.full((n, len(ACTIONS)), -1, dtype=np.int64)
        for a, (dr, dc) in enumerate(ACTIONS):
            r, c = rows + dr, cols + dc
            inside = (r >= 0) & (r < self.height) & (c >= 0) & (c < self.width)
            self.neighbour[inside, a] = r[inside] * self.width + c[inside]
        self._keys: torch.Tensor | None = None  # the key array the steps below were computed from
        self._walls: np.ndarray | None = None
        self._distance: np.ndarray | None = None
        self._steps: torch.Tensor | None = None

    def known_walls(self) -> np.ndarray:
        """(S,) bool: cells the count model has seen a move bump into."""
        n, a_n = self.counts.n_states, self.counts.n_actions
        keys = self.counts.keys.numpy()
        sa, s2 = keys // n, keys % n
        s, a = sa // a_n, sa % a_n
        target = self.neighbour[s, a]
        bumped = (s2 == s) & (target >= 0)
        walls = np.zeros(n, dtype=bool)
        walls[target[bumped]] = True
        return walls

    def distances(self, walls: np.ndarray) -> np.ndarray:
        """(S,) BFS steps from every cell to the goal in the maze whose only walls are ``walls``; a cell that
        cannot reach it gets S (more than any simple path). Moves are reversible in a grid, so the BFS runs from
        the goal."""
        n = walls.size
        dist = np.full(n, -1, dtype=np.int64)
        dist[self.goal] = 0
        neighbour, queue = self.neighbour.tolist(), deque([self.goal])
        blocked = walls.tolist()
        while queue:
            cur = queue.popleft()
            for nxt in neighbour[cur]:
                if nxt >= 0 and not blocked[nxt] and dist[nxt] < 0:
                    dist[nxt] = dist[cur] + 1
                    queue.append(nxt)
        dist[dist < 0] = n
        return dist

    def steps(self) -> torch.Tensor:
        """(S * A,) float32, flat ``s * A + a``: the fewest steps from s via a to entering the goal that the count
        model cannot rule out, ``1 + d_opt(s')``."""
        keys = self.counts.keys
        if self._steps is not None and keys is self._keys:
            return self._steps
        walls = self.known_walls()
        if self._distance is None or not np.array_equal(walls, self._walls):
            self._walls, self._distance = walls, self.distances(walls)
        dist = self._distance
        n, a_n = self.counts.n_states, self.counts.n_actions
        here = np.repeat(dist, a_n).reshape(n, a_n)  # s itself (a bump)
        target = self.neighbour
        there = np.where(target >= 0, dist[np.maximum(target, 0)], n)
        there = np.where((target >= 0) & walls[np.maximum(target, 0)], n, there)  # a known wall is no successor
        nearer = np.minimum(here, there).reshape(-1)  # untried (s, a): whichever successor it turns out to have
        known = keys.numpy()
        nearer[known // n] = dist[known % n]  # tried (s, a): the successor observed (one, in a deterministic maze)
        self._keys, self._steps = keys, torch.from_numpy(1 + nearer).to(torch.float32)
        return self._steps


class DistanceFloor:
    """Upper bounds on the steps to ``goal`` from every (s, a), along the transitions a :class:`CountModel` has seen.

    ``steps()[s * A + a]`` is ``1 + d_known(s')`` for a tried (s, a) with observed successor s', d_known the fewest
    observed transitions from s' into the goal (0 at the goal), and 0 ("no bound") where (s, a) is untried or s'
    has no observed route to the goal. The breadth-first search is the planner's, on the count model's cached
    structure (its predecessor lists), backwards from the goal.

    Args:
        counts: the count model (read, never written); its maze must be deterministic.
        goal: the goal cell.
    """

    def __init__(self, counts: CountModel, goal: int):
        self.counts, self.goal = counts, int(goal)
        self._keys: torch.Tensor | None = None  # the key array the steps below were computed from
        self._steps: torch.Tensor | None = None

    def distances(self) -> np.ndarray:
        """(S,) d_known: the fewest observed transitions from each cell into the goal; 0 at the goal, -1 where no
        observed route leads there."""
        st = self.counts.structure()
        if not st.deterministic:
            raise ValueError(
                "agent.distance_floor needs a deterministic maze: some (s, a) was seen to lead to two cells"
            )
        into_state, preds = Planner._predecessors(st)
        n_v = st.states.numel()
        dist = [-1] * (n_v + 1)
        dist[n_v] = 0  # the dummy slot (unvisited cells) is never reached
        slot = st.derived["slot"][self.goal]
        if slot < n_v:
            dist[slot] = 0  # the goal is terminal and normally never departed from, so it has no slot
        front = [y for y in into_state.get(self.goal, ()) if dist[y] < 0]
        for y in front:
            dist[y] = 1
        _bfs(front, dist, preds, n_v + 1)
        full = np.full(self.counts.n_states, -1, dtype=np.int64)
        full[st.states.numpy()] = dist[:n_v]
        full[self.goal] = 0
        return full

    def steps(self) -> torch.Tensor:
        """(S * A,) float32, flat ``s * A + a``: the steps from s via a to entering the goal along observed
        transitions, ``1 + d_known(s')``; 0 where there is no such route."""
        keys = self.counts.keys
        if self._steps is not None and keys is self._keys:
            return self._steps
        n = self.counts.n_states
        steps = np.zeros(n * self.counts.n_actions, dtype=np.int64)
        if keys.numel():
            dist = self.distances()
            known = keys.numpy()
            d = dist[known % n]
            steps[known[d >= 0] // n] = 1 + d[d >= 0]
        self._keys, self._steps = keys, torch.from_numpy(steps).to(torch.float32)
        return self._steps
