"""Per-run figures: the maze with visit counts and Smart Start targets, greedy paths and Q heatmaps."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ss_drl.envs.maze import Maze


def _base(ax, maze: Maze, values: np.ndarray, label: str, cmap: str = "viridis", log: bool = False):
    from matplotlib.colors import LogNorm

    data = np.ma.masked_where(maze.walls, values.astype(float))
    norm = LogNorm(vmin=1, vmax=max(float(data.max() or 1), 1)) if log else None
    image = ax.imshow(data, cmap=cmap, norm=norm, interpolation="nearest")
    ax.imshow(np.ma.masked_where(~maze.walls, np.ones_like(values)), cmap="gray_r", vmin=0, vmax=1.5)
    ax.plot(maze.start[1], maze.start[0], "o", color="red", markersize=7, label="S")
    ax.plot(maze.goal[1], maze.goal[0], "*", color="lime", markersize=11, markeredgecolor="k", label="G")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.figure.colorbar(image, ax=ax, fraction=0.046, pad=0.04, label=label)


def _title(ax, title: str, width: int = 60) -> None:
    """A title wrapped to ``width`` characters, so that a long one fits a narrow maze's axes."""
    ax.set_title("\n".join(textwrap.wrap(title, width)), fontsize=9)


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return path


def plot_visit_counts(maze: Maze, state_counts: torch.Tensor, targets: list[int], path: Path) -> Path:
    """The maze coloured by N(s) (log scale), with every chosen S_ss marked (size ~ how often it was chosen)."""
    fig = Figure(figsize=(6, 6 * maze.height / maze.width + 0.5))
    ax = fig.add_subplot()
    # Per cell: a maze's states are its cells; a MiniGrid task's states in one cell (direction, doors, carried
    # object) add up.
    cells = maze.cells(torch.arange(state_counts.numel()))
    counts = torch.zeros(maze.n_cells, dtype=state_counts.dtype).index_add_(0, cells, state_counts)
    counts = counts.reshape(maze.height, maze.width).numpy()
    _base(ax, maze, np.maximum(counts, 0), "visits N(s)", cmap="magma", log=True)
    if targets:
        cells, times = np.unique(maze.cells(torch.as_tensor(targets)).numpy(), return_counts=True)
        rows, cols = np.divmod(cells, maze.width)
        ax.scatter(cols, rows, s=10 + 40 * times / times.max(), facecolors="none", edgecolors="cyan", label="S_ss")
    ax.set_title(f"{maze.name}: visit counts and {len(targets)} smart start targets")
    ax.legend(loc="upper right", fontsize=7)
    return _save(fig, path)


def plot_minigrid_policy(task, path_states: list[int], out: Path, title: str, tile: int = 32) -> Path:
    """The MiniGrid frame (the fully observed grid, the agent in its start state) with the greedy path drawn through
    the cells it visits, from the start (red dot) to its end (lime star on the goal square when it gets there)."""
    fig = Figure(figsize=(6, 6 * task.height / task.width + 0.5))
    ax = fig.add_subplot()
    ax.imshow(task.frame(task.start_state, tile_size=tile))
    rows, cols = np.divmod(task.cells(torch.as_tensor(path_states)).numpy(), task.width)
    ax.plot((cols + 0.5) * tile, (rows + 0.5) * tile, "-", color="yellow", linewidth=2.5, alpha=0.8)
    ax.plot((cols[0] + 0.5) * tile, (rows[0] + 0.5) * tile, "o", color="red", markersize=7, label="start")
    ax.plot((cols[-1] + 0.5) * tile, (rows[-1] + 0.5) * tile, "*", color="lime", markersize=13, markeredgecolor="k",
            label="end")  # fmt: skip
    ax.set_xticks([])
    ax.set_yticks([])
    _title(ax, title)
    ax.legend(loc="upper right", fontsize=7)
    return _save(fig, out)


def plot_policy(maze: Maze, max_q: np.ndarray, path_cells: list[int], out: Path, title: str) -> Path:
    """Heatmap of max_a Q(s||G, a) with the greedy path from S drawn over it."""
    fig = Figure(figsize=(6, 6 * maze.height / maze.width + 0.5))
    ax = fig.add_subplot()
    _base(ax, maze, max_q.reshape(maze.height, maze.width), "max_a Q(s||G, a)")
    rows, cols = np.divmod(np.asarray(path_cells), maze.width)
    ax.plot(cols, rows, "-", color="white", linewidth=2)
    _title(ax, title)
    ax.legend(loc="upper right", fontsize=7)
    return _save(fig, out)
