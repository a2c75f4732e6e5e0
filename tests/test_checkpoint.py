"""Checkpoints that survive damage (issue 49, point 4): the save keeps the checkpoint before the latest as
checkpoint.prev.pt, a crash at any step of the save leaves a readable one, and trainer.resume falls back to the
previous checkpoint (one warning line) when the latest cannot be read, identical from there to an uninterrupted run.
"""

from __future__ import annotations

import copy
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch
from helpers import ROOT, TINY, Crash, compose_cfg, crash_after_save, rows_without_wall_clock

from ss_drl.training import checkpoint as ckpt
from ss_drl.training.checkpoint import FORMAT, FORMAT_KEY, UnreadableCheckpoint, check_resume, resume_from, task_config
from ss_drl.training.config import ConfigError
from ss_drl.training.outputs import (
    CHECKPOINT_FILE,
    CHECKPOINT_PREV_FILE,
    EPISODES_FILE,
    EVAL_FILE,
    SUMMARY_FILE,
    TRAIN_FILE,
)
from ss_drl.training.trainer import Trainer

#: A run of 1200 env steps with a checkpoint every 300, on a tiny network.
RUN = [
    "+experiment=easy_small_ss_her",
    *(o for o in TINY if not o.startswith("trainer.total_env_steps=")),
    "trainer.total_env_steps=1200",
    "trainer.checkpoint_interval=300",
    "trainer.log_interval=20",  # several train.csv rows between checkpoints
    "env.max_steps=100",  # several episodes between checkpoints
]


