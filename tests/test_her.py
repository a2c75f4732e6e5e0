"""``ss_drl.her.HindsightReplayBuffer``: HER goal relabeling at sample time, checked on small hand-built episodes.

Cells are chosen so that a goal names its source step: in most tests the next cell of copy ``e`` at absolute row
``t`` is ``cell(e, t) = 1000 * (e + 1) + t`` (or 11, 12, 13, ... for a single copy), so a sampled goal tells which
copy and which step it came from. The stored desired goal is ``GOAL = -1``, which is no cell, so a relabeled item is
recognisable. Expected goal sets are written out by hand or computed by a reference written here (per-copy episode
ids, no use of the buffer's bookkeeping).

The last tests put ``torchrl.data.HERReplayBuffer`` (torchrl 0.14) side by side with ours on the same data.
"""

from __future__ import annotations

import io
import random

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import HERReplayBuffer, LazyTensorStorage

from ss_drl.her import HindsightReplayBuffer

GOAL = -1  # stored desired goal: not a cell, so relabeled items are recognisable
KEYS = [
    "observation",
    "desired_goal",
    "action",
    ("next", "observation"),
    ("next", "desired_goal"),
    ("next", "reward"),
    ("next", "terminated"),
    ("next", "truncated"),
    ("next", "done"),
]


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Single-threaded torch: these tensors are tiny, and on a busy CPU intra-op threads make them 10x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def cell(env: int, row: int) -> int:
    return 1000 * (env + 1) + row


def make_batch(nxt, terminated=None, truncated=None, goal=GOAL, achieved: bool = False) -> TensorDict:
    """A (T, N) batch whose next cells are ``nxt`` (a 1-D list means N = 1); the observation is ``nxt - 1``.

    The stored reward is 1 where the next cell is the stored goal; ``done = terminated | truncated``. With
    ``achieved`` the batch also carries TorchRL HER's ``achieved_goal`` keys (root: the cell before the action).
    """
    nxt = torch.as_tensor(nxt, dtype=torch.int64)
    if nxt.ndim == 1:
        nxt = nxt.unsqueeze(1)
    shape = nxt.shape

    def flag(x):
        if x is None:
            return torch.zeros(shape, dtype=torch.bool)
        return torch.as_tensor(x, dtype=torch.bool).reshape(shape)

    terminated, truncated = flag(terminated), flag(truncated)
    goal = torch.as_tensor(goal, dtype=torch.int64)
    goal = goal.reshape(shape) if goal.numel() == shape.numel() else goal.expand(shape).clone()
    obs = nxt - 1
    td = TensorDict(
        {
            "observation": obs,
            "desired_goal": goal,
            "action": torch.zeros(shape, dtype=torch.int64),
            "next": {
                "observation": nxt,
                "desired_goal": goal.clone(),
                "reward": (nxt == goal).float().unsqueeze(-1),
                "terminated": terminated.unsqueeze(-1),
                "truncated": truncated.unsqueeze(-1),
                "done": (terminated | truncated).unsqueeze(-1),
            },
        },
        batch_size=shape,
    )
    if achieved:
        td.set("achieved_goal", obs.clone())
        td.set(("next", "achieved_goal"), nxt.clone())
    return td


def make_buffer(
    capacity, num_envs, batch_size=64, strategy="future", k=4, seed=0, goal_steps=False
) -> HindsightReplayBuffer:
    gen = torch.Generator().manual_seed(seed)
    return HindsightReplayBuffer(
        capacity, num_envs, batch_size, strategy=strategy, k=k, generator=gen, goal_steps=goal_steps
    )


def goal_sets(buf: HindsightReplayBuffer, slots, reps: int = 400) -> dict[int, set[int]]:
    """Slot -> set of goals that ``sample_goals`` gave over ``reps`` draws for that slot."""
    slots = torch.as_tensor(slots)
    goals = buf.sample_goals(slots.repeat(reps))[0].view(reps, len(slots))
    return {int(s): set(goals[:, j].tolist()) for j, s in enumerate(slots)}


def n_relabeled(batch_size: int, k: int) -> int:
    return round(batch_size * k / (k + 1))


def stored(buf: HindsightReplayBuffer, index: torch.Tensor) -> TensorDict:
    return buf.storage[index]


# One copy: episode A (rows 0-4, next cells 11..15, terminated at row 4) then episode B still running (rows 5-7,
# next cells 16, 17, 18). The next cell of row t is 11 + t.
TWO_EPISODES = dict(nxt=[11, 12, 13, 14, 15, 16, 17, 18], terminated=[0, 0, 0, 0, 1, 0, 0, 0])
FUTURE = {
    0: {11, 12, 13, 14, 15},
    1: {12, 13, 14, 15},
    2: {13, 14, 15},
    3: {14, 15},
    4: {15},
    5: {16, 17, 18},
    6: {17, 18},
    7: {18},
}
FINAL = {0: 15, 1: 15, 2: 15, 3: 15, 4: 15, 5: 18, 6: 18, 7: 18}
EPISODE = {t: ({11, 12, 13, 14, 15} if t <= 4 else {16, 17, 18}) for t in range(8)}


def test_rejects_bad_arguments_and_batches():
    with pytest.raises(ValueError, match="strategy"):
        make_buffer(8, 1, strategy="nearest")
    with pytest.raises(ValueError, match="k must be"):
        make_buffer(8, 1, k=-1)
    buf = make_buffer(10, 3)  # capacity rounded up to 4 rows of 3 copies
    assert buf.rows == 4
    with pytest.raises(ValueError, match="expected a"):
        buf.extend(make_batch([[11, 21]]))  # 2 copies, not 3
    with pytest.raises(ValueError, match="larger than the buffer"):
        buf.extend(make_batch([[cell(e, t) for e in range(3)] for t in range(5)]))


