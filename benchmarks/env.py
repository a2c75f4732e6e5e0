"""The ``env`` section: env steps/s of the raw gymnasium env, of the same env through TorchRL's ``GymEnv``, and of the
native :class:`~ss_drl.envs.batched.BatchedMazeEnv` at N copies (``step_and_maybe_reset``; all copies count)."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch

from benchmarks.common import MILLION, fmt_rate, markdown_table, median


def _time_raw_gym(env_id: str, actions: list[int]) -> float:
    import gymnasium

    env = gymnasium.make(env_id).unwrapped
    env.reset(seed=0)
    step, reset = env.step, env.reset
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = step(action)
        if terminated or truncated:
            reset()
    elapsed = time.perf_counter() - start
    env.close()
    return len(actions) / elapsed


def _time_torchrl_loop(env, actions: list[torch.Tensor], steps_per_call: int) -> float:
    """Steps/s of ``step_and_maybe_reset`` over pre-generated actions (``steps_per_call`` env steps per call)."""
    td = env.reset()
    step = env.step_and_maybe_reset
    start = time.perf_counter()
    for action in actions:
        td.set("action", action)
        _, td = step(td)
    elapsed = time.perf_counter() - start
    return len(actions) * steps_per_call / elapsed


def bench_env(
    repeats: int,
    raw_steps: int = 20_000,
    gym_steps: int = 3_000,
    batched_iters: int = 3_000,
    num_envs: Sequence[int] = (1, 16, 256),
    env_id: str = "SSDRL/Easy-v0",
) -> str:
    """Env steps/s: raw gymnasium, TorchRL ``GymEnv`` and the native batched env at each N (median of repeats)."""
    import gymnasium  # noqa: F401
    from torchrl.envs import GymEnv

    import ss_drl  # noqa: F401  (registers the SSDRL/*-v0 ids)
    from ss_drl.envs import ENV_IDS
    from ss_drl.envs.batched import BatchedMazeEnv

    preset = ENV_IDS[env_id]
    rng = np.random.default_rng(0)
    gen = torch.Generator().manual_seed(0)
    raw_actions = rng.integers(0, 4, raw_steps).tolist()
    gym_actions = list(torch.randint(0, 4, (gym_steps,), generator=gen).unbind(0))
    batched_actions = {n: list(torch.randint(0, 4, (batched_iters, n), generator=gen).unbind(0)) for n in num_envs}

    wrapped = GymEnv(env_id, categorical_action_encoding=True)
    batched = {n: BatchedMazeEnv(preset, num_envs=n) for n in num_envs}
    # Warm-up (imports, first-call allocations), untimed.
    _time_raw_gym(env_id, raw_actions[:200])
    _time_torchrl_loop(wrapped, gym_actions[:50], 1)
    for n, env in batched.items():
        _time_torchrl_loop(env, batched_actions[n][:50], n)

    results: dict[str, list[float]] = {"raw": [], "gym": [], **{f"n{n}": [] for n in num_envs}}
    for _ in range(repeats):
        results["raw"].append(_time_raw_gym(env_id, raw_actions))
        results["gym"].append(_time_torchrl_loop(wrapped, gym_actions, 1))
        for n, env in batched.items():
            results[f"n{n}"].append(_time_torchrl_loop(env, batched_actions[n], n))
    wrapped.close()
    med = {key: median(values) for key, values in results.items()}

    rows = [
        [f"raw gymnasium `gymnasium.make({env_id!r}).unwrapped`", 1, raw_steps, fmt_rate(med["raw"])],
        [f"TorchRL `GymEnv({env_id!r})`, step_and_maybe_reset", 1, gym_steps, fmt_rate(med["gym"])],
    ]
    for n in num_envs:
        rows.append(
            [f"native `BatchedMazeEnv`, N={n}, step_and_maybe_reset", n, batched_iters * n, fmt_rate(med[f"n{n}"])]
        )
    out = [
        f"## env: env steps per second ({preset} maze, random actions, reset on done; median of {repeats})",
        "",
        markdown_table(["env", "copies", "steps per repeat", "env steps/s"], rows),
        "",
    ]
    if 1 in num_envs:
        out.append(f"- native N=1 / TorchRL GymEnv: {med['n1'] / med['gym']:.2f}x")
        out.append(f"- native N=1 / raw gymnasium: {med['n1'] / med['raw']:.2f}x")
    biggest = max(num_envs)
    verdict = "yes" if med[f"n{biggest}"] > MILLION else "no"
    out.append(f"- native N={biggest}: {fmt_rate(med[f'n{biggest}'])} steps/s; exceeds 1,000,000 steps/s: {verdict}")
    return "\n".join(out) + "\n"