def snapshot(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def state(n: int, config: dict | None = None) -> dict:
    """A checkpoint of this format with every key the trainer reads (:data:`ckpt.STATE_KEYS`), numbered ``n``."""
    return {
        FORMAT_KEY: FORMAT,
        **dict.fromkeys(ckpt.STATE_KEYS),
        "n": n,
        "collector": {"env_steps": 100 * n},
        "config": config or {},
    }


# --- the save's rotation --------------------------------------------------------------------------------------------
def test_save_keeps_the_previous_checkpoint(tmp_path):
    ckpt.save(state(1), tmp_path)
    assert not (tmp_path / CHECKPOINT_PREV_FILE).exists()  # the first checkpoint: nothing before it
    ckpt.save(state(2), tmp_path)
    assert ckpt.read(tmp_path / CHECKPOINT_FILE)["n"] == 2
    assert ckpt.read(tmp_path / CHECKPOINT_PREV_FILE)["n"] == 1
    ckpt.save(state(3), tmp_path)
    assert ckpt.read(tmp_path / CHECKPOINT_FILE)["n"] == 3
    assert ckpt.read(tmp_path / CHECKPOINT_PREV_FILE)["n"] == 2
    assert {p.name for p in tmp_path.iterdir()} == {CHECKPOINT_FILE, CHECKPOINT_PREV_FILE}  # no temp file left


@pytest.mark.parametrize("step", [1, 2, 3])
def test_a_crash_at_any_step_of_a_save_leaves_a_readable_checkpoint(tmp_path, monkeypatch, step):
    """Step 1 writes the temp file (cut half way), step 2 renames checkpoint.pt to checkpoint.prev.pt, step 3 the
    temp file to checkpoint.pt. After a crash in any of them, the checkpoint the run continues from is whole: the
    latest (2) before step 3, else the new one (3) would only be there had step 3 happened."""
    ckpt.save(state(1), tmp_path)
    ckpt.save(state(2), tmp_path)
    real_save, real_replace = torch.save, ckpt.os.replace
    calls = {"replace": 0}

    def save(obj, f, *args, **kwargs):
        if step == 1:
            real_save(obj, f, *args, **kwargs)
            truncate(Path(f))  # the kill came while the bytes were going out
            raise Crash
        real_save(obj, f, *args, **kwargs)

    def replace(src, dst):
        calls["replace"] += 1
        if calls["replace"] == step - 1:
            raise Crash
        real_replace(src, dst)

    monkeypatch.setattr(ckpt.torch, "save", save)
    monkeypatch.setattr(ckpt.os, "replace", replace)
    with pytest.raises(Crash):
        ckpt.save(state(3), tmp_path)
    monkeypatch.undo()
    resumption = resume_from(tmp_path)
    assert resumption.state["n"] == 2
    if step == 3:  # between the renames: checkpoint.pt is missing, checkpoint.prev.pt holds the latest
        assert not (tmp_path / CHECKPOINT_FILE).exists()
        assert resumption.path == tmp_path / CHECKPOINT_PREV_FILE
        assert resumption.warning == (
            f"trainer.resume: {tmp_path / CHECKPOINT_FILE} is missing; continuing from "
            f"{tmp_path / CHECKPOINT_PREV_FILE} (env step 200), the checkpoint before it"
        )
    else:
        assert resumption.path == tmp_path / CHECKPOINT_FILE and resumption.warning is None
        assert ckpt.read(tmp_path / CHECKPOINT_PREV_FILE)["n"] == 1
    # The next save (the resumed run's) completes the rotation; a temp file left over is replaced.
    ckpt.save(state(4), tmp_path, keep_previous=not resumption.fell_back)
    assert ckpt.read(tmp_path / CHECKPOINT_FILE)["n"] == 4
    assert ckpt.read(tmp_path / CHECKPOINT_PREV_FILE)["n"] == 2
    assert {p.name for p in tmp_path.iterdir()} == {CHECKPOINT_FILE, CHECKPOINT_PREV_FILE}


def test_a_damaged_checkpoint_never_replaces_the_previous_one(tmp_path):
    """A run that fell back past a damaged checkpoint.pt saves with keep_previous=False: the damaged file is
    overwritten, and checkpoint.prev.pt stays the good one, so the two are never two copies of a damaged file."""
    ckpt.save(state(1), tmp_path)
    ckpt.save(state(2), tmp_path)
    truncate(tmp_path / CHECKPOINT_FILE)
    prev = (tmp_path / CHECKPOINT_PREV_FILE).read_bytes()
    ckpt.save(state(3), tmp_path, keep_previous=False)
    assert ckpt.read(tmp_path / CHECKPOINT_FILE)["n"] == 3
    assert (tmp_path / CHECKPOINT_PREV_FILE).read_bytes() == prev


# --- which checkpoint a resume continues from ------------------------------------------------------------------------
def test_resume_from_falls_back_past_a_damaged_checkpoint_only(tmp_path, monkeypatch):
    path, prev = tmp_path / CHECKPOINT_FILE, tmp_path / CHECKPOINT_PREV_FILE
    cfg = compose_cfg("+experiment=easy_small_dqn_her", "trainer.resume=true")
    config = task_config(cfg)
    ckpt.save(state(1, config), tmp_path)
    ckpt.save(state(2, config), tmp_path)
    for mmap in (False, True):  # the trainer's load and check_resume's look decide alike
        assert resume_from(tmp_path, mmap=mmap).state["n"] == 2
    check_resume(cfg, tmp_path)

    # The latest truncated: the previous one, with one line naming both files and the reason.
    truncate(path)
    for mmap in (False, True):
        resumption = resume_from(tmp_path, mmap=mmap)
        assert (resumption.path, resumption.state["n"]) == (prev, 1)
        assert resumption.warning.startswith(f"trainer.resume: {path} cannot be read (RuntimeError: PytorchStream")
        assert resumption.warning.endswith(f"; continuing from {prev} (env step 100), the checkpoint before it")
        assert "\n" not in resumption.warning and "miniz" not in resumption.warning  # torch's advice is cut
    check_resume(cfg, tmp_path)  # a resume that falls back passes the check before the run

    # Both damaged: refused, naming both.
    good_prev = prev.read_bytes()
    prev.write_bytes(b"")
    with pytest.raises(UnreadableCheckpoint) as both:
        check_resume(cfg, tmp_path)
    assert str(both.value).startswith(f"trainer.resume: {path} cannot be read (RuntimeError: ")
    assert str(both.value).endswith(f", and {prev} cannot be read (EOFError: Ran out of input)")
    assert "\n" not in str(both.value)

    # Damaged and nothing before it.
    prev.unlink()
    with pytest.raises(UnreadableCheckpoint, match=f"no {CHECKPOINT_PREV_FILE} to fall back to$"):
        resume_from(tmp_path)

    # The latest is whole but of another format (written before the learners were renamed): refused, not passed
    # over for the one before it, even when that one is of this format.
    prev.write_bytes(good_prev)
    torch.save({"config": config}, path)
    with pytest.raises(ConfigError) as old:
        resume_from(tmp_path)
    assert str(old.value) == (
        f"trainer.resume: {path} was written before the learners were renamed (docs/migration.md): continue it with "
        "a checkout of 7ac5009, or start a new run"
    )
    assert not isinstance(old.value, UnreadableCheckpoint)

    # The latest damaged and the previous one of another format: refused for the previous one's format.
    truncate(path)
    torch.save({FORMAT_KEY: 3, "config": config}, prev)
    with pytest.raises(ConfigError, match=f", and {prev} has checkpoint format 3, which this version"):
        resume_from(tmp_path)

    # The latest whole but pickled by other code (a class it names is missing): refused, not passed over.
    module = types.ModuleType("ss_drl_gone_module")

    class Gone:
        pass

    Gone.__module__, Gone.__qualname__ = module.__name__, "Gone"
    module.Gone = Gone
    monkeypatch.setitem(sys.modules, module.__name__, module)
    torch.save({**state(3, config), "extra": Gone()}, path)
    monkeypatch.delitem(sys.modules, module.__name__)
    torch.save(state(2, config), prev)  # a good checkpoint.prev.pt beside it
    with pytest.raises(UnreadableCheckpoint) as other:
        resume_from(tmp_path)
    assert str(other.value) == (
        f"trainer.resume: {path} cannot be read (ModuleNotFoundError: No module named 'ss_drl_gone_module')"
    )
    assert not other.value.damaged

    # No checkpoint.pt (a save cut between its renames): the previous one; neither: refused as before.
    path.unlink()
    assert resume_from(tmp_path).warning.startswith(f"trainer.resume: {path} is missing; continuing from {prev}")
    assert ckpt.should_resume(cfg, tmp_path)
    prev.unlink()
    with pytest.raises(ConfigError, match=f"^trainer.resume: no checkpoint to resume at {path}$"):
        check_resume(cfg, tmp_path)


def test_evaluate_names_a_damaged_checkpoint_in_one_line(tmp_path, capsys):
    from ss_drl.evaluate import main

    ckpt.save(state(1), tmp_path)
    ckpt.save(state(2), tmp_path)
    truncate(tmp_path / CHECKPOINT_FILE)
    before = snapshot(tmp_path)
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"evaluate.py: error: {tmp_path / CHECKPOINT_FILE} cannot be read (RuntimeError: ")
    assert err[0].endswith(f"; trainer.resume=true continues the run from {CHECKPOINT_PREV_FILE}")
    assert snapshot(tmp_path) == before