# --- 1. future ----------------------------------------------------------------------------------------------------
def test_future_sample_goals_are_exactly_the_steps_from_t_to_the_episode_end():
    buf = make_buffer(16, 1, strategy="future", seed=1)
    buf.extend(make_batch(**TWO_EPISODES))
    slots = torch.arange(8).repeat(500)
    goals = buf.sample_goals(slots)[0]
    source = goals - 11  # the row whose next cell is the goal
    end = torch.where(slots <= 4, 4, 7)
    assert bool(((source >= slots) & (source <= end)).all())  # every single draw is in [t, episode end]
    assert goal_sets(buf, range(8)) == FUTURE  # and over many draws each step of that range occurs

    # the generator drives the draw: same seed, same goals
    again = make_buffer(16, 1, strategy="future", seed=1)
    again.extend(make_batch(**TWO_EPISODES))
    assert torch.equal(again.sample_goals(slots)[0], goals)


def test_future_end_to_end_sample():
    torch.manual_seed(0)
    buf = make_buffer(16, 1, batch_size=2000, strategy="future", k=4, seed=2)
    buf.extend(make_batch(**TWO_EPISODES))
    data = buf.sample()
    n_her = n_relabeled(2000, 4)
    index, goal = data["index"][:n_her], data["desired_goal"][:n_her]
    assert torch.equal(data["next", "desired_goal"][:n_her], goal)
    assert set(zip(index.tolist(), goal.tolist())) == {(t, g) for t, gs in FUTURE.items() for g in gs}


# --- 2. final -----------------------------------------------------------------------------------------------------
def test_final_is_the_episode_last_next_state_or_the_newest_step_while_running():
    buf = make_buffer(16, 1, batch_size=500, strategy="final", seed=3)
    buf.extend(make_batch(**TWO_EPISODES))
    assert buf.sample_goals(torch.arange(8))[0].tolist() == [FINAL[t] for t in range(8)]

    buf.extend(make_batch([19], terminated=[1]))  # episode B ends at row 8 (next cell 19)
    assert buf.sample_goals(torch.arange(9))[0].tolist() == [15] * 5 + [19] * 4
    buf.extend(make_batch([20, 21]))  # episode C running: rows 9, 10
    assert buf.sample_goals(torch.arange(11))[0].tolist() == [15] * 5 + [19] * 4 + [21] * 2

    torch.manual_seed(0)
    data = buf.sample()
    n_her = n_relabeled(500, 4)
    expected = torch.tensor([15] * 5 + [19] * 4 + [21] * 2)[data["index"][:n_her]]
    assert torch.equal(data["desired_goal"][:n_her], expected)
    assert torch.equal(data["next", "desired_goal"][:n_her], expected)


# --- 3. episode and random ----------------------------------------------------------------------------------------
def test_episode_strategy_covers_the_whole_stored_episode():
    buf = make_buffer(16, 1, strategy="episode", seed=4)
    buf.extend(make_batch(**TWO_EPISODES))
    assert goal_sets(buf, range(8)) == EPISODE

    # an episode longer than the buffer offers only its steps still stored
    small = make_buffer(4, 1, strategy="episode", seed=4)
    small.extend(make_batch([11, 12, 13]))
    small.extend(make_batch([14, 15, 16]))  # rows 0, 1 overwritten; rows 2..5 stored
    assert goal_sets(small, range(4)) == {s: {13, 14, 15, 16} for s in range(4)}


def test_random_strategy_covers_every_stored_transition_of_every_copy():
    buf = make_buffer(8 * 2, 2, strategy="random", seed=5)  # 8 rows of 2 copies
    for first in (0, 4, 8):  # 12 rows written: rows 0..3 are overwritten
        rows = range(first, first + 4)
        nxt = [[cell(0, r), cell(1, r)] for r in rows]
        buf.extend(make_batch(nxt, terminated=[[r % 3 == 2, r % 5 == 4] for r in rows]))
    stored_cells = {cell(e, r) for e in range(2) for r in range(4, 12)}
    assert goal_sets(buf, range(16), reps=600) == {s: stored_cells for s in range(16)}


# --- 4. reward / terminated / truncated / done recomputation --------------------------------------------------------
# Three copies, 5 rows. Copy 0: real goal 15, reached (terminated) at row 4. Copy 1: truncated at row 2, then a
# running episode. Copy 2: truncated at row 2, then a running episode. Every relabeled transition of a copy gets the
# goal RELABEL[copy] (sample_goals is replaced, so the expected values are exact).
RECOMPUTE_NEXT = [[11, 21, 31], [12, 22, 32], [13, 23, 33], [14, 24, 34], [15, 25, 35]]
RECOMPUTE_TERMINATED = [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0]]
RECOMPUTE_TRUNCATED = [[0, 0, 0], [0, 0, 0], [0, 1, 1], [0, 0, 0], [0, 0, 0]]
RECOMPUTE_GOAL = [[15, 99, 99]] * 5
RELABEL = torch.tensor([13, 23, 31])
# expected after relabeling, rows x copies
EXP_REWARD = [[0, 0, 1], [0, 0, 0], [1, 1, 0], [0, 0, 0], [0, 0, 0]]
EXP_TERMINATED = EXP_REWARD  # copy 0 row 4 was terminal for goal 15: with goal 13 it is not
EXP_TRUNCATED = [[0, 0, 0], [0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 0]]  # copy 1 row 2 reaches 23: cleared
EXP_DONE = [[0, 0, 1], [0, 0, 0], [1, 1, 1], [0, 0, 0], [0, 0, 0]]


def recompute_batch() -> TensorDict:
    return make_batch(RECOMPUTE_NEXT, RECOMPUTE_TERMINATED, RECOMPUTE_TRUNCATED, goal=RECOMPUTE_GOAL)


