"""`dqnlab tune`: a study of settings on Optuna, each trial a dqnlab run."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from dqnlab.cli.common import ENV_HELP, Device, EnvKwargs, Wrappers, resolve_device
from dqnlab.errors import DqnlabError

if TYPE_CHECKING:
    import torch

    from dqnlab.tune.study import TunePlan

Trials = Annotated[
    int,
    typer.Option(
        help="Trials the study holds when the tune ends (a carried-on study counts those it has)"
    ),
]
Steps = Annotated[int, typer.Option(help="Training budget of each trial in agent steps")]
StartPreset = Annotated[
    str | None,
    typer.Option(
        help="The preset every trial starts from (nature for Atari, classic otherwise) or a .toml path"
    ),
]
FixedSettings = Annotated[
    list[str] | None,
    typer.Option("--set", help="A setting fixed for every trial: KEY=VALUE (repeatable)"),
]
SpaceFile = Annotated[
    Path | None, typer.Option(help="A TOML search space over the default one (docs/tune.md)")
]
Evaluations = Annotated[
    int,
    typer.Option(
        help="Periodic evaluations of each trial, which the pruner sees (eval_period_steps = steps / evaluations unless --set)"
    ),
]
Pruner = Annotated[str, typer.Option(help="median (rl-baselines3-zoo's) or none")]
Jobs = Annotated[
    int,
    typer.Option(
        help="Trials (and --verify's runs) trained at once, each in its own process with one "
        "PyTorch thread"
    ),
]
SamplerSeed = Annotated[
    int, typer.Option(help="Seed of the sampler (TPE); a trial's run seeds are set by --seeds")
]
Seeds = Annotated[
    int,
    typer.Option(
        help="Runs per trial, on the preset's seed and the next ones; the objective is their mean"
    ),
]
Objective = Annotated[
    str | None,
    typer.Option(
        help="best or last: a run's value is its best periodic evaluation's mean or its last "
        "one's (default: the network its final evaluation plays, final_eval_network)"
    ),
]
Verify = Annotated[
    int,
    typer.Option(
        help="Then train the best settings and the starting preset on N seeds no trial used "
        "(10 on), and play each run's best and last networks: verify.csv (docs/tune.md)"
    ),
]
StudyDir = Annotated[
    Path | None,
    typer.Option(
        help="Where the study is kept (default studies/ENV-PRESET); the same command carries it on"
    ),
]


def tune(
    env: Annotated[str, typer.Option(help=ENV_HELP)],
    trials: Trials,
    steps: Steps,
    preset: StartPreset = None,
    set_: FixedSettings = None,
    env_kwarg: EnvKwargs = None,
    wrapper: Wrappers = None,
    space: SpaceFile = None,
    evaluations: Evaluations = 10,
    pruner: Pruner = "median",
    jobs: Jobs = 1,
    seed: SamplerSeed = 0,
    seeds: Seeds = 1,
    objective: Objective = None,
    verify: Verify = 0,
    study_dir: StudyDir = None,
    device: Device = "auto",
) -> None:
    """Search settings with Optuna: each trial a dqnlab run pruned from its periodic
    evaluations; writes best.toml (a preset), trials.csv and Optuna's figures.

    * `dqnlab tune --env CartPole-v1 --trials 50 --steps 50000`
    * `dqnlab tune --env CartPole-v1 --trials 20 --steps 20000 --space space.toml --jobs 2`
    * `dqnlab tune --env Acrobot-v1 --trials 20 --steps 100000 --seeds 3 --verify 5`

    A killed tune is carried on by the same command: its unfinished trial resumes from
    its run's newest checkpoint."""
    try:
        import optuna  # noqa: F401
    except ImportError:
        raise DqnlabError("dqnlab tune needs Optuna: pip install 'dqnlab[tune]'") from None
    from dqnlab.config import parse_overrides, parse_pairs
    from dqnlab.envs import is_atari
    from dqnlab.run.rundir import preset_label, safe_name
    from dqnlab.tune.driver import tune as run_tune
    from dqnlab.tune.space import check_space, load_space
    from dqnlab.tune.study import BEST_FILE, TunePlan

    _check_counts(trials, steps, evaluations, jobs, pruner, seeds)
    if verify < 0:
        raise DqnlabError(f"--verify {verify}: must be 0 (no check) or more")
    preset = preset or ("nature" if is_atari(env) else "classic")
    fixed = parse_overrides(set_ or [])
    env_kwargs = parse_pairs(env_kwarg or [], "--env-kwarg")
    fixed = _with_env_arguments(preset, fixed, env, env_kwargs, wrapper or [])
    searched = load_space(space)
    check_space(searched, preset, fixed, env, steps)
    study_dir = study_dir or Path("studies") / f"{safe_name(env)}-{preset_label(preset)}"
    plan = TunePlan(env=env, preset=preset, steps=steps, space=searched, fixed=fixed,
                    evaluations=evaluations, pruner=pruner, seed=seed, seeds=seeds,
                    objective=_objective(objective, preset, fixed, env, study_dir))  # fmt: skip
    torch_device = resolve_device(device)
    typer.echo(f"dqnlab: tuning {env} from preset {preset}: {trials} trials of {steps} steps "
               f"into {study_dir}")  # fmt: skip
    command = shlex.join(["dqnlab", *sys.argv[1:]])
    study = run_tune(study_dir, plan, trials, torch_device, command, jobs=jobs)
    _say_result(study, study_dir / BEST_FILE)
    if verify:
        _verify(study_dir, plan, verify, torch_device, jobs)


