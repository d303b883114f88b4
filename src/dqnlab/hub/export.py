"""`dqnlab export`: a run's network and what describes it, as a folder (`run/exported.py`
names its files) that needs no pickle, no Hub and no run directory to be played.

The folder is written into a staging directory next to the target and renamed onto it
at the end, so a failure leaves nothing under the target's name.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from dqnlab import __version__
from dqnlab.config import config_fingerprint, config_from_dict, differing_settings
from dqnlab.errors import DqnlabError
from dqnlab.hub.card import CardFacts, model_card
from dqnlab.run import exported, rundir
from dqnlab.run.evaluate import final_evaluation, final_evaluation_record

# What results.json says the numbers are: `run/evaluate.py`'s protocol, in words.
PROTOCOL = (
    "dqnlab final evaluation (Mnih et al. 2015, Methods): whole games at epsilon, each of at "
    "most max_episode_frames raw frames (0: no cap), random no-op starts on Atari"
)


@dataclass
class Exported:
    """What `export_run` wrote."""

    folder: Path
    results: dict[str, Any]
    files: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # what was left out, and why


def export_run(
    run_dir: Path,
    out: Path,
    *,
    checkpoint: str = "best",
    episodes: int | None = None,
    seed: int,
    device: torch.device,
    video: bool = True,
    repo_id: str | None = None,
    echo: Callable[[str], object] = print,
) -> Exported:
    """Export the run's network `checkpoint` (best, last or a network file of this run)
    into the new folder `out` (absent, or an empty directory).

    The final evaluation is the run's final_evaluation.json when it is of this network;
    otherwise the network is evaluated (and, for best, the record saved in the run as
    `dqnlab evaluate` does). `video`: film one game when the environment renders."""
    config = rundir.load_run_config(run_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DqnlabError(f"--out {out} exists and is not an empty directory")
    path = _network_file(run_dir, checkpoint)
    payload = rundir.load_network(path)
    network_config = config_from_dict(payload["config"])
    if config_fingerprint(network_config) != config_fingerprint(config):
        raise DqnlabError(
            f"{path} is not a network of {run_dir}: their settings differ in "
            f"{', '.join(differing_settings(config, network_config))}"
        )
    staging = out.parent / f".{out.name}.partial-{os.getpid()}"
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        result = Exported(out, {})
        exported.save_network(exported.network_path(staging), payload)
        rundir.write_run_config(staging, config)
        result.results = _results(run_dir, checkpoint, path, payload, episodes, seed, device, echo)
        exported.save_json(staging / exported.RESULTS_FILE, result.results)
        for name in exported.LOG_FILES:
            if (run_dir / name).is_file():
                shutil.copyfile(run_dir / name, staging / name)
        if not _learning_curve(run_dir, staging / exported.CURVE_FILE):
            result.notes.append("no learning curve: the run has no periodic evaluation yet")
        if video:
            note = _film(staging, result.results["seed"], device)
            if note:
                result.notes.append(note)
        step = payload.get("step")
        files = sorted(p.name for p in staging.iterdir())
        facts = CardFacts(
            config, result.results, None if step is None else int(step), files, repo_id
        )
        (staging / exported.CARD_FILE).write_text(str(model_card(facts)))
        result.files = sorted(p.name for p in staging.iterdir())
        os.replace(staging, out)  # onto an empty directory too (rename(2))
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return result


def _network_file(run_dir: Path, checkpoint: str) -> Path:
    if checkpoint in ("best", "last"):
        path = rundir.network_path(run_dir, checkpoint)
        if not path.is_file():
            raise DqnlabError(f"{run_dir} has no {checkpoint} network yet ({path})")
        return path
    return Path(checkpoint)


def _results(
    run_dir: Path,
    checkpoint: str,
    path: Path,
    payload: dict[str, Any],
    episodes: int | None,
    seed: int,
    device: torch.device,
    echo: Callable[[str], object],
) -> dict[str, Any]:
    """results.json: the run's saved final evaluation when it is of this network (and of
    at least `episodes` games), else a new one."""
    step = payload.get("step")
    saved = rundir.load_final_evaluation(run_dir) if checkpoint == "best" else None
    usable = (
        saved is not None
        and step is not None
        and saved.get("checkpoint_step") == int(step)
        and (episodes is None or int(saved["episodes"]) >= episodes)
    )
    if saved is not None and usable:
        record = saved
    else:
        config = config_from_dict(payload["config"])
        count = episodes if episodes is not None else config.final_eval_episodes
        echo(f"dqnlab: evaluating {path} ({count} games of the final protocol)")
        evaluated, network = final_evaluation(run_dir, checkpoint, episodes, seed, device)
        record = final_evaluation_record(evaluated, config, network.path, network.step, seed)
        if checkpoint == "best":
            rundir.record_final_evaluation(run_dir, record)
    kept = ("env", "mean", "std", "episodes", "scores", "seed", "epsilon",
            "max_episode_frames", "frames", "checkpoint_step")  # fmt: skip
    return {
        **{key: record.get(key) for key in kept},
        "checkpoint": checkpoint if checkpoint in ("best", "last") else path.name,
        # How far the run had trained (its newest checkpoint): `dqnlab report` says whether
        # the exported agent finished its budget.
        "trained_steps": rundir.network_step(run_dir, "last"),
        "network": exported.MODEL_FILE,
        "protocol": PROTOCOL,
        "dqnlab_version": __version__,
    }


def _learning_curve(run_dir: Path, path: Path) -> bool:
    """The run's periodic evaluations as `dqnlab report` draws them (with Dopamine's curve
    behind an Atari game's); False when there are none."""
    from dqnlab.analysis.report.curves import curve_figure, learning_curves
    from dqnlab.analysis.report.reference import group_references, load_references
    from dqnlab.analysis.report.runs import group_runs, load_run

    run = load_run(run_dir)
    groups = group_runs([run])
    for group in groups:
        group.label = f"seed {run.config.seed}"
    curves = learning_curves(groups)
    if not curves:
        return False
    curve = curves[0]
    curve.references = group_references(groups, load_references([run.config]))
    curve_figure(curve).savefig(path, dpi=150)
    return True


def _film(folder: Path, seed: int, device: torch.device) -> str | None:
    """replay.mp4 (or .gif): one game of the final protocol from `seed`, played on one
    environment by the exported network itself; a note instead when the environment cannot
    be filmed."""
    from dqnlab.analysis.video import filmed_final_evaluation

    films = folder / ".films"
    try:
        recording, _ = filmed_final_evaluation(folder, "best", 1, seed, device, films, "auto")
        film = recording.paths[0]
        os.replace(film, folder / f"{exported.VIDEO_STEM}{film.suffix}")
    except DqnlabError as error:
        return f"no video: {error}"
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(films)
    return None
