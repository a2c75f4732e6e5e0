"""The package as a user installs it: a wheel (``pip install .``) trains from any directory with the configs it ships,
and an editable install (``pip install -e .``) reads the checkout's conf/ live.

Fast and offline: the wheel is built without build isolation from a copy of the checkout, and each install goes into
a fresh venv without pip whose only link to the dependencies (torch, hydra, ...) is a .pth file naming this
interpreter's site-packages. A path in a .pth is put on sys.path but the .pth files inside it are not run, so this
environment's own editable install of ss_drl is not loaded there; the tests check where ss_drl is imported from.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from helpers import ROOT, TINY
from omegaconf import OmegaConf

from ss_drl.training.outputs import CHECKPOINT_FILE, EPISODES_FILE, EVAL_FILE, SUMMARY_FILE

pytestmark = pytest.mark.slow

#: What a checkout holds besides the sources: never copied into the build.
NOT_SOURCES = shutil.ignore_patterns(
    ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", "outputs", "multirun", "wandb", ".*_cache"
)


def run(cmd: list, cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    """Run ``cmd`` as a user's shell would: no PYTHONPATH pointing at the checkout."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{cmd} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def copy_checkout(dest: Path) -> Path:
    shutil.copytree(ROOT, dest, ignore=NOT_SOURCES)
    return dest


def make_venv(path: Path) -> Path:
    """A fresh venv that sees this interpreter's site-packages (the dependencies) through a .pth file."""
    run([sys.executable, "-m", "venv", "--without-pip", path], cwd=path.parent)
    python = path / "bin" / "python"
    purelib = run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=path).stdout.strip()
    deps = [p for p in [*site.getsitepackages(), site.getusersitepackages()] if Path(p).is_dir()]
    (Path(purelib) / "_ss_drl_test_deps.pth").write_text("\n".join(deps) + "\n")
    return python


def pip_install(python: Path, *args) -> None:
    # pip comes from this interpreter's site-packages (the .pth); --ignore-installed: the ss-drl that this
    # environment has must neither satisfy the request nor be uninstalled.
    pip = [python, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--ignore-installed"]
    run([*pip, *args], cwd=python.parent)


def imported_from(python: Path, cwd: Path) -> tuple[Path, Path]:
    out = run([python, "-c", "import ss_drl, ss_drl.cli; print(ss_drl.__file__); print(ss_drl.cli.config_dir())"], cwd)
    module, conf = out.stdout.strip().splitlines()[-2:]
    return Path(module), Path(conf)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    src = copy_checkout(tmp / "src")
    run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", tmp / "dist", src], tmp)
    (built,) = (tmp / "dist").glob("ss_drl-*.whl")
    return built


def test_wheel_holds_every_module_and_config(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "ss_drl").rglob("*.py")}
    configs = {"ss_drl/" + p.relative_to(ROOT).as_posix() for p in (ROOT / "conf").rglob("*.yaml")}
    mazes = {p.relative_to(ROOT).as_posix() for p in (ROOT / "ss_drl" / "mazes").glob("*.txt")}
    assert "ss_drl/conf/config.yaml" in configs and "ss_drl/conf/hydra/launcher/slurm.yaml" in configs
    missing = sorted((modules | configs | mazes) - names)
    assert not missing, f"the wheel lacks {missing} (a new subpackage must be listed in pyproject.toml)"
    assert not [n for n in names if n.split("/")[0] in ("tests", "scripts", "benchmarks", "conf")], sorted(names)
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    scripts = zipfile.ZipFile(wheel).read(entry_points).decode()
    for script in ("ss-drl-train = ss_drl.cli:train_main", "ss-drl-evaluate", "ss-drl-plot", "ss-drl-diagnose"):
        assert script in scripts, scripts


def test_installed_wheel_trains_evaluates_and_plots_from_another_directory(wheel, tmp_path):
    venv = tmp_path / "venv"
    python = make_venv(venv)
    pip_install(python, wheel)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    module, conf = imported_from(python, elsewhere)
    assert module.is_relative_to(venv), f"ss_drl imported from {module}, not from the installed wheel"
    assert conf.is_relative_to(venv) and (conf / "experiment" / "easy_small_ss_her.yaml").is_file(), conf

    proc = run([venv / "bin" / "ss-drl-train", "+experiment=easy_small_ss_her", *TINY], elsewhere)
    (run_dir,) = (elsewhere / "outputs" / "easy_small_ss_her" / "seed0").iterdir()  # the default layout, under cwd
    assert str(run_dir) in proc.stdout.strip().splitlines()[-1]
    for name in (EPISODES_FILE, EVAL_FILE, SUMMARY_FILE, CHECKPOINT_FILE, "smart_start.png"):
        assert (run_dir / name).is_file(), f"{name} missing in {run_dir}"
    summary = json.loads((run_dir / SUMMARY_FILE).read_text())
    assert summary["completed"] is True
    assert summary["env_steps"] == 300 and summary["method"] == "ss_her"
    assert summary["experiment"] == "easy_small_ss_her"
    assert summary["config"]["agent"]["hidden"] == [16, 16]
    sources = OmegaConf.load(run_dir / ".hydra" / "hydra.yaml").hydra.runtime.config_sources
    main = next(s for s in sources if s.provider == "main")
    assert Path(main.path).is_relative_to(venv), f"configs read from {main.path}, not from the installed package"

    proc = run([venv / "bin" / "ss-drl-evaluate", run_dir], elsewhere)
    assert "greedy accuracy:" in proc.stdout
    assert (run_dir / "greedy_policy.png").stat().st_size > 0
    plots = elsewhere / "plots"
    run([venv / "bin" / "ss-drl-plot", elsewhere / "outputs", "--bootstrap", "20", "--out", plots], elsewhere)
    assert "easy_small" in (plots / "results.md").read_text()
    run([venv / "bin" / "ss-drl-diagnose", run_dir], elsewhere)
    assert (run_dir / "diagnosis.json").stat().st_size > 0


def test_editable_install_reads_the_checkouts_conf(tmp_path):
    src = copy_checkout(tmp_path / "src")
    python = make_venv(tmp_path / "venv")
    pip_install(python, "--no-build-isolation", "-e", src)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    module, conf = imported_from(python, elsewhere)
    assert module == src / "ss_drl" / "__init__.py", f"ss_drl imported from {module}, not from the editable checkout"
    assert conf == src / "conf"

    # An edit to conf/*.yaml is seen without reinstalling.
    maze = src / "conf" / "maze" / "easy_small.yaml"
    text = maze.read_text()
    assert "\ntrainer:\n  total_env_steps: " in text
    maze.write_text(text.replace("\ntrainer:\n  total_env_steps: ", "\ntrainer:\n  total_env_steps: 4321  # ", 1))
    job = run([tmp_path / "venv" / "bin" / "ss-drl-train", "+experiment=easy_small_ss_her", "--cfg", "job"], elsewhere)
    assert OmegaConf.create(job.stdout).trainer.total_env_steps == 4321
