"""The one breadth-first search of the project, on adjacency lists of integer nodes.

Its callers: the true maze's distances (:meth:`ss_drl.envs.maze.Maze.distances_from`, the optimal path length) and a
MiniGrid task's (:mod:`ss_drl.envs.minigrid`), the planner's distances to the smart start state on the count model's
observed transitions (:meth:`ss_drl.smart_start.planner.Planner._deterministic_sweeps`), the distance bounds of the TD
target (:mod:`ss_drl.agents.targets`) and the frontier explorer's routes (:mod:`ss_drl.agents.frontier`). The MiniGrid
adapter's enumeration of a task's reachable states is a search of its own: it discovers the graph by stepping
MiniGrid, so it has no adjacency lists to hand over.
"""

from __future__ import annotations

from collections.abc import Sequence


def breadth_first(
    front: list[int], dist: list[int], adjacency: Sequence[Sequence[int]], limit: int | None = None
) -> int:
    """Expand the search level by level from ``front``, whose nodes all sit at level ``L = dist[front[0]]`` (set by
    the caller), writing each newly reached node's level into ``dist``; a node is new while its entry is negative
    (entries >= 0 are never changed). ``adjacency[x]`` lists the nodes one step from ``x`` in the direction of the
    search. Stops after level ``limit`` (None: when nothing new is reached). Returns the deepest level reached (``L``
    itself if nothing new is; 0 for an empty front)."""
    if not front:
        return 0
    level = dist[front[0]]
    while limit is None or level < limit:
        nxt = []
        for x in front:
            for y in adjacency[x]:
                if dist[y] < 0:
                    dist[y] = level + 1
                    nxt.append(y)
        if not nxt:
            break
        front, level = nxt, level + 1
    return level