def test_relabeled_reward_and_flags_are_recomputed_and_the_rest_is_untouched(monkeypatch):
    buf = make_buffer(15, 3, batch_size=300, strategy="future", k=4)
    buf.extend(recompute_batch())
    monkeypatch.setattr(buf, "sample_goals", lambda index: (RELABEL[index % 3], torch.zeros_like(index)))
    before = buf.storage[torch.arange(15)].clone()
    torch.manual_seed(0)
    data = buf.sample()
    assert (buf.storage[torch.arange(15)] == before).all()  # relabeling works on the sampled copy only
    n_her = n_relabeled(300, 4)
    index = data["index"]
    row, env = index // 3, index % 3

    her = data[:n_her]
    r, e = row[:n_her], env[:n_her]
    assert torch.equal(her["desired_goal"], RELABEL[e])
    assert torch.equal(her["next", "desired_goal"], RELABEL[e])
    assert torch.equal(her["next", "reward"].squeeze(-1), torch.tensor(EXP_REWARD, dtype=torch.float32)[r, e])
    assert torch.equal(her["next", "terminated"].squeeze(-1), torch.tensor(EXP_TERMINATED, dtype=torch.bool)[r, e])
    assert torch.equal(her["next", "truncated"].squeeze(-1), torch.tensor(EXP_TRUNCATED, dtype=torch.bool)[r, e])
    assert torch.equal(her["next", "done"].squeeze(-1), torch.tensor(EXP_DONE, dtype=torch.bool)[r, e])
    # the special cases all occur in this batch
    slots_seen = set(index[:n_her].tolist())
    assert {4 * 3 + 0, 2 * 3 + 0, 2 * 3 + 1, 2 * 3 + 2, 0 * 3 + 2} <= slots_seen
    # state, action and next state are not touched
    original = stored(buf, index)
    for key in ("observation", "action", ("next", "observation")):
        assert torch.equal(data[key], original[key])
    # the un-relabeled part keeps its stored values exactly
    for key in KEYS:
        assert torch.equal(data[n_her:][key], original[n_her:][key]), key


def test_recomputation_rule_with_a_real_strategy():
    """Episode strategy: the terminal step of copy 0 gets other goals of its episode and must become non-terminal."""
    buf = make_buffer(15, 3, batch_size=4000, strategy="episode", k=4, seed=6)
    buf.extend(recompute_batch())
    torch.manual_seed(1)
    data = buf.sample()
    n_her = n_relabeled(4000, 4)
    her, original = data[:n_her], stored(buf, data["index"][:n_her])
    goal = her["desired_goal"]
    reached = her["next", "observation"] == goal
    truncated = original["next", "truncated"].squeeze(-1) & ~reached
    assert torch.equal(her["next", "desired_goal"], goal)
    assert torch.equal(her["next", "reward"].squeeze(-1), reached.float())
    assert torch.equal(her["next", "terminated"].squeeze(-1), reached)
    assert torch.equal(her["next", "truncated"].squeeze(-1), truncated)
    assert torch.equal(her["next", "done"].squeeze(-1), reached | truncated)
    was_terminal = original["next", "terminated"].squeeze(-1)
    assert bool((was_terminal & ~reached).any()), "a stored terminal step relabeled to another goal"
    assert not bool(her["next", "terminated"][was_terminal & ~reached].any())
    assert bool((~was_terminal & reached).any()), "a non-terminal step that reaches its new goal"


# --- 5. episode boundaries, env copies, split extends, wrap-around ----------------------------------------------------
def episode_reference(done_rows: dict[int, list[bool]]):
    """Per copy, the episode id of each absolute row from the done flags (episode ends at a done row)."""
    ids = {}
    for e, done in done_rows.items():
        cur, ids[e] = 0, []
        for d in done:
            ids[e].append(cur)
            cur += int(d)
    return ids


def expected_goals(strategy, ep_ids, e, t, written, rows):
    """Reference goal set for the transition of copy e at absolute row t (no buffer bookkeeping used)."""
    oldest = max(0, written - rows)
    same = [a for a in range(oldest, written) if ep_ids[e][a] == ep_ids[e][t]]
    if strategy == "future":
        return {cell(e, a) for a in same if a >= t}
    if strategy == "final":
        return {cell(e, max(same))}
    return {cell(e, a) for a in same}  # episode


def check_all_slots(buf, strategy, ep_ids, reps=150):
    written, rows, n = buf.rows_written, buf.rows, buf.num_envs
    oldest = max(0, written - rows)
    slots = torch.arange(min(written, rows) * n)
    goals = buf.sample_goals(slots.repeat(reps))[0].view(reps, -1).T.tolist()
    for s, drawn in enumerate(goals):
        r, e = divmod(s, n)
        t = written - 1 - (written - 1 - r) % rows  # absolute row now stored in storage row r
        for g in set(drawn):
            src_env, src_row = divmod(g, 1000)
            assert src_env - 1 == e, f"slot {s}: goal {g} from another copy"
            assert src_row >= oldest, f"slot {s}: goal {g} from overwritten data"
            assert ep_ids[e][src_row] == ep_ids[e][t], f"slot {s}: goal {g} from another episode"
            assert strategy != "future" or src_row >= t, f"slot {s}: goal {g} from a step before t"
        assert set(drawn) == expected_goals(strategy, ep_ids, e, t, written, rows), f"slot {s}"