# --- end to end ------------------------------------------------------------------------------------------------------
def _train_cmd(run_dir: Path, *extra: str) -> list[str]:
    return [sys.executable, str(ROOT / "scripts" / "train.py"), *RUN, f"hydra.run.dir={run_dir}", *extra]


def test_resume_with_both_checkpoints_damaged_is_refused_and_changes_nothing(tmp_path):
    """One line naming both files and their reasons, exit 2, before Hydra writes anything; the trainer refuses the
    same. (The files need not come from a run: the check reads nothing else.)"""
    run = tmp_path / "run"
    run.mkdir()
    config = task_config(compose_cfg(*RUN))
    torch.save(state(2, config), run / CHECKPOINT_FILE)
    truncate(run / CHECKPOINT_FILE)
    (run / CHECKPOINT_PREV_FILE).write_bytes(b"")
    (run / EPISODES_FILE).write_text("episode\r\n1\r\n")
    before = snapshot(run)
    result = subprocess.run(
        _train_cmd(run, "trainer.resume=true"), capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"ss-drl: config error: trainer.resume: {run / CHECKPOINT_FILE} cannot be read (")
    assert lines[0].endswith(f", and {run / CHECKPOINT_PREV_FILE} cannot be read (EOFError: Ran out of input)")
    assert "Traceback" not in result.stderr
    assert snapshot(run) == before
    with pytest.raises(UnreadableCheckpoint):
        Trainer(compose_cfg(*RUN, "trainer.resume=true"), run)
    assert snapshot(run) == before


