"""The ``her`` section: ms per ``HindsightReplayBuffer.sample()`` (batch 128, future, k = 4) at each stored size."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch

from benchmarks.common import fmt_ms, markdown_table, median


def synthetic_batch(rows: int, first_row: int, episode_len: int = 100, n_cells: int = 300):
    """A (rows, 1) batch of HER-buffer transitions: random cells, episodes of ``episode_len`` steps (truncated)."""
    from tensordict import TensorDict

    t = torch.arange(first_row, first_row + rows)
    done = ((t + 1) % episode_len == 0).view(rows, 1, 1)
    goal = torch.full((rows, 1), n_cells - 1, dtype=torch.int64)
    return TensorDict(
        {
            "observation": torch.randint(0, n_cells, (rows, 1)),
            "desired_goal": goal,
            "action": torch.randint(0, 4, (rows, 1)),
            "next": {
                "observation": torch.randint(0, n_cells, (rows, 1)),
                "desired_goal": goal.clone(),
                "reward": torch.zeros(rows, 1, 1, dtype=torch.float32),
                "terminated": torch.zeros(rows, 1, 1, dtype=torch.bool),
                "truncated": done,
                "done": done.clone(),
            },
        },
        batch_size=(rows, 1),
    )


def filled_buffer(size: int, batch_size: int = 128, k: int = 4, episode_len: int = 100, chunk: int = 250_000):
    """A full :class:`HindsightReplayBuffer` of ``size`` transitions (one env copy), filled by a few large extends."""
    from ss_drl.her import HindsightReplayBuffer

    buffer = HindsightReplayBuffer(
        size, num_envs=1, batch_size=batch_size, strategy="future", k=k, generator=torch.Generator().manual_seed(0)
    )
    chunk = min(chunk, size)
    for first in range(0, size, chunk):
        buffer.extend(synthetic_batch(min(chunk, size - first), first, episode_len))
    return buffer


def bench_her(
    repeats: int,
    sizes: Sequence[int] = (10_000, 1_000_000),
    samples: int = 200,
    batch_size: int = 128,
    k: int = 4,
    episode_len: int = 100,
) -> str:
    """ms per ``HindsightReplayBuffer.sample()`` at each stored size (median of samples, then of repeats).

    The table also counts what was timed: the ``sample()`` calls and the transitions they returned (batch rows).
    """
    rows, medians = [], {}
    for size in sizes:
        torch.manual_seed(0)
        start = time.perf_counter()
        buffer = filled_buffer(size, batch_size, k, episode_len)
        fill_s = time.perf_counter() - start
        for _ in range(10):  # warm-up
            buffer.sample()
        per_repeat, all_times, drawn = [], [], 0
        for _ in range(repeats):
            times = []
            for _ in range(samples):
                t0 = time.perf_counter()
                batch = buffer.sample()
                times.append((time.perf_counter() - t0) * 1e3)
                drawn += batch.numel()
            per_repeat.append(median(times))
            all_times += times
        medians[size] = median(per_repeat)
        p90 = float(np.percentile(all_times, 90))
        rows.append(
            [
                f"{size:,}",
                f"{len(buffer):,}",
                f"{fill_s:.2f}",
                f"{len(all_times):,}",
                f"{drawn:,}",
                fmt_ms(medians[size]),
                fmt_ms(p90),
            ]
        )
        del buffer
    headers = [
        "stored transitions",
        "len(buffer)",
        "fill s",
        "samples timed",
        "transitions drawn",
        "sample ms (median)",
        "sample ms (p90)",
    ]
    out = [
        f"## her: ms per `HindsightReplayBuffer.sample()` (batch {batch_size}, future, k={k}; synthetic episodes of "
        f"{episode_len} steps; median of {samples} samples, median of {repeats} repeats)",
        "",
        markdown_table(headers, rows),
        "",
    ]
    if len(sizes) > 1:
        small, big = min(sizes), max(sizes)
        out.append(
            f"- ratio {big:,} / {small:,}: {medians[big] / medians[small]:.2f}x (O(batch) sampling: ~1 expected)"
        )
    return "\n".join(out) + "\n"