@pytest.mark.parametrize("strategy", ["future", "final", "episode"])
def test_hand_built_episodes_split_across_extends_in_three_copies(strategy):
    # copy 0: episodes rows 0-1 | 2-5 | 6-8 running; copy 1: 0-2 | 3-8; copy 2: 0 | 1-3 | 4 | 5-8 running
    done = {
        0: [0, 1, 0, 0, 0, 1, 0, 0, 0],
        1: [0, 0, 1, 0, 0, 0, 0, 0, 1],
        2: [1, 0, 0, 1, 1, 0, 0, 0, 0],
    }
    buf = make_buffer(3 * 16, 3, strategy=strategy, seed=7)
    for lo, hi in ((0, 3), (3, 5), (5, 9)):  # episodes cross these extend() boundaries
        nxt = [[cell(e, t) for e in range(3)] for t in range(lo, hi)]
        buf.extend(make_batch(nxt, terminated=[[done[e][t] for e in range(3)] for t in range(lo, hi)]))
    ep_ids = episode_reference(done)
    check_all_slots(buf, strategy, ep_ids)
    # two of the expected sets written out, to anchor the reference
    sets = goal_sets(buf, [3 * 3 + 0, 2 * 3 + 2])  # copy 0 row 3 (episode 2-5), copy 2 row 2 (episode 1-3)
    c0 = {"future": {3, 4, 5}, "final": {5}, "episode": {2, 3, 4, 5}}[strategy]
    c2 = {"future": {2, 3}, "final": {3}, "episode": {1, 2, 3}}[strategy]
    assert sets == {9: {cell(0, a) for a in c0}, 8: {cell(2, a) for a in c2}}


@pytest.mark.parametrize("strategy", ["future", "final", "episode"])
@pytest.mark.parametrize("num_envs", [2, 3])
def test_goals_stay_in_copy_and_episode_after_wraparound(strategy, num_envs):
    rows = 8
    for seed in range(3):
        rng = random.Random(seed)
        p_done = (0.08, 0.3, 0.7)[seed]  # long episodes (longer than the buffer), medium, very short
        buf = make_buffer(rows * num_envs, num_envs, strategy=strategy, seed=seed)
        done_rows = {e: [] for e in range(num_envs)}
        written = 0
        for _ in range(14):  # ~60 rows through an 8-row buffer
            n_rows = rng.randint(1, rows)
            done = [[rng.random() < p_done for _ in range(num_envs)] for _ in range(n_rows)]
            nxt = [[cell(e, written + t) for e in range(num_envs)] for t in range(n_rows)]
            buf.extend(make_batch(nxt, terminated=done))
            for t in range(n_rows):
                for e in range(num_envs):
                    done_rows[e].append(done[t][e])
            written += n_rows
            check_all_slots(buf, strategy, episode_reference(done_rows))
        assert written > 2 * rows  # the buffer wrapped around


# --- 6. relabel ratio ----------------------------------------------------------------------------------------------
def test_k0_means_no_relabeling(monkeypatch):
    buf = make_buffer(16, 1, batch_size=64, strategy="future", k=0)
    buf.extend(make_batch(**TWO_EPISODES))
    assert buf.relabel_ratio == 0.0

    def fail(index):
        raise AssertionError("goals sampled with k = 0")

    monkeypatch.setattr(buf, "sample_goals", fail)
    data = buf.sample()
    original = stored(buf, data["index"])
    for key in KEYS:
        assert torch.equal(data[key], original[key]), key
    assert bool((data["desired_goal"] == GOAL).all())


@pytest.mark.parametrize(("batch_size", "expected"), [(1, 1), (2, 2), (7, 6), (50, 40), (256, 205)])
def test_k4_relabels_exactly_the_first_round_b_times_4_5_items(batch_size, expected):
    buf = make_buffer(16, 1, batch_size=batch_size, strategy="future", k=4)
    buf.extend(make_batch(**TWO_EPISODES))
    assert buf.relabel_ratio == 0.8
    assert n_relabeled(batch_size, 4) == expected
    data = buf.sample()
    relabeled = data["desired_goal"] != GOAL
    assert relabeled.tolist() == [True] * expected + [False] * (batch_size - expected)
    assert torch.equal(data["next", "desired_goal"] != GOAL, relabeled)


# --- 7. sampling reads O(batch) items, whatever the number stored ----------------------------------------------------
def _elements(index, length: int) -> int:
    if isinstance(index, slice):
        return len(range(*index.indices(length)))
    if isinstance(index, tuple):
        index = index[0]
    return torch.as_tensor(index).numel()


@pytest.fixture
def storage_reads(monkeypatch):
    """Every storage read as the number of elements it reads: ``LazyTensorStorage.get`` (``storage[...]``
    included) and our buffer's goal gather."""
    reads: list[int] = []
    original = LazyTensorStorage.get
    original_goals = HindsightReplayBuffer.achieved_goals

    def get(self, index):
        reads.append(_elements(index, len(self)))
        return original(self, index)

    def achieved_goals(self, slots):
        reads.append(_elements(slots, len(self)))
        return original_goals(self, slots)

    monkeypatch.setattr(LazyTensorStorage, "get", get)
    monkeypatch.setattr(HindsightReplayBuffer, "achieved_goals", achieved_goals)
    return reads


def filled_buffer(n_stored: int, num_envs: int = 4, batch_size: int = 256, goal_steps=False) -> HindsightReplayBuffer:
    buf = make_buffer(n_stored, num_envs, batch_size=batch_size, strategy="future", k=4, goal_steps=goal_steps)
    gen = torch.Generator().manual_seed(0)
    n_rows = n_stored // num_envs
    nxt = torch.randint(0, 500, (n_rows, num_envs), generator=gen)
    buf.extend(make_batch(nxt, terminated=torch.rand(n_rows, num_envs, generator=gen) < 0.02))
    return buf


def test_sampling_reads_only_batch_items_regardless_of_buffer_size(storage_reads):
    per_sample = {}
    for n_stored in (10_000, 200_000):
        buf = filled_buffer(n_stored)
        assert len(buf) == n_stored
        assert storage_reads == []  # extend() reads nothing back
        for _ in range(3):
            buf.sample()
        per_sample[n_stored] = list(storage_reads)
        storage_reads.clear()
    # each sample: the batch (256) and one goal per relabeled item (205); nothing proportional to the size
    assert per_sample[10_000] == per_sample[200_000] == [256, 205] * 3


