"""Entry points behind the ``ss-drl-train`` console script and scripts/train.py: Hydra wiring and one-line errors."""

from __future__ import annotations

import difflib
import os
import signal
import sys
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

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
    directory, so a refused run leaves nothing behind: the values, a run directory another run's outputs hold, and
    on ``trainer.resume`` the checkpoint (there, readable, of this format, written with the same config). Sweeps are
    checked per job instead (a refused job writes FAILED in its directory and the others go on), except that a new
    sweep is refused as a whole, before any job, when its directory already holds runs, and a resumed one when a job
    holds a checkpoint written before the learners were renamed."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        from ss_drl.training.checkpoint import check_resume, refuse_overwrite
        from ss_drl.training.config import ConfigError, validate_config

        global _created
        _created = _first_missing(Path(config.hydra.run.dir))
        run_dir = _resume_dir(config) or Path(config.hydra.run.dir)
        _refuse_on(
            lambda: (validate_config(config), refuse_overwrite(config, run_dir), check_resume(config, run_dir)),
            ConfigError,
        )

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        from ss_drl.training.checkpoint import refuse_overwrite, resumes
        from ss_drl.training.config import ConfigError

        sweep_dir = Path(config.hydra.sweep.dir)
        jobs = sorted(p for p in sweep_dir.glob("*") if p.is_dir()) if sweep_dir.is_dir() else []

        def check() -> None:
            for job in jobs:
                refuse_overwrite(config, job, key="hydra.sweep.dir")
                if resumes(config.trainer.resume):
                    _refuse_old_checkpoint(job)

        _refuse_on(check, ConfigError)

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        """A sweep some of whose jobs failed (each wrote ``FAILED``; a job clears its own when it starts) ends with one
        line naming them and exit code 1, after the others ran to their end, so that a script sees it."""
        sweep_dir = Path(config.hydra.sweep.dir)
        jobs = sorted(p for p in sweep_dir.glob("*") if p.is_dir() and not p.name.startswith("."))
        failed = [job for job in jobs if (job / FAILED_FILE).is_file()]
        if failed:
            names = ", ".join(job.name for job in failed[:3]) + (", ..." if len(failed) > 3 else "")
            print(f"ss-drl: {len(failed)} of {len(jobs)} jobs failed ({names}): see FAILED in each", file=sys.stderr)
            sys.exit(1)


def _refuse_old_checkpoint(run_dir: Path) -> None:
    """The checkpoint a job in ``run_dir`` would continue from (``checkpoint.pt``, or ``checkpoint.prev.pt`` when
    that one is damaged) written before the learners were renamed: :class:`ConfigError` (a cheap look: the tensors
    are mapped, not read)."""
    from ss_drl.training import checkpoint as ckpt

    try:
        ckpt.resume_from(run_dir, mmap=True)
    except (FileNotFoundError, ckpt.UnreadableCheckpoint):  # none, or none readable: the job's own failure (FAILED)
        return


