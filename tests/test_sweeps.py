"""Hydra multirun through the joblib launcher and through hydra-submitit-launcher (its local executor, and the SLURM
config up to sbatch), failure isolation, W&B that never blocks training and needs no network."""

from __future__ import annotations

import ipaddress
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import pytest
from helpers import ROOT, TINY, compose_cfg, wait_for
from omegaconf import OmegaConf

from ss_drl.training.outputs import CHECKPOINT_FILE, EPISODES_FILE, FAILED_FILE, SUMMARY_FILE
from ss_drl.training.trainer import Trainer


def sweep(sweep_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``scripts/train.py -m`` over easy_small DQN+HER with a tiny budget; returns the finished process."""
    return subprocess.run(
        [
            sys.executable,
            "scripts/train.py",
            "-m",
            "+experiment=easy_small_dqn_her",
            *overrides,
            *TINY,
            f"hydra.sweep.dir={sweep_dir}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )


def check_sweep(sweep_dir: Path, names: dict[str, float], launcher: str) -> list[Path]:
    """The sweep layout ``<sweep dir>/<num>_<experiment>_seed<seed>/`` with one directory per job, each run by
    ``launcher``; the gamma=1.5 jobs failed validation and wrote FAILED, the others completed. Returns the job dirs."""
    jobs = sorted(p for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert [j.name for j in jobs] == sorted(names)
    for job in jobs:
        hydra_cfg = OmegaConf.load(job / ".hydra" / "hydra.yaml").hydra
        assert hydra_cfg.launcher._target_ == launcher
        if names[job.name] > 1:
            assert not (job / SUMMARY_FILE).exists() and not (job / EPISODES_FILE).exists()
            assert "agent.gamma" in (job / FAILED_FILE).read_text()
        else:
            assert not (job / FAILED_FILE).exists()
            summary = json.loads((job / SUMMARY_FILE).read_text())
            assert summary["completed"] is True
            assert job.name.endswith(f"_seed{summary['seed']}")
    return jobs


def check_plot_skips_failed(sweep_dir: Path, failed: int) -> None:
    plot = subprocess.run(
        [sys.executable, "scripts/plot.py", str(sweep_dir), "--bootstrap", "50"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert plot.returncode == 0, plot.stderr
    assert plot.stderr.count("skipping") == failed, plot.stderr
    assert (sweep_dir / "plots" / "results.md").exists()


@pytest.mark.slow
def test_joblib_multirun_isolates_a_failing_job_and_plot_skips_it(tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = sweep(sweep_dir, "seed=0,1", "agent.gamma=0.9,1.5")  # the gamma=1.5 jobs fail validation
    # The others run to their end; then one line names the failed jobs, and the sweep exits 1 (it exited 0 before).
    assert result.returncode == 1, result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        "ss-drl: 2 of 4 jobs failed (1_easy_small_dqn_her_seed0, 3_easy_small_dqn_her_seed1): see FAILED in each"
    )
    # The joblib launcher (conf/hydra/launcher/local.yaml) ran the jobs in parallel worker processes.
    assert "Joblib.Parallel(n_jobs=-1" in result.stdout and "is launching 4 jobs" in result.stdout, result.stdout
    names = {"0_easy_small_dqn_her_seed0": 0.9, "1_easy_small_dqn_her_seed0": 1.5}
    names |= {"2_easy_small_dqn_her_seed1": 0.9, "3_easy_small_dqn_her_seed1": 1.5}
    jobs = check_sweep(sweep_dir, names, "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher")
    done = [j for j in jobs if (j / SUMMARY_FILE).exists()]
    assert {json.loads((j / SUMMARY_FILE).read_text())["seed"] for j in done} == {0, 1}
    check_plot_skips_failed(sweep_dir, failed=2)


def rows(path: Path) -> list[str]:
    return path.read_text().splitlines()


@pytest.mark.slow
def test_resume_auto_restarts_a_sweep_and_a_new_sweep_never_overwrites_one(tmp_path):
    """A sweep cut short (here: seed 0 run to 200 env steps of 400, seed 1 never started) is restarted with
    ``trainer.resume=auto`` in the same sweep directory: seed 0 continues from its checkpoint, keeping its rows,
    and seed 1 starts. A new sweep (``trainer.resume`` false) into that directory is refused as a whole, before any
    job, and leaves it byte for byte as it was."""
    sweep_dir = tmp_path / "sweep"
    budgetless = [o for o in TINY if not o.startswith("trainer.total_env_steps=")] + ["env.max_steps=50"]

    def run(*overrides: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "scripts/train.py", "-m", "+experiment=easy_small_dqn_her", *budgetless, *overrides,
             f"hydra.sweep.dir={sweep_dir}"],
            cwd=ROOT, capture_output=True, text=True, timeout=600,
        )  # fmt: skip

    cut = run("seed=0", "trainer.total_env_steps=200")
    assert cut.returncode == 0, cut.stderr
    seed0 = sweep_dir / "0_easy_small_dqn_her_seed0"
    first_rows = rows(seed0 / EPISODES_FILE)
    assert json.loads((seed0 / SUMMARY_FILE).read_text())["env_steps"] == 200

    # A job stopped by SIGTERM in a sweep writes FAILED with its message; the restart replaces it.
    (seed0 / FAILED_FILE).write_text("SIGTERM received: checkpoint written at 200 env steps\n")
    restarted = run("seed=0,1", "trainer.total_env_steps=400", "trainer.resume=auto")
    assert restarted.returncode == 0, restarted.stderr
    seed1 = sweep_dir / "1_easy_small_dqn_her_seed1"
    for job in (seed0, seed1):
        assert not (job / FAILED_FILE).exists(), (job / FAILED_FILE).read_text()
        summary = json.loads((job / SUMMARY_FILE).read_text())
        assert (summary["completed"], summary["env_steps"]) == (True, 400), job.name
    resumed_rows = rows(seed0 / EPISODES_FILE)
    assert resumed_rows[: len(first_rows)] == first_rows and len(resumed_rows) > len(first_rows)
    assert rows(seed1 / EPISODES_FILE)[1].startswith("1,")  # seed 1 started anew, at its first episode
    check_plot_skips_failed(sweep_dir, failed=0)  # both jobs count as runs

    before = {p.relative_to(sweep_dir).as_posix(): p.read_bytes() for p in sweep_dir.rglob("*") if p.is_file()}
    refused = run("seed=0,1", "trainer.total_env_steps=400")
    assert refused.returncode == 2, refused.stderr
    last = refused.stderr.strip().splitlines()[-1]
    assert last.startswith("ss-drl: config error: hydra.sweep.dir:") and "trainer.resume" in last, last
    after = {p.relative_to(sweep_dir).as_posix(): p.read_bytes() for p in sweep_dir.rglob("*") if p.is_file()}
    assert after == before, "a refused sweep changed the sweep directory"


def session_processes(sid: int) -> list[int]:
    """The live processes of session ``sid`` (field 6 of /proc/<pid>/stat), zombies aside."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended while we looked
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            pids.append(int(stat.parent.name))
    return pids


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads sessions from /proc")
def test_sigterm_stops_a_joblib_sweep_without_leaving_workers_or_starting_jobs(tmp_path):
    """SIGTERM to a sweep's process group (a batch scheduler, ``kill -- -PGID``): each running job writes its checkpoint
    and FAILED, and then no process is left. Before the fix, the joblib workers outlived the killed parent and ran the
    queued job to its end."""
    sweep_dir = tmp_path / "sweep"
    budgetless = [o for o in TINY if not o.startswith("trainer.total_env_steps=")]
    cmd = [sys.executable, "scripts/train.py", "-m", "+experiment=easy_small_dqn_her", "seed=0,1,2", *budgetless,
           "trainer.total_env_steps=200000", "trainer.checkpoint_interval=200", "env.max_steps=50",
           "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep_dir}"]  # fmt: skip
    jobs = [sweep_dir / f"{i}_easy_small_dqn_her_seed{i}" for i in range(3)]
    with (tmp_path / "out").open("w") as out:  # files, not pipes: a child blocked on a full pipe never checkpoints
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            both = lambda: all((job / CHECKPOINT_FILE).exists() for job in jobs[:2])  # noqa: E731
            wait_for(both, "a checkpoint in both running jobs", proc, timeout_s=300)
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=120)
            deadline = time.monotonic() + 120
            while session_processes(proc.pid) and time.monotonic() < deadline:
                time.sleep(0.5)
            left = session_processes(proc.pid)
        finally:
            for pid in session_processes(proc.pid):
                os.kill(pid, signal.SIGKILL)
    assert not left, f"processes {left} still ran 120 s after the sweep was sent SIGTERM"
    for job in jobs[:2]:
        failed = (job / FAILED_FILE).read_text()
        assert "SIGTERM received: checkpoint written" in failed, job.name
        assert failed.strip().endswith(
            f"; or the whole sweep: the same command with trainer.resume=auto hydra.sweep.dir={sweep_dir}"
        ), failed
        assert (job / CHECKPOINT_FILE).exists() and not (job / SUMMARY_FILE).exists(), job.name
    assert not (jobs[2] / SUMMARY_FILE).exists(), "the queued job ran after the sweep was stopped"