def test_goal_steps_read_one_episode_end_per_real_goal_item(storage_reads):
    """With ``goal_steps`` on (the hindsight bound), each real-goal item (51 of 256) also reads its episode's last
    next state (was G entered?); still nothing proportional to the size."""
    per_sample = {}
    for n_stored in (10_000, 200_000):
        buf = filled_buffer(n_stored, goal_steps=True)
        for _ in range(3):
            buf.sample()
        per_sample[n_stored] = list(storage_reads)
        storage_reads.clear()
    assert per_sample[10_000] == per_sample[200_000] == [256, 205, 51] * 3


# --- 8. torchrl.data.HERReplayBuffer side by side --------------------------------------------------------------------
# What a user of the two buffers sees on a real sample: (a) the relabeled goal, (b) the terminated/done flags, and
# (c) its episode cache once the storage wraps. How TorchRL reaches them (its episode cache, how often it reads the
# storage) is its own business and is not asserted here.
#
# TorchRL's defects are written as the assertion of the CORRECT behaviour (what ours does on the same data, and what a
# fixed upstream buffer would do), marked as strict expected failures: each fails today, and the day upstream fixes
# its buffer the test passes, which strict=True turns into an error (XPASS(strict)). Then drop the mark and decide
# whether our buffer is still needed. ``raises=`` names the failure each one expects today, so that any other error
# (an API change in TorchRL, a broken test) still fails loudly. Our buffer's side of each comparison is a plain test.
TORCHRL_DEFECT = "torchrl.data.HERReplayBuffer (torchrl 0.14) defect; fixed upstream if this XPASSes"


def torchrl_her(strategy, capacity=100, batch_size=64, **kwargs) -> HERReplayBuffer:
    def reward_fn(td):  # the same sparse reward as ours: next cell == goal
        return (td["next", "achieved_goal"] == td["desired_goal"]).float().unsqueeze(-1)

    return HERReplayBuffer(
        reward_fn,
        her_ratio=1.0,
        strategy=strategy,
        storage=LazyTensorStorage(capacity),
        batch_size=batch_size,
        **kwargs,
    )


def one_episode() -> TensorDict:
    """One episode, one copy: cells 10 -> 11 -> 12 -> 13, terminated at the last step."""
    return make_batch([11, 12, 13], terminated=[0, 0, 1], achieved=True)


@pytest.mark.xfail(strict=True, raises=AssertionError, reason=f"(a) {TORCHRL_DEFECT}: 'final' takes s_(T-1)")
def test_torchrl_her_a_final_goal_is_the_episode_last_next_state():
    # The correct "final" goal is s_T = 13, the state the last action reached, and the last transition, which is the
    # one that reached it, is rewarded. TorchRL's default achieved_goal_key ("achieved_goal", the root: before the
    # action) gives s_(T-1) = 12 instead, so its "final" relabel never rewards the transition that reached the goal.
    theirs = torchrl_her("final")
    theirs.extend(one_episode().reshape(-1))
    torch.manual_seed(0)
    data = theirs.sample()
    assert set(data["desired_goal"].tolist()) == {13}
    assert bool(data["next", "reward"][data["index"] == 2].all())


@pytest.mark.xfail(strict=True, raises=AssertionError, reason=f"(a) {TORCHRL_DEFECT}: 'future' includes s_t")
def test_torchrl_her_a_future_goals_are_the_states_reached_from_t_on():
    # The correct "future" goals of step t are the states reached from t on, s_(t+1) .. s_T. TorchRL's include the
    # step's own starting cell s_t (never reached by that step), and miss s_T.
    theirs = torchrl_her("future", batch_size=2000)
    theirs.extend(one_episode().reshape(-1))
    torch.manual_seed(0)
    data = theirs.sample()
    pairs = set(zip(data["index"].tolist(), data["desired_goal"].tolist()))
    assert pairs == {(0, 11), (0, 12), (0, 13), (1, 12), (1, 13), (2, 13)}


def test_ours_and_torchrl_with_the_post_action_key_take_the_goal_from_s_t_plus_1():
    """Our buffer's side of (a): "final" is s_T and rewards the last transition, "future" is s_(t+1) .. s_T. And the
    workaround for TorchRL: pointing achieved_goal_key at ("next", "achieved_goal") takes the post-action goal."""
    ours = make_buffer(10, 1, batch_size=64, strategy="final", k=1000)
    ours.extend(one_episode())
    torch.manual_seed(0)
    data = ours.sample()
    assert set(data["desired_goal"].tolist()) == {13}
    assert bool(data["next", "reward"][data["index"] == 2].all())
    ours = make_buffer(10, 1, strategy="future", seed=8)
    ours.extend(one_episode())
    assert goal_sets(ours, range(3)) == {0: {11, 12, 13}, 1: {12, 13}, 2: {13}}

    fixed = torchrl_her("final", achieved_goal_key=("next", "achieved_goal"))
    fixed.extend(one_episode().reshape(-1))
    assert set(fixed.sample()["desired_goal"].tolist()) == {13}


def two_episodes_with_goals() -> TensorDict:
    """Episode 1 (real goal 13): 11, 12, 13 terminated; episode 2 (real goal 99): 21, 22, 23, 24 truncated."""
    return make_batch(
        [11, 12, 13, 21, 22, 23, 24],
        terminated=[0, 0, 1, 0, 0, 0, 0],
        truncated=[0, 0, 0, 0, 0, 0, 1],
        goal=[13, 13, 13, 99, 99, 99, 99],
        achieved=True,
    )


def check_relabeled_flags(data: TensorDict, stored_truncated: torch.Tensor) -> None:
    """The flags a relabeled goal must have: terminated exactly where the next cell is the new goal (reward 1),
    truncated as stored unless the goal was reached, done = terminated | truncated."""
    reward = data["next", "reward"].squeeze(-1)
    assert torch.equal(reward, (data["next", "observation"] == data["desired_goal"]).float())
    truncated = stored_truncated.squeeze(-1) & (reward == 0)
    assert torch.equal(data["next", "terminated"].squeeze(-1), reward == 1)
    assert torch.equal(data["next", "truncated"].squeeze(-1), truncated)
    assert torch.equal(data["next", "done"].squeeze(-1), (reward == 1) | truncated)


