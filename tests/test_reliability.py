"""Determinism, checkpoint/resume after SIGTERM, NaN detection."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers import ROOT, compose_cfg, wait_for

from ss_drl.training.outputs import CHECKPOINT_FILE, EPISODES_FILE, EVAL_FILE, SUMMARY_FILE, truncate_csv
from ss_drl.training.trainer import Trainer

SMALL = [
    "agent.learning_starts=100",
    "agent.batch_size=32",
    "agent.hidden=[32,32]",
    "agent.embed_dim=8",
    "trainer.eval_interval=250",
]


def rows_without_wall(path: Path) -> list[list[str]]:
    with path.open() as f:
        rows = list(csv.reader(f))
    if "wall_s" not in rows[0]:
        return rows
    i = rows[0].index("wall_s")
    return [r[:i] + r[i + 1 :] for r in rows]


@pytest.mark.slow
def test_same_seed_gives_identical_outputs(tmp_path):
    overrides = ["+experiment=easy_small_ss_her", "trainer.total_env_steps=1500", *SMALL]
    for name in ("a", "b"):
        Trainer(compose_cfg(*overrides), tmp_path / name).train()
    for file in (EPISODES_FILE, EVAL_FILE):
        a, b = rows_without_wall(tmp_path / "a" / file), rows_without_wall(tmp_path / "b" / file)
        assert len(a) > 3
        assert a == b
    # ... and a different seed gives a different run
    Trainer(compose_cfg(*overrides, "seed=1"), tmp_path / "c").train()
    assert rows_without_wall(tmp_path / "c" / EPISODES_FILE) != rows_without_wall(tmp_path / "a" / EPISODES_FILE)


def _train_cmd(run_dir: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        str(ROOT / "scripts" / "train.py"),
        "+experiment=easy_small_ss_her",
        "trainer.total_env_steps=4000",
        "trainer.checkpoint_interval=500",
        "env.max_steps=100",  # episodes end by the cut, whatever the agent does: several before the first checkpoint
        *SMALL,
        f"hydra.run.dir={run_dir}",
        *extra,
    ]


@pytest.mark.slow
@pytest.mark.parametrize("env", [(), ("env.slip=0.2",)], ids=["deterministic", "slip"])
def test_sigterm_then_resume_equals_uninterrupted_run(tmp_path, env):
    """SIGTERM writes a checkpoint and stops; the resumed run then equals an uninterrupted one, with stochastic moves
    too (the env's and the evaluation's generators are in the checkpoint)."""
    full, cut = tmp_path / "full", tmp_path / "cut"
    subprocess.run(_train_cmd(full, *env), check=True, capture_output=True, cwd=ROOT, timeout=600)

    # Output goes to files, not pipes: a child blocked on a full pipe would never reach its checkpoint.
    err_path = tmp_path / "cut.stderr"
    with err_path.open("w") as err_file:
        proc = subprocess.Popen(_train_cmd(cut, *env), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err_file, text=True)
        # The first checkpoint (at 500 of 4000 env steps) is written atomically, after the CSV rows are flushed:
        # once it exists the run is past its start-up (signal handlers installed) with 3500 steps still to go.
        wait_for((cut / CHECKPOINT_FILE).exists, "first checkpoint", proc, timeout_s=300)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            pytest.fail("the run did not stop within 120 s of SIGTERM")
    err = err_path.read_text()
    assert proc.returncode == 128 + signal.SIGTERM, f"exit {proc.returncode}: not the shell's code for SIGTERM (143)"
    # The one line says how to resume: the same command and trainer.resume=<run dir>, which is what follows.
    assert "SIGTERM received: checkpoint written at " in err, err
    assert err.strip().splitlines()[-1].endswith(f"resume it with the same command and trainer.resume={cut}"), err
    assert "Traceback" not in err, err
    assert (cut / CHECKPOINT_FILE).exists()
    assert not (cut / SUMMARY_FILE).exists()
    interrupted_at = torch.load(cut / CHECKPOINT_FILE, weights_only=False)["collector"]["env_steps"]
    assert 500 <= interrupted_at < 4000
    assert len(rows_without_wall(cut / EPISODES_FILE)) > 1  # the interrupted run flushed its episodes

    resumed = subprocess.run(
        _train_cmd(cut, *env, f"trainer.resume={cut}"), capture_output=True, text=True, cwd=ROOT, timeout=600
    )
    assert resumed.returncode == 0, resumed.stderr
    for file in (EPISODES_FILE, EVAL_FILE):
        assert rows_without_wall(cut / file) == rows_without_wall(full / file), file
        data = (cut / file).read_bytes()
        assert data.count(b"\r\n") == data.count(b"\n"), f"{file}: mixed line endings after resume"
    a = json.loads((full / SUMMARY_FILE).read_text())
    b = json.loads((cut / SUMMARY_FILE).read_text())
    keys = ("episodes", "env_steps", "first_goal_env_step", "final_eval_length", "completed")
    for key in (*keys, "learned_env_step", "last_quarter_within"):
        assert a[key] == b[key]
    assert b["slip"] == (0.2 if env else 0) and b["eval_episodes"] == (48 if env else 1)


def test_truncate_csv_keeps_the_rows_bytes(tmp_path):
    """Resume cuts episodes.csv/eval.csv back to the checkpoint: the rows it keeps must stay byte for byte as the
    csv module wrote them (\r\n), or the resumed run leaves a file of mixed line endings (a bug, fixed)."""
    path = tmp_path / "rows.csv"
    with path.open("w", newline="") as f:
        csv.writer(f).writerows([["a", "b"], [1, 2], [3, 4], [5, 6]])
    truncate_csv(path, 2)
    assert path.read_bytes() == b"a,b\r\n1,2\r\n3,4\r\n"
    with path.open("a", newline="") as f:
        csv.writer(f).writerow([7, 8])
    assert path.read_bytes() == b"a,b\r\n1,2\r\n3,4\r\n7,8\r\n"


def snapshot(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def test_resume_without_checkpoint_is_a_clear_error(tmp_path):
    """Refused before Hydra creates the run directory (it used to be left holding .hydra/ and cli.log)."""
    result = subprocess.run(
        _train_cmd(tmp_path / "none", "trainer.resume=true"), capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        f"ss-drl: config error: trainer.resume: no checkpoint to resume at {tmp_path / 'none' / CHECKPOINT_FILE}"
    ]
    assert not (tmp_path / "none").exists(), "a refused run left its run directory behind"


OLD_CHECKPOINT = (
    "trainer.resume: {path} was written before the learners were renamed (docs/migration.md): continue it with a "
    "checkout of 7ac5009, or start a new run"
)


@pytest.mark.slow
def test_a_checkpoint_from_before_the_learners_were_renamed_is_refused_on_resume(tmp_path):
    """A run directory written at 7ac5009 or before (its checkpoint has no format marker; its summary.json and CSVs
    are complete) is refused on trainer.resume=true, auto and <dir>: one line, exit 2, before Hydra writes its
    .hydra/ files, and the run's files stay byte for byte as they were. The trainer refuses it too."""
    from ss_drl.training.checkpoint import FORMAT, FORMAT_KEY
    from ss_drl.training.config import ConfigError

    run = tmp_path / "run"
    overrides = ["+experiment=easy_small_dqn_her", "trainer.total_env_steps=200", *SMALL]
    Trainer(compose_cfg(*overrides), run).train()
    state = torch.load(run / CHECKPOINT_FILE, weights_only=False)
    assert state[FORMAT_KEY] == FORMAT  # what this version writes
    del state[FORMAT_KEY]
    torch.save(state, run / CHECKPOINT_FILE)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text("seed: 0\n")  # Hydra's record of the run: a resume rewrites it
    before = snapshot(run)
    assert {SUMMARY_FILE, EPISODES_FILE, EVAL_FILE, CHECKPOINT_FILE} <= set(before)
    expected = "ss-drl: config error: " + OLD_CHECKPOINT.format(path=run / CHECKPOINT_FILE)
    cwd = tmp_path / "cwd"  # where Hydra would put outputs/<experiment>/... for trainer.resume=<dir>
    cwd.mkdir()
    command = [sys.executable, str(ROOT / "scripts" / "train.py"), *overrides, "trainer.total_env_steps=400"]
    for resume in (["trainer.resume=true", f"hydra.run.dir={run}"], ["trainer.resume=auto", f"hydra.run.dir={run}"],
                   [f"trainer.resume={run}"]):  # fmt: skip
        result = subprocess.run([*command, *resume], capture_output=True, text=True, cwd=cwd, timeout=300)
        assert result.returncode == 2, result.stderr
        assert result.stderr.strip().splitlines() == [expected], result.stderr
        assert snapshot(run) == before, f"{resume}: a refused resume changed the run"
        assert list(cwd.iterdir()) == [], f"{resume}: a refused resume left {list(cwd.iterdir())}"
    resumed = compose_cfg(*overrides, "trainer.total_env_steps=400", "trainer.resume=true")
    with pytest.raises(ConfigError) as refused:
        Trainer(resumed, run)
    assert str(refused.value) == OLD_CHECKPOINT.format(path=run / CHECKPOINT_FILE)
    assert snapshot(run) == before


