"""Per-cell tables updated in proportion to the rows a batch touches (``agent.sparse_tables``, issue 49): the lazy
Adam against torch's SparseAdam, the lazy Polyak step against the dense one, the rows an update moves, and a run
with the option that resumes from a checkpoint as if it had never stopped."""

from __future__ import annotations

import pytest
import torch
from helpers import TINY, assert_resume_equals_uninterrupted, compose_cfg
from tensordict import TensorDict

from ss_drl.agents.tables import LazyAdam, LazyPolyak, clip_grad_norm
from ss_drl.envs.maze import load_maze
from ss_drl.smart_start import CountModel
from ss_drl.training.trainer import make_agent


def test_lazy_adam_is_sparse_adam_and_moves_only_the_rows_with_a_gradient():
    torch.manual_seed(0)
    ours = torch.randn(30, 4, requires_grad=True)
    torch_s = ours.detach().clone().requires_grad_(True)
    lazy, reference = LazyAdam([ours], lr=0.01), torch.optim.SparseAdam([torch_s], lr=0.01)
    for _ in range(25):
        rows = torch.randint(0, 30, (12,))
        before = ours.detach().clone()
        for table, opt in ((ours, lazy), (torch_s, reference)):
            opt.zero_grad()
            torch.nn.functional.embedding(rows, table, sparse=True).pow(2).sum().backward()
            opt.step()
        moved = (ours.detach() != before).any(dim=1)
        untouched = torch.ones(30, dtype=torch.bool).index_fill_(0, rows, False)
        assert not moved[untouched].any()  # rows the batch did not touch: not one bit changed
        assert moved[rows].all()
        torch.testing.assert_close(ours.detach(), torch_s.detach(), rtol=1e-6, atol=1e-6)


def test_lazy_polyak_equals_the_dense_lerp_at_every_read():
    """Three rows of a table, online rows moved at chosen steps; the lazy target, read at chosen steps, equals the
    dense Polyak step taken every update, by hand: ``target_k = online + (1 - tau)^k (target_0 - online)``."""
    tau = 0.25
    online = torch.tensor([[1.0], [2.0], [3.0]])
    target = torch.zeros(3, 1)
    dense_online, dense_target = online.clone(), target.clone()
    lazy = LazyPolyak([(online, target, "state")], tau)
    moves = {2: [0], 5: [0, 2], 6: [1]}  # update -> rows the optimizer moves (by +1)
    for update in range(1, 9):
        touched = torch.tensor(moves.get(update, []), dtype=torch.int64)
        lazy.catch_up({"state": touched})  # before the optimizer moves them
        online[touched] += 1
        dense_online[touched] += 1
        lazy.step({"state": touched})
        dense_target.lerp_(dense_online, tau)
        if update in (3, 7):  # a read of rows 1 and 2 only: row 0 stays as it was
            stale = target[0].clone()
            lazy.catch_up({"state": torch.tensor([1, 2])})
            torch.testing.assert_close(target[1:], dense_target[1:])
            assert torch.equal(target[0], stale)
    lazy.catch_up()
    torch.testing.assert_close(target, dense_target)
    # Row 2 by hand: target 0 toward online 3 for 4 steps, then toward 4 for 4 steps (moved before step 5).
    after4 = 3 + 0.75**4 * (0 - 3)
    torch.testing.assert_close(target[2], torch.tensor([4 + 0.75**4 * (after4 - 4)]))


def test_clip_grad_norm_scales_dense_and_sparse_gradients_together():
    table = torch.zeros(6, 2, requires_grad=True)
    weight = torch.zeros(2, requires_grad=True)
    table.grad = torch.sparse_coo_tensor([[1, 1, 4]], torch.tensor([[3.0, 0.0], [0.0, 0.0], [0.0, 4.0]]), (6, 2))
    weight.grad = torch.tensor([0.0, 12.0])
    total = clip_grad_norm([table, weight], max_norm=6.5)
    assert float(total) == pytest.approx(13.0)  # sqrt(3^2 + 4^2 + 12^2)
    assert table.grad.is_coalesced()
    torch.testing.assert_close(table.grad.to_dense()[[1, 4]], torch.tensor([[1.5, 0.0], [0.0, 2.0]]), atol=1e-5, rtol=0)
    torch.testing.assert_close(weight.grad, torch.tensor([0.0, 6.0]), atol=1e-5, rtol=0)


def _agent(sparse: bool):
    maze = load_maze("easy_small")
    cfg = compose_cfg("+experiment=easy_small_ss_her_bounded", f"agent.sparse_tables={str(sparse).lower()}")
    counts = CountModel(maze.n_cells)
    torch.manual_seed(0)
    return make_agent(cfg, maze, 0, counts), maze


def _batch(maze, rows: int = 64):
    table = maze.transition_table()
    gen = torch.Generator().manual_seed(1)
    obs, nxt, act = [], [], torch.randint(0, 4, (rows,), generator=gen)
    cell = maze.start_cell
    for a in act.tolist():
        obs.append(cell)
        cell = int(table[cell, a])
        nxt.append(cell)
    obs, nxt = torch.tensor(obs).view(rows, 1), torch.tensor(nxt).view(rows, 1)
    goal = torch.full((rows, 1), maze.goal_cell)
    flag = torch.zeros(rows, 1, 1, dtype=torch.bool)
    flag[-1] = True  # one episode, cut at its end
    return TensorDict(
        {
            "observation": obs, "desired_goal": goal, "action": act.view(rows, 1),
            "next": {"observation": nxt, "desired_goal": goal.clone(), "reward": torch.zeros(rows, 1, 1),
                     "terminated": torch.zeros_like(flag), "truncated": flag, "done": flag},
        },
        batch_size=(rows, 1),
    )  # fmt: skip


def test_an_update_moves_exactly_the_table_rows_of_its_sample():
    agent, maze = _agent(sparse=True)
    agent.store(_batch(maze))
    key = ("state_encoder", "cells", "weight")
    table = agent.loss.value_network_params.get(key)
    seen = set()
    real_sample = agent.replay_buffer.sample

    def sample():
        s = real_sample()
        seen.update(s.get("observation").reshape(-1).tolist())
        return s

    agent.replay_buffer.sample = sample
    before = table.detach().clone()
    agent.update()
    moved = set(torch.nonzero((table.detach() != before).any(dim=1)).flatten().tolist())
    assert moved == seen  # the state table: the sampled states' rows, and no other


def test_sparse_tables_need_a_table_and_soft_target_updates():
    maze = load_maze("easy_small")
    for overrides, message in (
        (("agent.encoder=coords",), "no per-cell table"),
        (("agent.target_update=hard",), "target_update=soft"),
    ):
        cfg = compose_cfg("+experiment=easy_small_ss_her_bounded", "agent.sparse_tables=true", *overrides)
        with pytest.raises(ValueError, match=message):
            make_agent(cfg, maze, 0, CountModel(maze.n_cells))


@pytest.mark.slow
def test_a_run_with_sparse_tables_and_frontier_exploration_resumes_as_if_uninterrupted(tmp_path):
    run = [
        "+experiment=easy_small_ss_her_bounded",
        *(o for o in TINY if not o.startswith("trainer.total_env_steps=")),
        "agent.sparse_tables=true", "smart_start.select=frontier", "smart_start.explore=frontier",
        "trainer.total_env_steps=1200", "trainer.checkpoint_interval=300", "env.max_steps=100",
    ]  # fmt: skip
    assert_resume_equals_uninterrupted(run, tmp_path)