@pytest.mark.xfail(strict=True, raises=AssertionError, reason=f"(b) {TORCHRL_DEFECT}: terminated/done kept as stored")
def test_torchrl_her_b_recomputes_terminated_and_done_for_the_new_goal():
    # TorchRL recomputes the reward for the relabeled goal but keeps terminated/done as stored for the real goal: a
    # step that reaches its new goal bootstraps past it, and the real goal's last step stays terminal for goals it
    # does not reach. The post-action key is used, so that only (b) is at play.
    theirs = torchrl_her("episode", batch_size=2000, achieved_goal_key=("next", "achieved_goal"))
    theirs.extend(two_episodes_with_goals().reshape(-1))
    torch.manual_seed(0)
    data = theirs.sample()
    check_relabeled_flags(data, theirs.storage[data["index"]]["next", "truncated"])


def test_ours_recomputes_terminated_and_done_for_the_new_goal():
    """Our buffer's side of (b), on the same episodes; both kinds of flag change occur in the sample."""
    ours = make_buffer(10, 1, batch_size=2000, strategy="episode", k=1000, seed=9)
    ours.extend(two_episodes_with_goals())
    data = ours.sample()[: n_relabeled(2000, 1000)]
    stored_flags = ours.storage[data["index"]]["next"]
    check_relabeled_flags(data, stored_flags["truncated"])
    reward = data["next", "reward"].squeeze(-1)
    assert bool(((reward == 1) & ~stored_flags["terminated"].squeeze(-1)).any())  # a new goal reached: now terminal
    assert bool(((reward == 0) & stored_flags["terminated"].squeeze(-1)).any())  # the old terminal step: no longer


def wrapped_by_extend(theirs: HERReplayBuffer | None, ours: HindsightReplayBuffer) -> None:
    """Three 3-step episodes (cells 1-3, 11-13, 21-23, each terminated) through multi-item extends into a storage of
    6: rows 0-2 hold the third episode, rows 3-5 the second. TorchRL's buffer is sampled after each of the first two
    (filling its episode cache)."""
    for i in range(3):
        batch = make_batch([10 * i + 1, 10 * i + 2, 10 * i + 3], terminated=[0, 0, 1], achieved=True)
        ours.extend(batch)
        if theirs is not None:
            theirs.extend(batch.reshape(-1))
            if i < 2:
                theirs.sample()


#: The final goal of each row once both wrap tests have written their episodes.
WRAPPED_BY_EXTEND = {0: 23, 1: 23, 2: 23, 3: 13, 4: 13, 5: 13}
WRAPPED_BY_ADD = {0: 21, 1: 23, 2: 23}  # 21 ends the episode at row 0; 22, 23 are still running


@pytest.mark.xfail(
    strict=True,
    raises=(RuntimeError, AssertionError),
    reason=f"(c) {TORCHRL_DEFECT}: after a multi-item extend past the wrap, its cache key holds a tensor",
)
def test_torchrl_her_c_samples_correct_goals_after_the_storage_wraps_by_extend():
    # Today the sample raises (RuntimeError: "Boolean value of Tensor with more than one value is ambiguous"): its
    # episode cache key holds the storage cursor as a tensor once the storage wraps.
    theirs = torchrl_her("final", capacity=6, batch_size=300, achieved_goal_key=("next", "achieved_goal"))
    wrapped_by_extend(theirs, make_buffer(6, 1, strategy="final"))
    torch.manual_seed(0)
    data = theirs.sample()
    assert dict(zip(data["index"].tolist(), data["desired_goal"].tolist())) == WRAPPED_BY_EXTEND


def add_two_episodes(theirs: HERReplayBuffer | None, ours: HindsightReplayBuffer) -> TensorDict | None:
    """Episodes 11, 12, 13 (terminated) and then 21 (terminated), 22, 23 (running) into a storage of 3, TorchRL's
    one step at a time with add(), sampled after each episode; returns TorchRL's last sample."""
    data = None
    for cells, term in (([11, 12, 13], [0, 0, 1]), ([21, 22, 23], [1, 0, 0])):
        batch = make_batch(cells, terminated=term, achieved=True)
        ours.extend(batch)
        if theirs is not None:
            for t in range(3):
                theirs.add(batch[t, 0])
            torch.manual_seed(0)
            data = theirs.sample()
    return data


@pytest.mark.xfail(
    strict=True,
    raises=AssertionError,
    reason=f"(c) {TORCHRL_DEFECT}: after `capacity` add() calls its cache key repeats: a stale cache",
)
def test_torchrl_her_c_samples_correct_goals_after_the_storage_wraps_by_add():
    # Today the goal crosses the episode boundary after row 0: row 0's final goal comes out as 23, not 21.
    theirs = torchrl_her("final", capacity=3, batch_size=300, achieved_goal_key=("next", "achieved_goal"))
    data = add_two_episodes(theirs, make_buffer(3, 1, batch_size=300, strategy="final", k=1000))
    assert dict(zip(data["index"].tolist(), data["desired_goal"].tolist())) == WRAPPED_BY_ADD


def test_ours_samples_correct_goals_after_the_storage_wraps():
    """Our buffer's side of (c): the final goal of every row after both kinds of wrap."""
    ours = make_buffer(6, 1, strategy="final")
    wrapped_by_extend(None, ours)
    assert ours.sample_goals(torch.arange(6))[0].tolist() == [WRAPPED_BY_EXTEND[r] for r in range(6)]
    ours = make_buffer(3, 1, batch_size=300, strategy="final", k=1000)
    add_two_episodes(None, ours)
    assert ours.sample_goals(torch.arange(3))[0].tolist() == [WRAPPED_BY_ADD[r] for r in range(3)]