def _refuse_on(check, error: type[Exception]) -> None:
    """Run ``check``; on ``error``, one line on stderr and exit 2, before Hydra writes anything. Any other exception
    refuses the run too, named by its type: Hydra turns an exception in a callback into a warning and starts the job
    anyway, unchecked (a checkpoint whose config was not a mapping did that)."""
    try:
        check()
    except error as exc:
        print(f"ss-drl: config error: {exc}", file=sys.stderr)
        sys.exit(2)
    except Exception as exc:  # noqa: BLE001 - a check that fails is a refusal, never a run that goes on unchecked
        print(f"ss-drl: config error: the check before the run failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        sys.exit(2)


#: The first directory on the way to ``hydra.run.dir`` that did not exist when the run started (None: it existed),
#: set by :class:`ValidateBeforeRun`. A run refused after Hydra created the run directory removes it again, when
#: Hydra's own files are all it holds (:func:`_remove_hydra_files`).
_created: Path | None = None


def _first_missing(path: Path) -> Path | None:
    """The outermost directory of ``path`` (itself included) that does not exist, or None when ``path`` exists."""
    path = path.absolute()
    if path.exists():
        return None
    while not path.parent.exists():
        path = path.parent
    return path


def _remove_hydra_files() -> None:
    """Undo what Hydra wrote for a single run that was then refused: its run directory (``.hydra/`` and the job's
    log) and the directories above it that Hydra created, if this run created them and nothing else is in them."""
    if _created is None or _is_multirun():
        return
    hydra_cfg = HydraConfig.get()
    out = Path(hydra_cfg.runtime.output_dir).absolute()
    if not out.is_relative_to(_created) or not out.is_dir():
        return
    subdir = out / hydra_cfg.output_subdir if hydra_cfg.output_subdir else None
    own = {out / f"{hydra_cfg.job.name}.log"}
    if subdir is not None:
        own |= {subdir / name for name in ("config.yaml", "hydra.yaml", "overrides.yaml")}
    entries = list(out.rglob("*"))
    files = [p for p in entries if not p.is_dir()]
    if any(p not in own for p in files) or any(p.is_dir() and p != subdir for p in entries):
        return  # something else was written there: keep it all
    for path in files:
        path.unlink()
    if subdir is not None and subdir.is_dir():
        subdir.rmdir()
    directory = out
    while True:
        try:
            directory.rmdir()
        except OSError:  # not empty (another run's directory beside it)
            return
        if directory == _created:
            return
        directory = directory.parent


def _resume_dir(cfg: DictConfig) -> Path | None:
    """The run directory that ``trainer.resume=<dir>`` names, if it names one."""
    resume = cfg.trainer.resume
    if isinstance(resume, str) and resume not in ("", "true", "false", "auto"):
        return Path(resume)
    return None


def _run_dir(cfg: DictConfig) -> Path:
    """The run directory: ``trainer.resume=<dir>``, else Hydra's (``hydra.run.dir``, or the job's in a sweep)."""
    return _resume_dir(cfg) or Path(HydraConfig.get().runtime.output_dir)


def _sweep_dir() -> Path:
    """The running sweep's directory (``hydra.sweep.dir``)."""
    return Path(HydraConfig.get().sweep.dir)


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
        return _fail(str(exc), code=128 + exc.signum, signum=exc.signum)
    except (FloatingPointError, FileNotFoundError, ValueError) as exc:
        return _fail(f"{type(exc).__name__}: {exc} (run directory: {run_dir})", code=1)
    except Exception:  # noqa: BLE001
        if not _is_multirun():
            raise
        # In a sweep, one failing job must not take the others down: record it and go on.
        (run_dir / FAILED_FILE).write_text(traceback.format_exc())
        print(f"ss-drl: job failed, see {run_dir / FAILED_FILE}", file=sys.stderr)
        return None
    if _resume_dir(cfg) is not None:  # the run continued in the directory trainer.resume named: Hydra's own
        _remove_hydra_files()  # directory for it (outputs/<experiment>/...) holds only Hydra's files
    first = summary["first_goal_env_step"]
    goal = f"first goal at {first}" if first is not None else "G never reached"
    print(
        f"{summary['experiment']} seed {summary['seed']}: {summary['episodes']} episodes, {summary['env_steps']} env "
        f"steps in {summary['wall_s']:.1f}s ({summary['env_steps_per_s']:.0f} steps/s); "
        f"{goal}; greedy length {summary['final_eval_length']} "
        f"(optimal {summary['optimal_length']}); outputs in {run_dir}"
    )
    return summary["final_eval_length"]


def _fail(message: str, code: int, signum: int | None = None):
    """One clear line on stderr. In a sweep the job is marked failed and the sweep goes on; alone, exit non-zero,
    leaving no run directory behind when the run was refused before it wrote anything of its own.

    A job stopped by ``signum`` (SIGINT/SIGTERM, its checkpoint written) stops its sweep too: its process then dies by
    that signal, so that a sweep worker never starts the next job after the user stopped the sweep (Hydra's joblib
    workers outlive a killed parent, and would otherwise run the queued jobs to the end)."""
    if signum is not None and _is_multirun():
        message += f"; or the whole sweep: the same command with trainer.resume=auto hydra.sweep.dir={_sweep_dir()}"
    print(f"ss-drl: {message}", file=sys.stderr)
    if _is_multirun():
        out = Path(HydraConfig.get().runtime.output_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / FAILED_FILE).write_text(message + "\n")
        if signum is not None:
            sys.stdout.flush()
            sys.stderr.flush()
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
        return None
    _remove_hydra_files()
    sys.exit(code)


#: Command-line options that change where Hydra finds configs, or whose argument may hold ``=`` (``-sc install=bash``):
#: with any of them the command line is Hydra's to check.
_HYDRA_ONLY = (
    "--config-dir", "-cd", "--config-path", "-cp", "--config-name", "-cn", "hydra.searchpath",
    "-sc", "--shell-completion", "--info", "-i",
)  # fmt: skip
#: Characters of a sweep function (``glob(...)``, ``range(...)``) or an interpolation: Hydra expands such a value.
_EXPANDED = "()[]{}$*"
#: The most group combinations of a sweep that :func:`check_override_keys` composes; beyond, the sweep is Hydra's.
_MAX_COMBINATIONS = 16
_ABSENT = object()


def _command_line(argv: list[str], conf: Path) -> list[tuple[str, str, str | None]] | None:
    """``(key, value, group)`` of each ``key=value`` override of the command line, ``group`` the config group it
    chooses (a folder of ``conf``) or None for a value; None when the command line is Hydra's to check
    (:data:`_HYDRA_ONLY`). Options, removals (``~key``) and Hydra's own keys are left out."""
    if any(arg.split("=", 1)[0] in _HYDRA_ONLY for arg in argv):
        return None
    out = []
    for arg in argv:
        if arg.startswith(("-", "~")) or "=" not in arg:
            continue
        key, value = arg.split("=", 1)
        name = key.lstrip("+").split("@", 1)[0]
        if name and not name.startswith("hydra"):
            out.append((key, value, name if (conf / name).is_dir() else None))
    return out


def _did_you_mean(name: str, names, prefix: str = "") -> str:
    """``did you mean a or b?`` for the names nearest ``name`` (each with ``prefix``), or "" when none is near."""
    near = difflib.get_close_matches(name, [str(n) for n in names], n=3, cutoff=0.6)
    return f"did you mean {' or '.join(prefix + n for n in near)}?" if near else ""


def _default_groups(conf: Path) -> set[str]:
    """The config groups that ``conf/config.yaml``'s defaults list chooses (``env``, ``agent``, ...): the others
    (``experiment``, ``maze``, ...) are added with ``+``."""
    defaults = OmegaConf.load(conf / "config.yaml").get("defaults", [])
    return {str(key).split("@", 1)[0] for entry in defaults if isinstance(entry, DictConfig) for key in entry}


def check_overrides_parse(argv: list[str]) -> None:
    """Refuse a command-line override that Hydra's grammar cannot read, e.g. ``agent.hidden=[1,2`` (:class:`~ss_drl.
    training.config.ConfigError`, one line naming it), before Hydra reports it in three lines with exit code 1."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    from ss_drl.training.config import ConfigError

    if any(arg.split("=", 1)[0] in _HYDRA_ONLY for arg in argv):
        return
    parser = OverridesParser.create()
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        try:
            parser.parse_overrides([arg])
        except OverrideParseException as exc:
            reason = next((line.strip() for line in str(exc).splitlines() if line.strip()), "bad syntax")
            raise ConfigError(
                f"{arg}: not an override Hydra can read ({reason}; the grammar: "
                "https://hydra.cc/docs/advanced/override_grammar/basic/)"
            ) from None


def check_group_choices(argv: list[str], conf: Path) -> None:
    """Refuse a config group choice on the command line that names no file, e.g. ``+experiment=no_such_name``
    (:class:`~ss_drl.training.config.ConfigError`, one line naming the group and the nearest choices), before Hydra
    composes the config: Hydra's own report runs to one line per shipped experiment. Sweep lists (``a,b``) are
    checked item by item; sweep functions (``glob(...)``, ``range(...)``) and interpolations are left to Hydra.
    Refused too, where Hydra would report them in three lines with exit code 1: a group outside the defaults list
    chosen without ``+`` (``experiment=easy_ss``), and a group chosen twice."""
    from ss_drl.training.config import ConfigError

    chosen: dict[str, str] = {}
    by_default = _default_groups(conf)
    for key, value, group in _command_line(argv, conf) or ():
        if group is not None and "@" not in key:
            if group in chosen:
                raise ConfigError(
                    f"{group}: chosen twice ({chosen[group]} and {key}={value}); give it once, or sweep both with "
                    f"-m +{group}={chosen[group].split('=', 1)[1]},{value}"
                )
            chosen[group] = f"{key}={value}"
            if not key.startswith("+") and group not in by_default:
                raise ConfigError(f"{group}: not in the default config; choose it with +{group}={value}")
        if group is None or any(c in value for c in _EXPANDED):
            continue  # a value (agent.lr=...), or a choice Hydra expands
        for choice in (v.strip().strip("'\"") for v in value.split(",")):
            if not choice or choice == "null" or (conf / group / f"{choice}.yaml").is_file():
                continue
            names = sorted(p.stem for p in (conf / group).glob("*.yaml"))
            hint = _did_you_mean(choice, names)
            if not hint:
                hint = (
                    f"the choices: {', '.join(names)}" if len(names) <= 12 else f"see {conf / group}/ for the choices"
                )
            raise ConfigError(f"{group}: unknown value {choice!r} (no {conf / group / choice}.yaml); {hint}")


def check_override_keys(argv: list[str], conf: Path) -> None:
    """Refuse an override of a key the config does not have, e.g. ``agent.lrr=0.1`` (:class:`~ss_drl.training.config.
    ConfigError`, one line naming the key and the nearest keys beside it), before Hydra composes the config: Hydra
    refuses it too, in seven lines and with exit code 1. Refused as well: a key added with ``+`` or ``++``, which
    Hydra would accept and no run would read (every setting is in conf/), and ``+key`` for a key the config has. The
    config is composed with the command line's group choices; in a sweep, once per combination of the swept groups'
    choices (a key that one of them lacks is named with that choice, and the sweep is refused before any job). Left
    to Hydra: ``~`` removals, Hydra's own keys and options, sweep functions choosing a group, interpolations, another
    search path, and a command line Hydra cannot compose."""
    import itertools

    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from ss_drl.training.config import ConfigError

    groups, keys = [], []
    for key, value, group in _command_line(argv, conf) or ():
        if group is not None:
            if any(c in value for c in _EXPANDED):
                return  # a sweep function or an interpolation choosing a group: Hydra's to expand
            groups.append([f"{key}={choice}" for choice in value.split(",")])
        else:
            keys.append(key)
    combinations = list(itertools.product(*groups))
    if not keys or len(combinations) > _MAX_COMBINATIONS:
        return
    sweep = any(len(choices) > 1 for choices in groups)
    for combination in combinations:
        try:
            with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
                cfg = compose("config", overrides=list(combination))
        except (HydraException, OmegaConfBaseException):
            return  # a command line Hydra cannot compose: its own report says why
        for key in keys:
            name = key.lstrip("+")
            if OmegaConf.select(cfg, name, default=_ABSENT, throw_on_resolution_failure=False) is _ABSENT:
                raise ConfigError(_missing_key(cfg, name, combination if sweep else None))
            if key.startswith("+") and not key.startswith("++"):  # Hydra: "Could not append ..., already at ..."
                raise ConfigError(f"{name}: already in the config; set it without the +: {name}=...")


def _missing_key(cfg: DictConfig, key: str, combination) -> str:
    """The one line for an override of ``key``, which ``cfg`` lacks (``combination``: the sweep's group choices that
    composed ``cfg``, or None outside a sweep)."""
    parent, _, leaf = key.rpartition(".")
    node = OmegaConf.select(cfg, parent, default=None) if parent else cfg
    if not isinstance(node, DictConfig):
        return f"{key}: no such key in the config ({parent or key} is not a section of it)"
    hint = _did_you_mean(leaf, node.keys(), f"{parent}." if parent else "")
    if combination is not None:
        return f"{key}: no such key in the config of the sweep's {' '.join(combination)}" + (
            f"; {hint}" if hint else ""
        )
    return f"{key}: no such key in the config" + (
        f"; {hint}" if hint else " (the README's Configuration table lists them)"
    )


def train_main() -> None:
    """``ss-drl-train +experiment=NAME [key=value ...]`` (also ``-m`` sweeps): what scripts/train.py runs."""
    from ss_drl.training.config import ConfigError

    try:
        conf = config_dir()
    except FileNotFoundError as exc:
        sys.exit(str(exc))
    _refuse_on(lambda: check_overrides_parse(sys.argv[1:]), ConfigError)
    _refuse_on(lambda: check_group_choices(sys.argv[1:], conf), ConfigError)
    _refuse_on(lambda: check_override_keys(sys.argv[1:], conf), ConfigError)
    hydra.main(config_path=str(conf), config_name="config", version_base="1.3")(_train)()