def test_resume_with_a_budget_below_the_steps_run_is_refused_and_changes_nothing(tmp_path):
    """The audit of session 47 resumed a finished run of 1500 env steps with trainer.total_env_steps=500: it exited 0
    and rewrote checkpoint.pt and summary.json, whose config then said 500 beside 1500 env steps. Now: one line, exit
    2, nothing changed; the trainer refuses the same; a budget of at least the steps run passes."""
    run = tmp_path / "run"
    run.mkdir()
    torch.save(state(9, task_config(compose_cfg(*RUN))), run / CHECKPOINT_FILE)  # 900 env steps run
    before = snapshot(run)
    result = subprocess.run(
        _train_cmd(run, "trainer.resume=true", "trainer.total_env_steps=500"),
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        f"ss-drl: config error: trainer.total_env_steps: 500 is below the 900 env steps {run / CHECKPOINT_FILE} has "
        "run; continue it with a budget of at least 900"
    ]
    assert snapshot(run) == before
    with pytest.raises(ConfigError, match=r"^trainer.total_env_steps: 899 is below the 900 env steps "):
        Trainer(compose_cfg(*RUN, "trainer.resume=true", "trainer.total_env_steps=899"), run).train()
    assert snapshot(run) == before
    for budget in (900, 5000):
        check_resume(compose_cfg(*RUN, "trainer.resume=true", f"trainer.total_env_steps={budget}"), run)


@pytest.mark.slow  # two runs of 1200 env steps
def test_resume_past_a_truncated_checkpoint_equals_an_uninterrupted_run(tmp_path):
    """A run of 1200 env steps crashes right after its third checkpoint (about 900 env steps), whose file is then
    cut in half. trainer.resume=true warns in one line and continues from the one before (about 600): the CSVs are
    cut back to it, and eval.csv, episodes.csv and train.csv come out as an uninterrupted run's (wall-clock columns
    aside)."""
    full, cut = tmp_path / "full", tmp_path / "cut"
    Trainer(compose_cfg(*RUN), full).train()

    saves = crash_after_save(Trainer(compose_cfg(*RUN), cut), 3)
    assert len(saves) == 3 and saves[-1] < 1200
    prev_steps = ckpt.read(cut / CHECKPOINT_PREV_FILE)["collector"]["env_steps"]
    assert prev_steps == saves[1]
    truncate(cut / CHECKPOINT_FILE)
    assert len(rows_without_wall_clock(cut / EPISODES_FILE)) < len(rows_without_wall_clock(full / EPISODES_FILE))

    resumed = subprocess.run(
        _train_cmd(cut, "trainer.resume=true"), capture_output=True, text=True, cwd=ROOT, timeout=600
    )
    assert resumed.returncode == 0, resumed.stderr
    warnings = [line for line in resumed.stderr.splitlines() if "trainer.resume" in line]
    assert len(warnings) == 1, resumed.stderr
    assert warnings[0].startswith(f"ss-drl: warning: trainer.resume: {cut / CHECKPOINT_FILE} cannot be read (")
    assert warnings[0].endswith(
        f"; continuing from {cut / CHECKPOINT_PREV_FILE} (env step {prev_steps}), the checkpoint before it"
    )
    assert "Traceback" not in resumed.stderr
    for file in (EPISODES_FILE, EVAL_FILE, TRAIN_FILE):
        assert rows_without_wall_clock(cut / file) == rows_without_wall_clock(full / file), file
    assert (cut / SUMMARY_FILE).is_file()
    # The run's two checkpoints are whole again: the damaged file was overwritten, not kept as the previous one.
    final, before_final = ckpt.read(cut / CHECKPOINT_FILE), ckpt.read(cut / CHECKPOINT_PREV_FILE)
    assert final["collector"]["env_steps"] == 1200
    assert prev_steps < before_final["collector"]["env_steps"] <= 1200


