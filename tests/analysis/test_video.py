"""Videos of evaluation games (video.py): the games and scores of `play`, every raw frame
in order, one file per game named with its score, MP4 or GIF."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import gymnasium as gym
import imageio.v2 as imageio
import imageio.v3 as iio
import numpy as np
import pytest

from dqnlab.analysis import video
from dqnlab.analysis.video import (
    ATARI_MP4_SCALE,
    choose_video_format,
    format_score,
    mp4_unavailable_reason,
    record_games,
    video_file_name,
)
from dqnlab.config import Config, derive_seeds, resolve_config
from dqnlab.envs import make_env
from dqnlab.errors import DqnlabError
from dqnlab.run.lockstep import play_games
from dqnlab.run.play import play
from tests.helpers import BlinkEnv, untrained_agent

EPSILON = 0.05
SEED = 3
PONG_CAP = 300  # frames, no-ops included: an untrained network's games end at the cap
GAMES = 2

needs_mp4 = pytest.mark.skipif(mp4_unavailable_reason() is not None, reason="no MP4 encoder")


class NoImageEnv(BlinkEnv):
    metadata = {"render_modes": [], "render_fps": 50}


class NoRenderModeEnv(BlinkEnv):
    def __init__(self) -> None:
        super().__init__()


class GrayImageEnv(BlinkEnv):
    """Says it renders rgb_array, renders grey floats."""

    def render(self) -> np.ndarray:
        return super().render().mean(axis=2)


BLINK_ID = "DqnlabVideoTest/Blink-v0"
NO_IMAGE_ID = "DqnlabVideoTest/NoImage-v0"
GRAY_IMAGE_ID = "DqnlabVideoTest/GrayImage-v0"
NO_RENDER_MODE_ID = "DqnlabVideoTest/NoRenderMode-v0"
if BLINK_ID not in gym.registry:
    gym.register(BLINK_ID, entry_point=BlinkEnv)
    gym.register(NO_IMAGE_ID, entry_point=NoImageEnv)
    gym.register(GRAY_IMAGE_ID, entry_point=GrayImageEnv)
    gym.register(NO_RENDER_MODE_ID, entry_point=NoRenderModeEnv)


def reference_play(config: Config, cap: int) -> tuple[list[float], list[np.ndarray]]:
    """`play` on an environment built as `record_games` builds it: scores and raw frames."""
    env = make_env(
        config,
        training=False,
        seed=derive_seeds(SEED, 1)[0],
        max_episode_frames=cap,
        render_mode=None if config.env == "pong" else "rgb_array",
    )
    frames: list[np.ndarray] = []
    env.frame_callback = lambda frame: frames.append(frame.copy())  # type: ignore[attr-defined]
    result = play(untrained_agent(config), env, config.history_length, EPSILON, max_episodes=GAMES)
    env.close()
    return result.scores, frames


def record(config: Config, out_dir: Path, cap: int, video_format: str):
    return record_games(
        untrained_agent(config),
        config,
        GAMES,
        SEED,
        out_dir,
        epsilon=EPSILON,
        max_episode_frames=cap,
        video_format=video_format,
    )


def read_mp4(path: Path) -> np.ndarray:
    return np.stack(list(imageio.get_reader(path, format="FFMPEG").iter_data()))


@pytest.fixture(scope="module")
def pong_reference(pong: Config) -> tuple[list[float], list[np.ndarray]]:
    return reference_play(pong, PONG_CAP)


def reset_screen(config: Config) -> np.ndarray:
    env = make_env(config, training=False, seed=derive_seeds(SEED, 1)[0])
    env.ale.reset_game()  # type: ignore[attr-defined]
    return env.ale.getScreenRGB()  # type: ignore[attr-defined]


def test_score_and_file_names() -> None:
    assert format_score(-21.0) == "-21"
    assert format_score(12.5) == "12.5"
    assert format_score(400.0) == "400"
    assert format_score(0.1 + 0.2) == "0.3" and format_score(1 / 3) == "0.33"
    assert video_file_name("pong", 1, 30, -21.0, "mp4") == "pong-game01-score-21.mp4"
    assert video_file_name("ALE/Pong-v5", 7, 150, 3.0, "gif") == "ALE_Pong-v5-game007-score3.gif"
    assert (
        video_file_name("my.module:Env", 12, 12, 0.5, "mp4") == "my.module_Env-game12-score0.5.mp4"
    )


@needs_mp4
def test_mp4_games_have_plays_scores_and_every_raw_frame(pong, pong_reference, tmp_path):
    scores, frames = pong_reference
    recording = record(pong, tmp_path, PONG_CAP, "mp4")
    assert recording.video_format == "mp4" and recording.fps == 60
    assert recording.result.scores == scores
    agent = untrained_agent(pong)
    assert (
        play_games(
            agent, pong, GAMES, SEED, epsilon=EPSILON, max_episode_frames=PONG_CAP, num_envs=1
        ).scores
        == scores
    )
    assert [p.name for p in recording.paths] == [
        video_file_name("pong", i + 1, GAMES, score, "mp4") for i, score in enumerate(scores)
    ]
    assert sorted(tmp_path.iterdir()) == sorted(recording.paths)  # no partial file left
    # Each game: its first screen, then every emulator frame up to the cap (no-ops included).
    assert recording.result.frames == GAMES * PONG_CAP
    assert len(frames) == GAMES * (PONG_CAP + 1)
    first_screen = reset_screen(pong)
    decoded_frames = []
    for path in recording.paths:
        video = read_mp4(path)
        scale = ATARI_MP4_SCALE
        assert video.shape == (PONG_CAP + 1, 210 * scale, 160 * scale, 3)
        video = video[:, ::scale, ::scale]
        assert np.abs(video[0].astype(int) - first_screen).mean() < 2
        decoded_frames.append(video)
    error = np.abs(np.concatenate(decoded_frames).astype(int) - np.stack(frames))
    assert error.mean() < 2 and np.percentile(error, 99) <= 8


def test_gif_keeps_every_third_frame_exactly(pong, pong_reference, tmp_path):
    scores, frames = pong_reference
    recording = record(pong, tmp_path, PONG_CAP, "gif")
    assert recording.video_format == "gif" and recording.fps == 20
    assert recording.result.scores == scores
    assert [p.name for p in recording.paths] == [
        video_file_name("pong", i + 1, GAMES, score, "gif") for i, score in enumerate(scores)
    ]
    for game, path in enumerate(recording.paths):
        video = iio.imread(path, index=None, mode="RGB")
        game_frames = frames[game * (PONG_CAP + 1) : (game + 1) * (PONG_CAP + 1)]
        np.testing.assert_array_equal(video, np.stack(game_frames[::3]))
        assert iio.immeta(path, index=0)["duration"] == 50  # milliseconds: 20 frames/s
    np.testing.assert_array_equal(iio.imread(recording.paths[0], index=0), reset_screen(pong))


@pytest.mark.parametrize("video_format", ["gif", pytest.param("mp4", marks=needs_mp4)])
def test_gymnasium_env_rendered_frames(video_format, tmp_path):
    config = resolve_config("classic", env=BLINK_ID)
    scores, frames = reference_play(config, 0)
    recording = record(config, tmp_path, 0, video_format)
    assert recording.result.scores == scores
    assert [p.name for p in recording.paths] == [
        video_file_name(BLINK_ID, i + 1, GAMES, score, video_format)
        for i, score in enumerate(scores)
    ]
    assert recording.result.frames + GAMES == len(frames)  # one frame per reset and step
    starts = [i for i, frame in enumerate(frames) if frame[0, 0, 0] == 0]  # t = 0: a reset
    games = np.split(np.stack(frames), starts[1:])
    assert len(games) == GAMES
    for game_frames, path in zip(games, recording.paths, strict=True):
        if video_format == "gif":
            assert recording.fps == 25  # every 2nd frame of 50
            np.testing.assert_array_equal(
                iio.imread(path, index=None, mode="RGB"), game_frames[::2]
            )
        else:
            assert recording.fps == 50
            video = read_mp4(path)
            assert video.shape == (len(game_frames), 22, 34, 3)  # padded to even sizes
            assert np.abs(video[:, :21, :33].astype(int) - game_frames).mean() < 8


@pytest.mark.filterwarnings("ignore::UserWarning")  # Gymnasium's own warnings about these envs
@pytest.mark.parametrize(
    ("name", "message"),
    [
        (NO_IMAGE_ID, "cannot be filmed: .* offers \\[\\]"),
        (NO_RENDER_MODE_ID, "cannot be filmed: it cannot be made with render_mode"),
        (GRAY_IMAGE_ID, "renders an array of float64 \\(21, 33\\), not an RGB image"),
    ],
)
def test_env_that_cannot_render_raises_and_leaves_no_file(name, message, tmp_path):
    config = resolve_config("classic", env=name)
    with pytest.raises(DqnlabError, match=message):
        record(config, tmp_path, 0, "gif")
    assert not list(tmp_path.iterdir())


def test_cartpole_records_or_says_why_not(tmp_path):
    config = resolve_config("classic", env="CartPole-v1")
    if importlib.util.find_spec("pygame") is None:
        with pytest.raises(DqnlabError, match="pygame"):
            record(config, tmp_path, 20, "gif")
        assert not list(tmp_path.iterdir())
    else:
        recording = record(config, tmp_path, 20, "gif")
        assert len(recording.paths) == GAMES


def test_format_choice(monkeypatch):
    assert choose_video_format("gif") == ("gif", "")
    with pytest.raises(DqnlabError, match="webm"):
        choose_video_format("webm")
    if mp4_unavailable_reason() is None:
        assert choose_video_format("auto") == ("mp4", "")
    monkeypatch.setattr(video, "mp4_unavailable_reason", lambda: "no ffmpeg found")
    assert choose_video_format("auto") == ("gif", "GIF instead of MP4: no ffmpeg found")
    with pytest.raises(DqnlabError, match="cannot write MP4 videos: no ffmpeg found"):
        choose_video_format("mp4")


def test_gif_fallback_says_why_and_what_it_keeps(pong, monkeypatch, tmp_path):
    monkeypatch.setattr(video, "mp4_unavailable_reason", lambda: "no ffmpeg found")
    recording = record(pong, tmp_path, 30, "auto")
    assert recording.video_format == "gif"
    assert recording.note == "GIF instead of MP4: no ffmpeg found; 1 frame in 3 kept, 20 frames/s"
    assert [p.suffix for p in recording.paths] == [".gif"] * GAMES


def test_recording_again_replaces_the_films_of_an_earlier_recording(tmp_path):
    """Films of the same environment from before (other scores, game counts or format)
    would pass for this recording's: only this recording's are left."""
    config = resolve_config("classic", env=BLINK_ID)
    stale = [
        tmp_path / video_file_name(BLINK_ID, 1, GAMES, 12345, "gif"),
        tmp_path / video_file_name(BLINK_ID, 7, 100, 2.5, "mp4"),
        tmp_path / "DqnlabVideoTest_Blink-v0-game03.partial.gif",
    ]
    kept = [tmp_path / "notes.gif", tmp_path / video_file_name("pong", 1, 1, 3, "mp4")]
    for path in stale + kept:
        path.write_bytes(b"an older file")
    recording = record(config, tmp_path, 0, "gif")
    assert sorted(tmp_path.iterdir()) == sorted([*recording.paths, *kept])
