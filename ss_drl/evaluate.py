"""Load a run's checkpoint, run greedy episodes from S, print length/success, and draw the greedy path over a
heatmap of max_a Q(s||G, a)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

from ss_drl.training.outputs import CHECKPOINT_FILE, CHECKPOINT_PREV_FILE


class OldCheckpoint(ValueError):
    """A checkpoint of another format (one written before the learners were renamed): ``str(err)`` is one line."""


def load_agent(run_dir: Path):
    """The trained agent and maze of a run directory, from its checkpoint; :class:`OldCheckpoint` when the checkpoint
    is of another format (its config names options and learners that this version does not have), and
    :class:`~ss_drl.training.checkpoint.UnreadableCheckpoint` when torch cannot read it (both one line). A damaged
    checkpoint.pt is not passed over for checkpoint.prev.pt here: the run's final state is what is evaluated."""
    from ss_drl.smart_start import CountModel
    from ss_drl.training import checkpoint as ckpt
    from ss_drl.training.trainer import make_agent, make_maze

    path = Path(run_dir) / CHECKPOINT_FILE
    try:
        state = ckpt.read(path)
    except ckpt.UnreadableCheckpoint as exc:
        if exc.damaged and (Path(run_dir) / CHECKPOINT_PREV_FILE).is_file():
            raise ckpt.UnreadableCheckpoint(
                f"{exc}; trainer.resume=true continues the run from {CHECKPOINT_PREV_FILE}", exc.damaged
            ) from None
        raise
    problem = ckpt.format_problem(state, path)
    if problem is not None:
        if ckpt.written_before_rename(state):
            problem += f": read it with a checkout of {ckpt.LAST_OLD_COMMIT}"
        raise OldCheckpoint(problem)
    ckpt.check_state(state, path)
    cfg = OmegaConf.create(state["config"])
    maze = make_maze(cfg.env)
    counts = CountModel(maze.n_states, maze.n_actions)
    counts.load_state_dict(state["counts"])
    agent = make_agent(cfg, maze, int(cfg.seed), counts)
    agent.load_state_dict(state["agent"])
    return agent, maze, cfg


def _out_problem(out: Path) -> str | None:
    """Why the figure cannot be written to ``out`` (checked before the evaluation), or None."""
    import matplotlib.pyplot as plt

    formats = plt.figure().canvas.get_supported_filetypes()
    plt.close("all")
    if out.is_dir():
        return "is a directory; give a file name such as greedy_policy.png"
    if not out.parent.is_dir():
        return f"its folder {out.parent} does not exist"
    if out.suffix.lstrip(".").lower() not in formats:
        return (
            f"unknown figure format {out.suffix or '(none)'!r} (allowed: {', '.join('.' + f for f in sorted(formats))})"
        )
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("run_dir", type=Path, help="a run directory written by scripts/train.py")
    parser.add_argument(
        "--episodes", type=int, default=None,
        help="greedy episodes from S (default: the run's trainer.eval_episodes, derived from env.slip: 1 without "
        "slips, where every episode is the same walk)",
    )  # fmt: skip
    parser.add_argument(
        "--seed", type=int, default=0,
        help="seed of the slips' generator (runs with env.slip > 0): its own draws, not the trainer's, so the mean "
        "length varies around the run's last evaluation",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=None, help="PNG path (default: <run dir>/greedy_policy.png)")
    args = parser.parse_args(argv)
    if not (args.run_dir / CHECKPOINT_FILE).is_file():
        print(f"evaluate.py: error: no {CHECKPOINT_FILE} in {args.run_dir}", file=sys.stderr)
        return 2
    if args.episodes is not None and args.episodes < 1:
        print(f"evaluate.py: error: --episodes: {args.episodes} is out of range (allowed: >= 1)", file=sys.stderr)
        return 2
    out = args.out or args.run_dir / "greedy_policy.png"
    problem = _out_problem(out)
    if problem:
        print(f"evaluate.py: error: --out: {out}: {problem}", file=sys.stderr)
        return 2
    from ss_drl.training.checkpoint import UnreadableCheckpoint
    from ss_drl.training.config import ConfigError
    from ss_drl.training.figures import plot_minigrid_policy, plot_policy
    from ss_drl.training.greedy import evaluate_policy, evaluation_episodes, greedy_accuracy, greedy_policy, optimum
    from ss_drl.training.learned import BOUND, within_bound

    try:
        agent, maze, cfg = load_agent(args.run_dir)
    except (OldCheckpoint, UnreadableCheckpoint, ConfigError) as exc:
        print(f"evaluate.py: error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - a checkpoint this version cannot rebuild an agent from: one line
        path = args.run_dir / CHECKPOINT_FILE
        print(f"evaluate.py: error: {path}: cannot rebuild the agent: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    # As the trainer evaluates: the greedy policy rolled out in the env's dynamics, slips included, against the
    # shortest path or, under slips, the optimal policy's expected steps from S.
    slip = float(cfg.env.get("slip", 0) or 0)
    episodes = args.episodes or evaluation_episodes(slip, cfg.trainer.get("eval_episodes"))
    optimal = optimum(maze, slip)
    policy = greedy_policy(agent, maze)
    generator = torch.Generator().manual_seed(args.seed)
    ev = evaluate_policy(policy, maze, cfg.env.max_steps, int(episodes), slip, generator)
    if len(ev.lengths) == 1:
        length = ev.lengths[0]
        print(f"episode 1: length {length}, success {int(ev.success)} (optimal {optimal})")
    else:
        length = round(ev.mean_length, 3)
        within = within_bound(length, ev.success, optimal)  # the learned rule's own test, in exact fractions
        print(
            f"{len(ev.lengths)} greedy episodes from S at slip {slip:g} (seed {args.seed}): mean length {length}, "
            f"success rate {ev.success_rate:.3f} (optimal {optimal}); within {float(BOUND):g}x the optimum with "
            f"every episode at G: {'yes' if within else 'no'}"
        )
    accuracy = greedy_accuracy(policy, maze)
    print(f"greedy accuracy: {accuracy:.3f} (fraction of states whose greedy action is on a shortest path)")
    what = "greedy length" if len(ev.lengths) == 1 else "mean greedy length"
    title = f"{cfg.experiment} seed {cfg.seed}: {what} {length} (optimal {optimal})"
    if cfg.env.get("id"):  # a MiniGrid task: its own frame with the greedy path
        plot_minigrid_policy(maze, ev.path, out, title)
    else:
        q = agent.greedy_q_values(torch.arange(maze.n_cells), torch.tensor([maze.goal_cell]))[0]
        plot_policy(maze, q.amax(dim=-1).numpy(), ev.path, out, title)
    print(f"wrote {out}")
    return 0