# --- 9. state_dict round trip ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("strategy", ["future", "final", "episode", "random"])
def test_state_dict_round_trip_gives_identical_samples(strategy):
    buf = make_buffer(6 * 2, 2, batch_size=128, strategy=strategy, k=4, seed=10)
    rng = random.Random(0)
    written = 0
    for n_rows in (4, 5, 3):  # wraps around, episodes left open
        nxt = [[cell(e, written + t) for e in range(2)] for t in range(n_rows)]
        buf.extend(make_batch(nxt, terminated=[[rng.random() < 0.3 for _ in range(2)] for _ in range(n_rows)]))
        written += n_rows
    blob = io.BytesIO()
    torch.save(buf.state_dict(), blob)
    blob.seek(0)
    restored = make_buffer(6 * 2, 2, batch_size=128, strategy=strategy, k=4, seed=123)
    restored.load_state_dict(torch.load(blob, weights_only=False))

    def same_samples():
        out = []
        for b in (buf, restored):
            torch.manual_seed(42)
            b.generator.manual_seed(43)
            out.append(b.sample())
        for key in ["index", *KEYS]:
            assert torch.equal(out[0][key], out[1][key]), key

    same_samples()
    # the episode bookkeeping came along: writing on closes the same open episodes in both
    nxt = [[cell(e, written + t) for e in range(2)] for t in range(2)]
    batch = make_batch(nxt, terminated=[[1, 0], [0, 1]])
    buf.extend(batch)
    restored.extend(batch)
    same_samples()
    goals = []
    for b in (buf, restored):
        b.generator.manual_seed(44)
        goals.append(b.sample_goals(torch.arange(12))[0])
    assert torch.equal(goals[0], goals[1])


# --- n-step targets --------------------------------------------------------------------------------------------------
# One copy, G = 15, gamma = 0.5, n = 3. Episode A: rows 0-4, next cells 11..15, enters G at row 4 (terminated).
# Episode B: rows 5-7, next cells 21..23, cut by the time limit at row 7 (truncated). Episode C: rows 8-9, next cells
# 31, 32, still running.
N_STEP_NEXT = [11, 12, 13, 14, 15, 21, 22, 23, 31, 32]
N_STEP_EPISODES = [range(0, 5), range(5, 8), range(8, 10)]


def n_step_buffer(
    strategy: str, k: int, goal_steps: bool = False, window_states: bool = False
) -> HindsightReplayBuffer:
    buf = HindsightReplayBuffer(
        64,
        1,
        512,
        strategy=strategy,
        k=k,
        generator=torch.Generator().manual_seed(3),
        n_step=3,
        gamma=0.5,
        goal_steps=goal_steps,
        window_states=window_states,
    )
    terminated = [t == 4 for t in range(10)]
    truncated = [t == 7 for t in range(10)]
    buf.extend(make_batch(N_STEP_NEXT, terminated=terminated, truncated=truncated, goal=15))
    return buf


def expected_n_step(row: int, goal: int, n: int = 3, gamma: float = 0.5) -> tuple[int, float, bool, bool, int]:
    """(next cell, reward, terminated, truncated, m) by walking the episode table above."""
    episode = next(e for e in N_STEP_EPISODES if row in e)
    reward, m = 0.0, 0
    for j, t in enumerate(range(row, min(row + n, episode.stop))):
        m = j + 1
        if N_STEP_NEXT[t] == goal:
            return N_STEP_NEXT[t], reward + gamma**j, True, False, m
    last = row + m - 1
    return N_STEP_NEXT[last], reward, False, last == 7, m


def check_n_step_sample(buf: HindsightReplayBuffer) -> list[tuple[int, int]]:
    data, info = buf.sample(return_info=True)
    rows = torch.as_tensor(info["index"]).tolist()
    nxt = data["next"]
    seen = []
    for i, row in enumerate(rows):
        goal = int(data["desired_goal"][i])
        cell, reward, terminated, truncated, m = expected_n_step(row, goal)
        assert int(nxt["observation"][i]) == cell, (row, goal)
        assert float(nxt["reward"][i, 0]) == pytest.approx(reward), (row, goal)
        assert bool(nxt["terminated"][i, 0]) == terminated, (row, goal)
        assert bool(nxt["truncated"][i, 0]) == truncated, (row, goal)
        assert bool(nxt["done"][i, 0]) == (terminated or truncated)
        assert int(data["n_steps"][i, 0]) == m, (row, goal)
        assert int(data["observation"][i]) == N_STEP_NEXT[row] - 1  # the transition's own start is kept
        seen.append((row, goal))
    return seen


def test_n_step_targets_for_the_real_goal_by_hand():
    buf = n_step_buffer("future", k=0)
    seen = set(check_n_step_sample(buf))
    data, info = buf.sample(return_info=True)
    by_row = {int(r): i for i, r in enumerate(torch.as_tensor(info["index"]).tolist())}
    nxt = data["next"]
    # Written out: from row 2 the window reaches G at its third step; from row 3 at its second.
    assert (int(nxt["observation"][by_row[2]]), float(nxt["reward"][by_row[2], 0])) == (15, 0.25)
    assert int(data["n_steps"][by_row[2], 0]) == 3 and bool(nxt["terminated"][by_row[2], 0])
    assert (float(nxt["reward"][by_row[3], 0]), int(data["n_steps"][by_row[3], 0])) == (0.5, 2)
    # Row 0: three steps, no goal, bootstraps from cell 13.
    assert (int(nxt["observation"][by_row[0]]), int(data["n_steps"][by_row[0], 0])) == (13, 3)
    assert not bool(nxt["terminated"][by_row[0], 0])
    # Row 6: the episode is cut after row 7: two steps, truncated, from cell 23; never into episode C.
    assert (int(nxt["observation"][by_row[6]]), int(data["n_steps"][by_row[6], 0])) == (23, 2)
    assert bool(nxt["truncated"][by_row[6], 0]) and not bool(nxt["terminated"][by_row[6], 0])
    # Row 8: the running episode holds two stored steps: the window stops at the newest.
    assert (int(nxt["observation"][by_row[8]]), int(data["n_steps"][by_row[8], 0])) == (32, 2)
    assert {row for row, _ in seen} == set(range(10))


