"""Entry points behind scripts/*.py: Hydra wiring and clean one-line errors."""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from ss_drl.training.outputs import FAILED_FILE

CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "conf")


def _run_dir(cfg: DictConfig) -> Path:
    resume = cfg.trainer.resume
    if isinstance(resume, str) and resume not in ("", "true", "false"):
        return Path(resume)
    return Path(HydraConfig.get().runtime.output_dir)


def _is_multirun() -> bool:
    from hydra.types import RunMode

    return HydraConfig.get().mode == RunMode.MULTIRUN


@hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")
def _train(cfg: DictConfig):
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
    _train()
