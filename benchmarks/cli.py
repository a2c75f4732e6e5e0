"""The command line of ``scripts/benchmark.py``: its parser, the header (command, versions, machine), :func:`main`."""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from benchmarks.common import quiet_torchrl
from benchmarks.env import bench_env
from benchmarks.her import bench_her
from benchmarks.planner import bench_planner
from benchmarks.train import bench_train, sb3_available, sb3_version
from benchmarks.update import bench_update

SECTIONS = ("env", "train", "planner", "her", "update")
#: Default repeats per section (``--repeats`` overrides them all). The train section is the slow one.
DEFAULT_REPEATS = {"env": 5, "train": 3, "planner": 15, "her": 5, "update": 7}
QUICK_REPEATS = 2
#: The experiment the train section times without ``--experiment``.
DEFAULT_EXPERIMENT = "easy_dqn_her"
#: ``--quick``: every section at small sizes (keyword arguments of its ``bench_*`` function), a smoke run.
QUICK_SIZES: dict[str, dict] = {
    "env": dict(raw_steps=2_000, gym_steps=500, batched_iters=200),
    "train": dict(steps=200, max_steps=100, learning_starts=100),
    "planner": dict(mazes=("easy_small", "random29")),
    "her": dict(sizes=(1_000, 10_000), samples=50),
    "update": dict(maze="easy_small", transitions=2_000, updates=10),
}
BENCHES = {
    "env": bench_env,
    "train": bench_train,
    "planner": bench_planner,
    "her": bench_her,
    "update": bench_update,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scripts/benchmark.py",
        description="ss-drl throughput benchmarks; prints markdown tables (medians over repeats).",
    )
    parser.add_argument("--section", choices=(*SECTIONS, "all"), default="all", help="which benchmark (default all)")
    parser.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="repeats per measurement (default: " + ", ".join(f"{k} {v}" for k, v in DEFAULT_REPEATS.items()) + ")",
    )
    parser.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads, for ss-drl and SB3 alike (default 1)"
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="every section small (the HER buffer at 1k and 10k transitions, the planner on easy_small and a 29x29 "
        "random maze, 200 timed training steps) and 2 repeats: a smoke run",
    )
    parser.add_argument(
        "--train-steps",
        type=int,
        default=None,
        help="timed env steps after learning_starts in the train section (default 1500; --quick 200)",
    )
    parser.add_argument(
        "--experiment",
        default=None,
        help="the experiment the train section times (default easy_dqn_her, with easy_ss_her for information); "
        "compared with SB3 when it is a replay-only dqn_her",
    )
    parser.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a Hydra override for the timed experiment's runs in the train section (repeatable), e.g. "
        "--override agent.sparse_tables=true; the baseline runs as it is",
    )
    parser.add_argument(
        "--baseline-checkout",
        default=None,
        metavar="PATH",
        help="a git checkout of an older commit (e.g. `git worktree add ../base 7ac5009`): the train section runs the "
        "experiment there too, named as there (docs/migration.md), interleaved with this checkout's runs",
    )
    return parser


def command_line(argv: Sequence[str], prog: str) -> str:
    """The command as typed: ``python PROG ARGS``, shell-quoted."""
    return "python " + " ".join(shlex.quote(part) for part in (prog, *argv))


def header(argv: Sequence[str], prog: str) -> str:
    import gymnasium
    import tensordict
    import torchrl

    sb3 = sb3_version() if sb3_available() else "not installed"
    command = command_line(argv, prog)
    return "\n".join(
        [
            "# ss-drl benchmark",
            "",
            f"`$ {command}`",
            "",
            f"python {platform.python_version()}, torch {torch.__version__} (threads {torch.get_num_threads()}), "
            f"torchrl {torchrl.__version__}, tensordict {tensordict.__version__}, gymnasium {gymnasium.__version__}, "
            f"stable-baselines3 {sb3}; {os.cpu_count()} CPUs ({platform.processor() or platform.machine()}); "
            f"load average {', '.join(f'{x:.2f}' for x in os.getloadavg())}",
            "",
        ]
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``scripts/benchmark.py``; returns the exit code (0; 2 for an experiment with no baseline)."""
    if argv is None:
        prog, argv = sys.argv[0], sys.argv[1:]
    else:
        prog = "scripts/benchmark.py"
    parser = build_parser()
    args = parser.parse_args(argv)
    for option, value in (
        ("--threads", args.threads),
        ("--repeats", args.repeats),
        ("--train-steps", args.train_steps),
    ):
        if value is not None and value < 1:
            parser.error(f"{option} must be >= 1, got {value}")
    sections = SECTIONS if args.section == "all" else (args.section,)
    train_options = {}
    if args.experiment is not None:
        train_options["experiments"] = (args.experiment,)
    if args.override:
        if "train" not in sections:
            parser.error("--override applies to the train section")
        bad = [o for o in args.override if "=" not in o]
        if bad:
            parser.error(f"--override: {bad[0]!r} is not KEY=VALUE")
        train_options["overrides"] = tuple(args.override)
    if args.baseline_checkout is not None:
        if "train" not in sections:
            parser.error("--baseline-checkout applies to the train section")
        if not (Path(args.baseline_checkout) / "scripts" / "train.py").is_file():
            parser.error(
                f"--baseline-checkout: {args.baseline_checkout} has no scripts/train.py (not an ss-drl checkout)"
            )
        from benchmarks.train import baseline_invocation

        try:
            baseline_invocation(args.experiment or DEFAULT_EXPERIMENT)
        except ValueError as exc:  # refused in one line, before any run
            print(f"scripts/benchmark.py: --baseline-checkout: {exc}", file=sys.stderr)
            return 2
        train_options["baseline_checkout"] = args.baseline_checkout
    quiet_torchrl()
    torch.set_num_threads(args.threads)
    print(header(argv, prog), flush=True)
    for section in sections:
        repeats = args.repeats or (QUICK_REPEATS if args.quick else DEFAULT_REPEATS[section])
        sizes = dict(QUICK_SIZES[section]) if args.quick else {}
        if section == "train":
            if args.train_steps is not None:
                sizes["steps"] = args.train_steps
            sizes.update(train_options, command=command_line(argv, prog))
        start = time.perf_counter()
        text = BENCHES[section](repeats, **sizes)
        print(text, flush=True)
        print(f"_{section}: {time.perf_counter() - start:.0f} s_\n", flush=True)
    return 0