# --- a run written before a config key was added --------------------------------------------------------------------
def test_a_run_written_before_greedy_path_resumes_as_it_ran(tmp_path):
    """A checkpoint whose config lacks ``smart_start.greedy_path`` (written before the option existed) resumes with it
    off, as that run ran, and equals an uninterrupted run; resuming it with the option on is refused in one line."""
    full, cut = tmp_path / "full", tmp_path / "cut"
    Trainer(compose_cfg(*RUN), full).train()
    crash_after_save(Trainer(compose_cfg(*RUN), cut), 2)
    for name in (CHECKPOINT_FILE, CHECKPOINT_PREV_FILE):
        saved = ckpt.read(cut / name)
        del saved["config"]["smart_start"]["greedy_path"]
        torch.save(saved, cut / name)
    with pytest.raises(ConfigError, match=r"^trainer.resume: config 'smart_start' differs from the checkpoint's"):
        Trainer(compose_cfg(*RUN, "trainer.resume=true", "smart_start.greedy_path=true"), cut).train()
    Trainer(compose_cfg(*RUN, "trainer.resume=true"), cut).train()
    for file in (EPISODES_FILE, EVAL_FILE, TRAIN_FILE):
        assert rows_without_wall_clock(cut / file) == rows_without_wall_clock(full / file), file


def test_a_finished_run_from_before_the_evaluation_rng_resumes_to_its_summary(tmp_path):
    """A checkpoint written before evaluations rolled out in the env holds no ``eval_rng`` nor ``last_success_rate``.
    Resuming such a finished run with its own budget (``trainer.resume=auto`` over an old sweep does) ran no
    evaluation and crashed writing the summary (``round(None)``; found by a session-47 reading): the last evaluation's
    success, one deterministic episode then, is its success rate."""
    run = tmp_path / "run"
    first = Trainer(compose_cfg(*RUN), run).train()
    for name in (CHECKPOINT_FILE, CHECKPOINT_PREV_FILE):
        saved = ckpt.read(run / name)
        del saved["eval_rng"], saved["last_success_rate"]
        torch.save(saved, run / name)
    again = Trainer(compose_cfg(*RUN, "trainer.resume=true"), run).train()
    assert again["final_eval_success_rate"] == first["final_eval_success_rate"] in (0.0, 1.0)
    assert again["learned_env_step"] == first["learned_env_step"]


@pytest.mark.parametrize("experiment", ["easy_ss_her", "easy_ss_her_bounded", "easy_tabular_ss", "medium_dqn"])
def test_a_config_from_before_every_added_key_is_compatible_with_the_settings_it_ran(experiment):
    """A checkpoint of this format written before any of :data:`ckpt.ADDED_KEYS` existed (its config without them)
    resumes under today's config of the same experiment wherever today's values are those the run had; a value it
    did not have is refused. Before session 47 only ``smart_start.greedy_path`` was filled in, so a format-2 run older
    than the exploration options could not be resumed at all."""
    overrides = (
        [f"+experiment={experiment}", "smart_start=on"] if "bounded" in experiment else [f"+experiment={experiment}"]
    )
    current = task_config(compose_cfg(*overrides))
    saved = copy.deepcopy(current)
    removed = 0
    for section, key in ckpt.ADDED_KEYS:
        if key in (saved.get(section) or {}):
            assert current[section][key] == ckpt.ADDED_KEYS[section, key], (section, key)
            del saved[section][key]
            removed += 1
    assert removed >= (2 if experiment == "easy_tabular_ss" else 9)
    ckpt.check_compatible(saved, current)
    if "smart_start" in current and "select" in current["smart_start"]:
        changed = copy.deepcopy(current)
        changed["smart_start"]["explore"] = "frontier"
        with pytest.raises(ConfigError, match=r"^trainer.resume: config 'smart_start' differs"):
            ckpt.check_compatible(saved, changed)