@pytest.mark.slow
def test_a_resumed_sweep_holding_a_checkpoint_from_before_the_rename_is_refused(tmp_path):
    """A sweep directory whose job holds a checkpoint written at 7ac5009 or before (no format marker): restarting
    the sweep with trainer.resume=auto is refused as a whole, before any job, with one line, and leaves the sweep
    directory as it was."""
    import torch

    from ss_drl.training.outputs import CHECKPOINT_FILE

    sweep_dir = tmp_path / "sweep"
    job = sweep_dir / "0_easy_small_dqn_her_seed0"
    job.mkdir(parents=True)
    torch.save({"config": {"method": "dqn_her"}, "evals": []}, job / CHECKPOINT_FILE)
    (job / EPISODES_FILE).write_text("episode\n")
    before = {p.relative_to(sweep_dir).as_posix(): p.read_bytes() for p in sweep_dir.rglob("*") if p.is_file()}
    result = sweep(sweep_dir, "seed=0,1", "trainer.resume=auto")
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        f"ss-drl: config error: trainer.resume: {job / CHECKPOINT_FILE} was written before the learners were renamed "
        "(docs/migration.md): continue it with a checkout of 7ac5009, or start a new run"
    ]
    after = {p.relative_to(sweep_dir).as_posix(): p.read_bytes() for p in sweep_dir.rglob("*") if p.is_file()}
    assert after == before and sorted(p.name for p in sweep_dir.iterdir()) == [job.name]