def test_check_resume_refuses_what_cannot_be_continued(tmp_path):
    """The check that runs before anything is written: an old or unknown format, an unreadable checkpoint, another
    config, no checkpoint, one that lacks what the trainer reads; each one line naming trainer.resume. A checkpoint of
    this format with the same config (budgets aside) passes, and a new run (resume false) reads nothing."""
    from ss_drl.training.checkpoint import FORMAT, FORMAT_KEY, STATE_KEYS, check_resume, task_config
    from ss_drl.training.config import ConfigError

    cfg = compose_cfg("+experiment=easy_small_dqn_her", "trainer.resume=true")
    path = tmp_path / CHECKPOINT_FILE

    def refused(state) -> str:
        if isinstance(state, bytes):
            path.write_bytes(state)
        else:
            torch.save(state, path)
        with pytest.raises(ConfigError) as info:
            check_resume(cfg, tmp_path)
        message = str(info.value)
        assert message.startswith("trainer.resume: ") and "\n" not in message, message
        return message

    config = task_config(cfg)
    full = {FORMAT_KEY: FORMAT, **dict.fromkeys(STATE_KEYS), "config": config}  # what the trainer reads, all there
    assert refused({"config": config}) == OLD_CHECKPOINT.format(path=path)
    assert refused({FORMAT_KEY: 1, "config": config}) == OLD_CHECKPOINT.format(path=path)
    assert "format 3, which this version (format 2) cannot read" in refused({FORMAT_KEY: 3, "config": config})
    assert f"{path} cannot be read" in refused(b"not a checkpoint")
    # Read by torch but no checkpoint of any version: said so, not taken for one from before the renaming.
    assert refused([1, 2]) == f"trainer.resume: {path} holds a list, not a checkpoint"
    assert "config 'seed' differs" in refused({**full, "config": {**config, "seed": 1}})
    # Of this format but not what the trainer wrote: refused here, before Hydra rewrites the run's .hydra/ files (it
    # was a KeyError or AttributeError traceback in the job, after them).
    assert refused({k: v for k, v in full.items() if k != "agent"}) == (
        f"trainer.resume: {path} lacks agent: not a checkpoint this trainer wrote"
    )
    assert refused({**full, "config": "easy"}) == f"trainer.resume: {path} holds no config mapping; start the run anew"
    assert refused({k: v for k, v in full.items() if k != "evals"}) == (
        f"trainer.resume: {path} predates the list of evaluations; start the run anew"
    )
    other_budget = {**config, "trainer": {**config["trainer"], "total_env_steps": 1}}
    torch.save({**full, "config": other_budget}, path)
    check_resume(cfg, tmp_path)  # budgets may change on resume
    check_resume(compose_cfg("+experiment=easy_small_dqn_her"), tmp_path / "missing")  # a new run: nothing to read
    path.unlink()
    with pytest.raises(ConfigError, match="^trainer.resume: no checkpoint to resume at"):
        check_resume(cfg, tmp_path)


