"""What every benchmark section shares: the checkout's config directory, number formats, medians and timers."""

from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from ss_drl.analysis.tables import format_markdown_table

#: The Hydra configs of the checkout the benchmarks run from (``conf/`` next to ``benchmarks/``).
CONFIG_DIR = Path(__file__).resolve().parent.parent / "conf"
MILLION = 1_000_000

__all__ = ["CONFIG_DIR", "MILLION", "compose_config", "fmt_ms", "fmt_rate", "markdown_table", "median", "timed"]


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A section's markdown table (:func:`ss_drl.analysis.tables.format_markdown_table`); numbers formatted already."""
    return format_markdown_table(headers, rows)


def fmt_rate(x: float) -> str:
    """Steps per second with thousands separators."""
    return f"{x:,.0f}"


def fmt_ms(x: float) -> str:
    return f"{x:.3f}" if x < 10 else f"{x:.1f}"


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values))


def timed(fn: Callable, repeats: int) -> tuple[float, object]:
    """Median ms of ``repeats`` calls of ``fn`` and the last call's result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return median(times) * 1e3, result


def quiet_torchrl() -> None:
    """TorchRL logs an INFO line per replay-buffer storage it creates; keep the tables clean. Its import sets the
    level (from RL_LOGGING_LEVEL), so import it first."""
    import torchrl  # noqa: F401

    logging.getLogger("torchrl").setLevel(logging.WARNING)


def compose_config(overrides: Sequence[str]):
    """Compose the checkout's ``conf/config.yaml`` in-process with Hydra overrides."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides))