@pytest.mark.slow
def test_submitit_local_multirun_isolates_a_failing_job(tmp_path):
    """The SLURM launcher's code path (hydra-submitit-launcher: pickled jobs, one process each, results collected
    back) through its local executor: the same layout and failure isolation as the joblib sweeps."""
    sweep_dir = tmp_path / "sweep"
    result = sweep(sweep_dir, "hydra/launcher=submitit_local", "seed=0", "agent.gamma=0.9,1.5")
    assert result.returncode == 1, result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith("ss-drl: 1 of 2 jobs failed (1_easy_small_dqn_her_seed0)")
    target = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"
    names = {"0_easy_small_dqn_her_seed0": 0.9, "1_easy_small_dqn_her_seed0": 1.5}
    jobs = check_sweep(sweep_dir, names, target)
    # Each job ran in its own submitit process, which ran the job and pickled its result back.
    submitit_ids = {OmegaConf.load(j / ".hydra" / "hydra.yaml").hydra.job.id for j in jobs}
    assert len(submitit_ids) == 2
    for job_id in submitit_ids:
        assert (sweep_dir / ".submitit" / job_id / f"{job_id}_0_result.pkl").is_file(), job_id
    check_plot_skips_failed(sweep_dir, failed=1)


def test_slurm_launcher_config_submits_an_sbatch_array(tmp_path, monkeypatch):
    """conf/hydra/launcher/slurm.yaml through the plugin's own launch code, on a machine with fake srun/sbatch:
    the config composes, submitit accepts its parameters, and the sbatch script is a job array that runs each job
    under this interpreter with the configured limits."""
    import submitit.slurm.slurm as submitit_slurm
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from ss_drl.cli import _train

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    script = tmp_path / "submitted.sh"
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 0\n")
    (bin_dir / "sbatch").write_text(f'#!/bin/sh\ncp "$1" {script}\necho "Submitted batch job 4242"\n')
    for tool in bin_dir.iterdir():
        tool.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")

    class Submitted(Exception):
        pass

    def results(job):  # the launcher waits for the jobs' results: stop there, sbatch has run
        raise Submitted(job.job_id)

    monkeypatch.setattr(submitit_slurm.SlurmJob, "results", results)
    sweep_dir = tmp_path / "sweep"
    overrides = ["hydra/launcher=slurm", "hydra.launcher.partition=debug", f"hydra.sweep.dir={sweep_dir}"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=easy_small_dqn_her", *overrides], return_hydra_config=True)
    launcher = instantiate(cfg.hydra.launcher)
    assert type(launcher).__name__ == "SlurmLauncher"
    launcher.setup(hydra_context=None, task_function=_train, config=cfg)
    with pytest.raises(Submitted, match="4242_0"):
        launcher.launch([["seed=0"], ["seed=1"]], initial_job_idx=0)

    sbatch = script.read_text()
    for line in (
        "#SBATCH --array=0-1%2",  # two jobs, at most min(array_parallelism, 2) at once
        "#SBATCH --partition=debug",
        "#SBATCH --time=240",
        "#SBATCH --mem=4GB",
        "#SBATCH --cpus-per-task=1",
        "#SBATCH --ntasks-per-node=1",
        f"#SBATCH --output={sweep_dir}/.submitit/%A_%a/%A_%a_0_log.out",
    ):
        assert line in sbatch.splitlines(), f"{line!r} not in\n{sbatch}"
    assert f"{sys.executable} -u -m submitit.core._submit" in sbatch
    for task in (0, 1):
        assert (sweep_dir / ".submitit" / f"4242_{task}" / f"4242_{task}_submitted.pkl").is_file()


def _cfg(*overrides):
    return compose_cfg("+experiment=easy_small_dqn_her", *TINY, *overrides)


class NoNetwork:
    """Blocks and records every connection that leaves this machine: in this process at ``socket.connect``, and in
    child processes (wandb-core) through HTTP(S)/ALL proxy variables that point at a local listener which records
    and drops each connection."""

    def __init__(self, monkeypatch):
        self.blocked: list = []
        self.proxied = 0
        self._server = socket.create_server(("127.0.0.1", 0))
        self._server.settimeout(0.2)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()
        proxy = f"http://127.0.0.1:{self._server.getsockname()[1]}"
        for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
            monkeypatch.setenv(name, proxy)
        for name in ("NO_PROXY", "no_proxy"):
            monkeypatch.delenv(name, raising=False)
        real_connect = socket.socket.connect

        def connect(sock, address):
            if sock.family == socket.AF_UNIX or self._is_local(address):
                return real_connect(sock, address)
            self.blocked.append(address)
            raise OSError(f"network blocked by the test: connect to {address}")

        monkeypatch.setattr(socket.socket, "connect", connect)

    @staticmethod
    def _is_local(address) -> bool:
        host = address[0] if isinstance(address, tuple) else address
        if host == "localhost":
            return True
        try:
            return ipaddress.ip_address(host).is_loopback
        except ValueError:
            return False

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.proxied += 1
            conn.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._server.close()


@pytest.fixture
def no_network(monkeypatch):
    guard = NoNetwork(monkeypatch)
    yield guard
    guard.close()


def test_no_network_guard_blocks_and_records(no_network):
    with pytest.raises(OSError, match="network blocked"):
        socket.create_connection(("192.0.2.1", 443), timeout=1)  # TEST-NET-1: a remote address
    assert no_network.blocked == [("192.0.2.1", 443)]
    with socket.create_connection(("127.0.0.1", int(os.environ["HTTPS_PROXY"].rsplit(":", 1)[1])), timeout=5):
        pass
    no_network.close()
    assert no_network.proxied == 1


@pytest.mark.slow  # a training run
def test_wandb_offline_needs_no_network(tmp_path, monkeypatch, no_network):
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # 50-step episodes: several end within the 300 steps whatever the agent does, so train/return is logged.
        cfg = _cfg("logger=wandb", "logger.mode=offline", "env.max_steps=50")
        summary = Trainer(cfg, tmp_path / "run").train()
    assert summary["completed"]
    assert not [w for w in caught if "W&B is off" in str(w.message)], "wandb did not start"
    no_network.close()
    assert no_network.blocked == [] and no_network.proxied == 0, "W&B offline tried to reach the network"
    # The offline run holds the logged metrics (its record log names each metric key), ready for `wandb sync`.
    (record_log,) = (tmp_path / "run").glob("wandb/offline-run-*/run-*.wandb")
    records = record_log.read_bytes()
    for key in ("train/return", "train/length", "train/loss", "eval/length", "eval/greedy_accuracy"):
        assert key.encode() in records, f"{key} not in {record_log}"


@pytest.mark.slow  # a training run
def test_failing_wandb_init_falls_back_to_csv(tmp_path, monkeypatch):
    import wandb

    def broken_init(*args, **kwargs):
        raise RuntimeError("no W&B here")

    monkeypatch.setattr(wandb, "init", broken_init)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = Trainer(_cfg("logger=wandb", "logger.mode=online"), tmp_path).train()
    assert summary["completed"]
    assert (tmp_path / EPISODES_FILE).exists()
    assert [w for w in caught if "W&B is off" in str(w.message)]


def wandb_init_calls(tmp_path, monkeypatch, cfg) -> list[dict]:
    """The keyword arguments of each ``wandb.init`` call a RunLogger of ``cfg`` makes (the recording init then fails,
    so no W&B run starts)."""
    import wandb

    from ss_drl.training.outputs import RunLogger

    calls = []

    def init(**kwargs):
        calls.append(kwargs)
        raise RuntimeError("recorded")

    monkeypatch.setattr(wandb, "init", init)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        RunLogger(tmp_path, cfg, OmegaConf.to_container(cfg, resolve=True)).close()
    return calls


@pytest.mark.parametrize(
    ("overrides", "group", "label"),
    [
        (["+experiment=easy_small_ss_her"], "easy_small_ss_her", "ss_her"),
        (["+experiment=easy_small_ss_her_bounded"], "easy_small_ss_her_bounded", "ss_her_bounded"),
        (["+experiment=easy_small_ss_her", "agent=dqn_bounded"], "easy_small_ss_her[ss_her_bounded]", "ss_her_bounded"),
        (["+experiment=easy_small_dqn_her_bounded", "agent=dqn"], "easy_small_dqn_her_bounded[dqn_her]", "dqn_her"),
        (["+experiment=easy_small_ss_her", "logger.group=mine"], "mine", "ss_her"),
    ],
)
def test_wandb_groups_runs_by_what_they_ran(tmp_path, monkeypatch, overrides, group, label):
    """The W&B group is the experiment name when it names the method that ran, else the experiment name with the
    method label (an agent override never files one learner's runs under the other's name), and the job type the
    method label (ss_drl/methods.py); logger.group, when set, is the group."""
    cfg = compose_cfg(*overrides, "logger=wandb", "logger.mode=offline")
    (call,) = wandb_init_calls(tmp_path, monkeypatch, cfg)
    assert (call["group"], call["job_type"]) == (group, label)
    assert call["name"] == f"{cfg.experiment}-seed0"


@pytest.mark.parametrize(
    ("env_mode", "overrides", "mode"),
    [
        (None, [], "offline"),
        ("disabled", [], "disabled"),
        ("online", [], "online"),
        ("disabled", ["logger.mode=offline"], "offline"),
    ],
)
def test_wandb_mode_is_wandb_mode_from_the_environment_unless_logger_mode_is_set(
    tmp_path, monkeypatch, env_mode, overrides, mode
):
    """``logger=wandb`` takes its mode from ``$WANDB_MODE``, else offline; ``logger.mode`` on the command line wins.
    (A bug, fixed: the config's offline was passed to wandb.init and silently beat ``WANDB_MODE=disabled``.)"""
    if env_mode is None:
        monkeypatch.delenv("WANDB_MODE", raising=False)
    else:
        monkeypatch.setenv("WANDB_MODE", env_mode)
    cfg = compose_cfg("+experiment=easy_small_ss_her", "logger=wandb", *overrides)
    calls = wandb_init_calls(tmp_path, monkeypatch, cfg)
    assert [call["mode"] for call in calls] == ([] if mode == "disabled" else [mode])
    assert OmegaConf.to_container(cfg, resolve=True)["logger"]["mode"] == mode