# --- a new run never overwrites another; trainer.resume=auto continues a run if it can, else starts it ---
def test_new_run_in_a_directory_holding_a_run_is_refused_and_touches_nothing(tmp_path):
    """Issue: a run started without trainer.resume in an existing run's directory deleted its CSV files and then
    overwrote its checkpoint. It is refused (exit 2, one line naming hydra.run.dir and the file) before Hydra
    writes its .hydra/ files, and the directory is left byte for byte as it was."""
    existing = tmp_path / "run"
    (existing / ".hydra").mkdir(parents=True)
    (existing / ".hydra" / "config.yaml").write_text("seed: 0\n")
    (existing / EPISODES_FILE).write_text("episode,return\n0,1.0\n")
    before = {p.name: p.read_bytes() for p in existing.rglob("*") if p.is_file()}
    result = subprocess.run(_train_cmd(existing), capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert result.returncode == 2, result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("ss-drl: config error: hydra.run.dir:"), last
    assert str(existing) in last and EPISODES_FILE in last and "trainer.resume" in last, last
    assert {p.name: p.read_bytes() for p in existing.rglob("*") if p.is_file()} == before


def test_the_trainer_refuses_a_directory_holding_a_run_unless_it_resumes(tmp_path):
    from ss_drl.training.checkpoint import refuse_overwrite, should_resume
    from ss_drl.training.config import ConfigError

    new, auto, resume = (
        compose_cfg("+experiment=easy_small_dqn_her", f"trainer.resume={r}") for r in ("false", "auto", "true")
    )
    refuse_overwrite(new, tmp_path / "missing")  # no directory, or one without a run's files: a new run may start
    (tmp_path / "cli.log").write_text("")
    refuse_overwrite(new, tmp_path)
    assert should_resume(auto, tmp_path) is False  # auto without a checkpoint: start the run
    for name in (SUMMARY_FILE, EVAL_FILE, CHECKPOINT_FILE):
        (tmp_path / name).write_text("")
        with pytest.raises(ConfigError, match=f"^hydra.run.dir: {tmp_path} already holds a run \\(.*{name}"):
            Trainer(new, tmp_path)
    refuse_overwrite(auto, tmp_path)  # continuing is what resume is for
    refuse_overwrite(resume, tmp_path)
    assert should_resume(auto, tmp_path) is True  # auto with a checkpoint: continue it
    # auto where a finished run lost its checkpoint would start anew over its results: refused
    (tmp_path / CHECKPOINT_FILE).unlink()
    with pytest.raises(ConfigError, match=f"^hydra.run.dir: {tmp_path} holds a finished run .* no {CHECKPOINT_FILE}"):
        refuse_overwrite(auto, tmp_path)
    (tmp_path / SUMMARY_FILE).unlink()
    refuse_overwrite(auto, tmp_path)  # a run cut before its first checkpoint: auto starts it anew
    assert should_resume(auto, tmp_path) is False


@pytest.mark.slow  # a training run
def test_nan_loss_stops_the_run_and_keeps_the_last_checkpoint(tmp_path, monkeypatch):
    cfg = compose_cfg(
        "+experiment=easy_small_dqn_her", "trainer.total_env_steps=2000", "trainer.checkpoint_interval=400", *SMALL
    )
    trainer = Trainer(cfg, tmp_path)
    network = trainer.agent.q_network
    original = network.forward
    calls = {"n": 0}

    def poisoned(observation, desired_goal):
        out = original(observation, desired_goal)
        if trainer.collector.env_steps >= 900 and torch.is_grad_enabled():
            calls.setdefault("first_update", trainer.agent.updates)  # the update whose loss turns NaN
            calls["n"] += 1
            return out * float("nan")
        return out

    monkeypatch.setattr(network, "forward", poisoned)
    with pytest.raises(FloatingPointError, match="non-finite") as stop:
        trainer.train()
    assert calls["n"] >= 1
    # The loss is read at the logging cadence, not per update: the run stops within one logging period, and the
    # message names the first update whose loss was not finite.
    assert f"non-finite DQN loss (nan) at update {calls['first_update']}" in str(stop.value)
    assert trainer.agent.updates - calls["first_update"] <= trainer.log_interval
    state = torch.load(tmp_path / CHECKPOINT_FILE, weights_only=False)
    # The last checkpoint is the one due at 800 (interval 400), at the end of that batch: before the poison at 900.
    assert 800 <= state["collector"]["env_steps"] < 900
    params = state["agent"]["loss"]
    assert all(torch.isfinite(v).all() for v in params.values() if v.is_floating_point())
