"""Which way should `num_envs` step N Atari emulators: dqnlab's own environments one after
another in the process, or ale-py's threaded vector environment? Answered once (issue 22,
2026-12-03: ale-py's is 1.13x faster with one thread and 1.56x with two, but cannot save
and restore each emulator, which exact resuming needs, so dqnlab steps its own); the
figures and the reasons are in docs/benchmark.md, "Does it help to run several
environments?" (#many-environments). Run: `python scripts/emulators.py --emulators 8
--steps 4000`.

Both step N Breakout emulators at random actions and produce the same kind of
observation, per agent step, for all N:

- `in_process`: dqnlab's `AtariEnv`s one after another in this process, as training steps
  them (4 raw frames, RGB max-pool of the last two, luminance, area resize to 84x84);
- `ale_vector_T_threads`: ale-py's `AtariVectorEnv` with T C++ threads returning the
  max-pooled 210x160 RGB frame of its 4-frame step, then dqnlab's same preprocessing
  (`FramePreprocessor`) on each frame of the batch in this process.

In alternating rounds, agent steps per second over all N environments. The vector
environment cannot save and restore each emulator, which exact resuming needs: this only
says what it would gain.
"""

from __future__ import annotations

import time
from typing import Annotated, Any

import numpy as np
import typer

from dqnlab.cli.bench import Env, JsonPath, report
from dqnlab.cli.common import run_command
from dqnlab.envs.atari import RAW_FRAME_SHAPE, AtariEnv, FramePreprocessor
from dqnlab.errors import DqnlabError


def _in_process(envs: list[AtariEnv], steps: int, rng: np.random.Generator) -> float:
    start = time.perf_counter()
    for _ in range(steps):
        for env in envs:
            _, _, terminal, _ = env.step(int(rng.integers(env.num_actions)))
            if terminal or env.game_over:
                env.reset(new_game=env.game_over)
    return steps * len(envs) / (time.perf_counter() - start)


def _vector(vector: Any, count: int, steps: int, rng: np.random.Generator) -> float:
    preprocess = FramePreprocessor()
    out = np.empty((count, 84, 84), dtype=np.uint8)
    actions = int(vector.single_action_space.n)
    start = time.perf_counter()
    for _ in range(steps):
        observations, *_ = vector.step(rng.integers(actions, size=count))
        frames = observations.reshape(count, *RAW_FRAME_SHAPE)
        for index in range(count):  # already pooled: the same frame as both of the pair
            preprocess(frames[index], frames[index], out[index])
    return steps * count / (time.perf_counter() - start)


def _vector_env(game: str, count: int, threads: int) -> Any:
    """ale-py's vector environment of `count` emulators, stepping as dqnlab's do."""
    from ale_py.vector_env import AtariVectorEnv

    return AtariVectorEnv(
        game, count, num_threads=threads, img_height=RAW_FRAME_SHAPE[0],
        img_width=RAW_FRAME_SHAPE[1], grayscale=False, stack_num=1, frameskip=4, maxpool=True,
        reward_clipping=False, use_fire_reset=False, noop_max=30,
    )  # fmt: skip


def measure_emulators(
    count: int = 8, steps: int = 500, rounds: int = 3, game: str = "breakout"
) -> dict[str, Any]:
    """Agent steps/s of `count` emulators each way, `steps` vector steps per round."""
    rng = np.random.default_rng(0)
    envs = [AtariEnv(game, seed=index, training=True) for index in range(count)]
    for env in envs:
        env.reset(new_game=True)
    vectors = {threads: _vector_env(game, count, threads) for threads in (1, 2)}
    figures: dict[str, Any] = {"emulators": count, "emulator_steps": steps, "game": game}
    runs: dict[str, list[float]] = {"in_process": []}
    runs.update({f"ale_vector_{threads}_threads": [] for threads in vectors})
    try:
        for vector in vectors.values():
            vector.reset(seed=0)
        for round_ in range(rounds + 1):  # the first warms up, untimed
            timed = {"in_process": _in_process(envs, steps, rng)}
            for threads, vector in vectors.items():
                timed[f"ale_vector_{threads}_threads"] = _vector(vector, count, steps, rng)
            if round_:
                for name, value in timed.items():
                    runs[name].append(value)
    finally:
        for vector in vectors.values():
            vector.close()
        for env in envs:
            env.close()
    for name, values in runs.items():
        figures[f"{name}_agent_steps_per_second"] = float(np.mean(values))
        figures[f"{name}_agent_steps_per_second_runs"] = [round(v, 1) for v in values]
        figures[f"{name}_ratio"] = float(np.mean(values) / np.mean(runs["in_process"]))
    return figures


app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)


@app.command()
def main(
    emulators: Annotated[int, typer.Option(help="Emulators stepped each way")] = 8,
    steps: Annotated[
        int, typer.Option(help="Agent steps timed in each round, of all the emulators together")
    ] = 2000,
    env: Env = "breakout",
    json_path: JsonPath = None,
) -> None:
    """Agent steps/s of N emulators stepped by dqnlab in one process against ale-py's
    threaded vector environment (1 and 2 threads), the same preprocessing each way, in
    alternating rounds."""
    if emulators < 1:
        raise DqnlabError(f"--emulators {emulators}: give at least 1")
    report(measure_emulators(emulators, steps=max(1, steps // emulators), game=env), json_path)


if __name__ == "__main__":
    run_command(app)