def _verify(study_dir: Path, plan: TunePlan, count: int, device: torch.device, jobs: int) -> None:
    """The best settings against the starting preset on `count` new seeds, `jobs` runs at a
    time (`tune/verify.py`)."""
    from dqnlab.tune.verify import VERIFY_TABLE, summary, verification_seeds
    from dqnlab.tune.verify import verify as run_verify

    seeds = verification_seeds(plan, 0, count)
    typer.echo(f"dqnlab: checking the best settings and {plan.preset} on {count} new seeds "
               f"(the preset's seed + {seeds[0]} on) into {study_dir / 'verify'}")  # fmt: skip
    checked = run_verify(study_dir, plan, count, device, jobs=jobs)
    for line in summary(checked, plan.preset):
        typer.echo(f"dqnlab: {line}")
    typer.echo(f"dqnlab: every game in {study_dir / VERIFY_TABLE}")


def _with_env_arguments(
    preset: str, fixed: dict, env: str, env_kwargs: dict, wrappers: list[str]
) -> dict:
    """`--env-kwarg` and `--wrapper` as fixed settings of every trial, added to the
    preset's and --set's as `train` adds them (`with_env_arguments`); the environment the
    trials will make is made once first (`check_env`), so one that cannot be is refused
    before anything is written."""
    from dqnlab.config import resolve_config, with_env_arguments
    from dqnlab.envs import check_env

    config = with_env_arguments(resolve_config(preset, fixed, env=env), env_kwargs, wrappers)
    check_env(config)
    if not env_kwargs and not wrappers:
        return fixed
    return {**fixed, "env_kwargs": config.env_kwargs, "env_wrappers": list(config.env_wrappers)}


def _objective(
    objective: str | None, preset: str, fixed: dict, env: str, study_dir: Path | None = None
) -> str:
    """--objective; by default the study's own where `study_dir` holds one (so the same
    command carries on a study begun before the option, whose objective was the last
    evaluation), else the network the trials' final evaluation plays."""
    from dqnlab.config import resolve_config
    from dqnlab.tune.study import OBJECTIVES, recorded_objective

    if objective is None:
        recorded = None if study_dir is None else recorded_objective(study_dir)
        return recorded or resolve_config(preset, fixed, env=env).final_eval_network
    if objective not in OBJECTIVES:
        raise DqnlabError(f"--objective {objective!r} is not one of: {', '.join(OBJECTIVES)}")
    return objective


def _check_counts(
    trials: int, steps: int, evaluations: int, jobs: int, pruner: str, seeds: int
) -> None:
    """The numbers of the command line, before anything is written."""
    for option, value in (("--trials", trials), ("--steps", steps), ("--seeds", seeds),
                          ("--evaluations", evaluations), ("--jobs", jobs)):  # fmt: skip
        if value < 1:
            raise DqnlabError(f"{option} {value}: must be at least 1")
    if evaluations > steps:
        raise DqnlabError(f"--evaluations {evaluations} is more than --steps {steps}")
    if pruner not in ("median", "none"):
        raise DqnlabError(f"--pruner {pruner!r} is not one of: median, none")


def _say_result(study, best_path: Path) -> None:  # noqa: ANN001 - optuna is optional
    from optuna.trial import TrialState

    counts = {state: len(study.get_trials(states=(state,))) for state in TrialState}
    summary = ", ".join(f"{n} {state.name.lower()}" for state, n in counts.items() if n)
    if not counts[TrialState.COMPLETE]:
        typer.echo(f"dqnlab: {summary}; no trial completed, so no {best_path.name}")
        return
    best = study.best_trial
    typer.echo(f"dqnlab: {summary}; best: trial {best.number} with {best.value:.2f}, "
               f"settings in {best_path}")  # fmt: skip
