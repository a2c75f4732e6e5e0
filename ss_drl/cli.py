"""Entry points behind the ``ss-drl-train`` console script and scripts/train.py: Hydra wiring and one-line errors."""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from ss_drl.training.outputs import FAILED_FILE

_PACKAGE = Path(__file__).resolve().parent


def config_dir() -> Path:
    """The Hydra config directory: the copy installed with the package (``pip install .`` ships the checkout's
    ``conf/`` as ``ss_drl/conf``), else ``conf/`` of the checkout the package lies in (scripts/*.py, editable
    installs, PYTHONPATH), so that an edit to conf/*.yaml is seen there without reinstalling."""
    for candidate in (_PACKAGE / "conf", _PACKAGE.parent / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise FileNotFoundError(
        f"ss-drl: no Hydra configs: neither {_PACKAGE / 'conf'} (installed package) nor {_PACKAGE.parent / 'conf'} "
        "(checkout) holds config.yaml; reinstall ss-drl"
    )


class ValidateBeforeRun(Callback):
    """Hydra callback (``hydra.callbacks`` in conf/config.yaml): check the config before Hydra creates the run
    directory, so a refused run leaves nothing behind. Sweeps are checked per job instead (a refused job writes
    FAILED in its directory and the others go on), except that a new sweep is refused as a whole, before any job,
    when its directory already holds runs."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        from ss_drl.training.checkpoint import refuse_overwrite
        from ss_drl.training.config import ConfigError, validate_config

        run_dir = _resume_dir(config) or Path(config.hydra.run.dir)
        _refuse_on(lambda: (validate_config(config), refuse_overwrite(config, run_dir)), ConfigError)

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        from ss_drl.training.checkpoint import refuse_overwrite
        from ss_drl.training.config import ConfigError

        sweep_dir = Path(config.hydra.sweep.dir)
        jobs = sorted(p for p in sweep_dir.glob("*") if p.is_dir()) if sweep_dir.is_dir() else []
        _refuse_on(lambda: [refuse_overwrite(config, job, key="hydra.sweep.dir") for job in jobs], ConfigError)


def _refuse_on(check, error: type[Exception]) -> None:
    """Run ``check``; on ``error``, one line on stderr and exit 2, before Hydra writes anything."""
    try:
        check()
    except error as exc:
        print(f"ss-drl: config error: {exc}", file=sys.stderr)
        sys.exit(2)


def _resume_dir(cfg: DictConfig) -> Path | None:
    """The run directory that ``trainer.resume=<dir>`` names, if it names one."""
    resume = cfg.trainer.resume
    if isinstance(resume, str) and resume not in ("", "true", "false", "auto"):
        return Path(resume)
    return None


def _run_dir(cfg: DictConfig) -> Path:
    """The run directory: ``trainer.resume=<dir>``, else Hydra's (``hydra.run.dir``, or the job's in a sweep)."""
    return _resume_dir(cfg) or Path(HydraConfig.get().runtime.output_dir)


def _is_multirun() -> bool:
    from hydra.types import RunMode

    return HydraConfig.get().mode == RunMode.MULTIRUN


def _train(cfg: DictConfig):
    """Hydra's task function: one run, or one job of a sweep."""
    from ss_drl.training.config import ConfigError
    from ss_drl.training.trainer import TrainingInterrupted, train

    run_dir = _run_dir(cfg)
    try:
        summary = train(cfg, run_dir)
    except ConfigError as exc:
        return _fail(f"config error: {exc}", code=2)
    except TrainingInterrupted as exc:
        return _fail(str(exc), code=130)
    except (FloatingPointError, FileNotFoundError, ValueError) as exc:
        return _fail(f"{type(exc).__name__}: {exc} (run directory: {run_dir})", code=1)
    except Exception:  # noqa: BLE001
        if not _is_multirun():
            raise
        # In a sweep, one failing job must not take the others down: record it and go on.
        (run_dir / FAILED_FILE).write_text(traceback.format_exc())
        print(f"ss-drl: job failed, see {run_dir / FAILED_FILE}", file=sys.stderr)
        return None
    first = summary["first_goal_env_step"]
    print(
        f"{summary['experiment']} seed {summary['seed']}: {summary['episodes']} episodes, {summary['env_steps']} env "
        f"steps in {summary['wall_s']:.1f}s ({summary['env_steps_per_s']:.0f} steps/s); first goal at "
        f"{first if first is not None else 'never'}; greedy length {summary['final_eval_length']} "
        f"(optimal {summary['optimal_length']}); outputs in {run_dir}"
    )
    return summary["final_eval_length"]


def _fail(message: str, code: int):
    """One clear line on stderr. In a sweep the job is marked failed and the sweep goes on; alone, exit non-zero."""
    print(f"ss-drl: {message}", file=sys.stderr)
    if _is_multirun():
        out = Path(HydraConfig.get().runtime.output_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / FAILED_FILE).write_text(message + "\n")
        return None
    sys.exit(code)


def train_main() -> None:
    """``ss-drl-train +experiment=NAME [key=value ...]`` (also ``-m`` sweeps): what scripts/train.py runs."""
    try:
        conf = config_dir()
    except FileNotFoundError as exc:
        sys.exit(str(exc))
    hydra.main(config_path=str(conf), config_name="config", version_base="1.3")(_train)()