def test_n_step_targets_for_relabeled_goals_by_hand():
    """'episode' goals can lie before the transition: such a goal is never reached, and the window still stops at
    the episode's end. Every sampled item is checked against the table."""
    buf = n_step_buffer("episode", k=1000)
    seen = set()
    for _ in range(4):
        seen |= set(check_n_step_sample(buf))
    # A relabeled transition whose episode ends inside its window without reaching the goal (row 6, goal 21).
    assert (6, 21) in seen
    assert expected_n_step(6, 21) == (23, 0.0, False, True, 2)
    # And one that reaches a relabeled goal inside the window (row 5, goal 23: on its third step).
    assert (5, 23) in seen
    assert expected_n_step(5, 23) == (23, 0.25, True, False, 3)


def test_n_step_one_keeps_td0():
    buf = HindsightReplayBuffer(64, 1, 256, k=0, generator=torch.Generator().manual_seed(0))
    buf.extend(make_batch(N_STEP_NEXT, terminated=[t == 4 for t in range(10)], goal=15))
    data, info = buf.sample(return_info=True)
    assert (data["n_steps"] == 1).all()
    rows = torch.as_tensor(info["index"])
    assert (data["next", "observation"] == torch.tensor(N_STEP_NEXT)[rows]).all()


def test_n_step_must_be_positive():
    with pytest.raises(ValueError, match="n_step must be >= 1"):
        HindsightReplayBuffer(64, 1, 8, n_step=0)


# --- 10. goal_steps: how many steps on the stored episode reached each sample's goal (for the hindsight bound) --------
def expected_goal_steps(row: int, goal: int) -> int:
    """From the episode table above: k such that the step row + k - 1 of the same episode has next cell ``goal``
    (the episode's steps have distinct next cells, so the step is unique), 0 if none at or after ``row``."""
    episode = next(e for e in N_STEP_EPISODES if row in e)
    later = [t for t in range(row, episode.stop) if N_STEP_NEXT[t] == goal]
    return later[0] - row + 1 if later else 0


def test_goal_steps_for_the_real_goal_by_hand():
    """Episode A (rows 0-4) entered G = 15 at row 4: k = 5 - t. Episode B was cut by the time limit and C is still
    running: 0, they are not known to reach G."""
    buf = n_step_buffer("future", k=0, goal_steps=True)
    data, info = buf.sample(return_info=True)
    rows = torch.as_tensor(info["index"]).tolist()
    assert set(rows) == set(range(10))
    got = {row: int(data["goal_steps"][i, 0]) for i, row in enumerate(rows)}
    assert got == {0: 5, 1: 4, 2: 3, 3: 2, 4: 1, 5: 0, 6: 0, 7: 0, 8: 0, 9: 0}


@pytest.mark.parametrize("strategy", ["future", "final", "episode"])
def test_goal_steps_for_relabeled_goals_by_hand(strategy):
    """A relabeled goal taken from step t' >= t of the same episode is reached t' - t + 1 steps on, also when the
    n-step window ends before it (row 5, goal 23: k = 3; row 6 of episode B, goal 23: k = 2); a goal from before t
    ('episode') is not known to be reached: 0."""
    buf = n_step_buffer(strategy, k=1000, goal_steps=True)
    seen = set()
    for _ in range(4):
        data, info = buf.sample(return_info=True)
        for i, row in enumerate(torch.as_tensor(info["index"]).tolist()):
            goal = int(data["desired_goal"][i])
            assert int(data["goal_steps"][i, 0]) == expected_goal_steps(row, goal), (row, goal)
            seen.add((row, goal))
    if strategy != "final":
        assert (5, 23) in seen and expected_goal_steps(5, 23) == 3
    if strategy == "episode":
        assert (7, 21) in seen and expected_goal_steps(7, 21) == 0  # a goal behind the transition


def test_no_goal_steps_or_window_states_unless_asked_for():
    """Off (the default), samples carry no ``goal_steps`` and no ``window_observation``: nothing computes what no
    loss reads."""
    data = n_step_buffer("future", k=4).sample()
    assert "goal_steps" not in data.keys()
    assert "window_observation" not in data.keys()


# --- 11. window states: the state after each step of the n-step window (for the n_step_max targets) ---------------
@pytest.mark.parametrize("strategy", ["future", "final", "episode"])
def test_window_states_by_hand(strategy):
    """The first m entries of ``window_observation`` are the next cells of rows t..t+m-1 (m from the same walk as
    the n-step targets), also for a relabeled goal entered inside the window (row 5, goal 22: m = 2) and a window cut
    by the episode's end (row 7: m = 1)."""
    buf = n_step_buffer(strategy, k=3, window_states=True)
    seen = set()
    for _ in range(4):
        data, info = buf.sample(return_info=True)
        assert data["window_observation"].shape == (512, 3)
        for i, row in enumerate(torch.as_tensor(info["index"]).tolist()):
            goal = int(data["desired_goal"][i])
            m = expected_n_step(row, goal)[4]
            assert int(data["n_steps"][i, 0]) == m
            assert data["window_observation"][i, :m].tolist() == N_STEP_NEXT[row : row + m], (row, goal)
            seen.add((row, goal, m))
    assert (7, 15, 1) in seen  # cut by the time limit after one step
    if strategy != "final":
        assert (5, 22, 2) in seen  # a relabeled goal entered at the window's second step


def test_window_states_with_one_step_targets_are_the_next_states():
    buf = HindsightReplayBuffer(64, 1, 32, k=1, generator=torch.Generator().manual_seed(0), window_states=True)
    buf.extend(make_batch(**TWO_EPISODES))
    data = buf.sample()
    assert torch.equal(data["window_observation"], data["next", "observation"].unsqueeze(1))
