"""Videos of evaluation games: every raw frame of each game, one file per game, its score
in the file name.

An Atari game is filmed from every emulator frame, the RGB screen (210x160), including the
frames inside the action repeat and the random no-op start, at the console's 60 Hz: a game
of the final protocol's 5 minutes is 18,000 frames. Any other environment is filmed from
`env.render()` after each reset and step, at its `render_fps`. Frames go to the encoder
as they are emulated; no game is held in memory.

MP4 (H.264, yuv420p: what browsers play) through imageio-ffmpeg's ffmpeg; where there is
none, GIF (lossless, every 3rd frame of a 60 Hz game at 20 frames/s: a GIF's frame time is
a whole number of hundredths of a second and browsers slow down frames shorter than two).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from dqnlab.algorithm.agent import Agent
from dqnlab.config import Config, derive_seeds
from dqnlab.envs import Environment, is_atari, make_env
from dqnlab.envs.atari import AtariEnv
from dqnlab.envs.generic import GymnasiumEnv
from dqnlab.errors import DqnlabError
from dqnlab.run.evaluate import EvaluatedNetwork, load_evaluated_agent
from dqnlab.run.play import EvaluationResult, play

VIDEO_FORMATS = ("auto", "mp4", "gif")
ATARI_FPS = 60  # NTSC frame rate of the console, one emulator frame per video frame
DEFAULT_RENDER_FPS = 30  # for a Gymnasium env whose metadata gives no render_fps
# Nearest-neighbour upscaling of Atari screens before H.264's yuv420p, which stores colour
# at half resolution: at 1x the colour of one-pixel details (Breakout's bricks) bleeds,
# 1% of pixel values off by 36 or more; at 2x by 3 or less, for 10% more bytes.
ATARI_MP4_SCALE = 2
# x264 constant rate factor: visually lossless, and a 5-minute game is a few MB at most.
MP4_CRF = 18
GIF_MAX_FPS = 25


@dataclass
class Recording:
    """What `record_games` played and wrote."""

    result: EvaluationResult  # as `play(..., max_episodes=episodes)` returns it
    paths: list[Path]  # one file per game, in game order
    video_format: str  # "mp4" or "gif"
    fps: float  # frames per second of the files
    note: str  # for GIF: why not MP4 if MP4 was wanted, and which frames are kept


def mp4_unavailable_reason() -> str | None:
    """Why MP4 files cannot be written here (no imageio-ffmpeg, no ffmpeg, no libx264),
    or None if they can."""
    try:
        import imageio_ffmpeg
    except ImportError as error:
        return f"imageio-ffmpeg is not installed ({error})"
    try:
        ffmpeg = imageio_ffmpeg.get_ffmpeg_exe()
        encoders = subprocess.run(
            [ffmpeg, "-hide_banner", "-encoders"], capture_output=True, text=True, check=True
        ).stdout
    except (RuntimeError, OSError, subprocess.CalledProcessError) as error:
        return f"no working ffmpeg found ({error})"
    if " libx264 " not in encoders:
        return f"{ffmpeg} has no libx264 encoder"
    return None


def choose_video_format(video_format: str = "auto") -> tuple[str, str]:
    """("mp4" or "gif", why GIF where MP4 was wanted or "") for `video_format`."""
    if video_format not in VIDEO_FORMATS:
        raise DqnlabError(f"video format {video_format!r} is not one of {list(VIDEO_FORMATS)}")
    if video_format == "gif":
        return "gif", ""
    reason = mp4_unavailable_reason()
    if reason is None:
        return "mp4", ""
    if video_format == "mp4":
        raise DqnlabError(f"cannot write MP4 videos: {reason}")
    return "gif", f"GIF instead of MP4: {reason}"


def format_score(score: float) -> str:
    """A score as a file name shows it: 21, -21, 12.5, 0.33 (no trailing .0, at most
    two decimals)."""
    text = f"{float(score):.2f}".rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def video_file_name(env_name: str, game: int, games: int, score: float, extension: str) -> str:
    """`{env}-game{NN}-score{S}.{extension}` for game number `game` (from 1) of `games`;
    an env name such as ALE/Pong-v5 or module:Env is made safe (ALE_Pong-v5)."""
    return f"{_game_stem(env_name, game, games)}-score{format_score(score)}.{extension}"


def _game_stem(env_name: str, game: int, games: int) -> str:
    return f"{_safe_name(env_name)}-game{game:0{max(2, len(str(games)))}d}"


def _safe_name(env_name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", env_name).strip("._") or "env"


def _remove_earlier_films(out_dir: Path, env_name: str) -> None:
    """Films of this environment from an earlier recording into `out_dir`: with other
    games or scores in their names, they would pass for this recording's."""
    pattern = re.compile(rf"{re.escape(_safe_name(env_name))}-game\d+-score.*\.(mp4|gif)")
    for path in out_dir.glob(f"{_safe_name(env_name)}-game*"):
        if pattern.fullmatch(path.name) or ".partial." in path.name:
            path.unlink()


# Encoders: append(frame) with an RGB uint8 (H, W, 3) array, close() ---------------------


class _Mp4Writer:
    def __init__(self, path: Path, fps: float, scale: int) -> None:
        import imageio.v2 as imageio

        filters = [f"scale=iw*{scale}:ih*{scale}:flags=neighbor"] if scale > 1 else []
        filters.append("pad=ceil(iw/2)*2:ceil(ih/2)*2")  # yuv420p needs even sizes
        self._writer = imageio.get_writer(
            path,
            format="FFMPEG",
            fps=fps,
            codec="libx264",
            quality=None,  # the rate factor is set below
            pixelformat="yuv420p",
            macro_block_size=1,  # no resizing by imageio: the pad filter makes sizes even
            ffmpeg_log_level="error",
            # faststart: the index at the start, so that a browser plays while loading
            output_params=["-crf", str(MP4_CRF), "-vf", ",".join(filters)]
            + ["-movflags", "+faststart"],
        )

    def append(self, frame: np.ndarray) -> None:
        self._writer.append_data(frame)  # piped to ffmpeg at once: the buffer can be reused

    def close(self) -> None:
        self._writer.close()


class _GifWriter:
    """An animated GIF written frame by frame (Pillow's writer keeps every frame until the
    end), keeping every `stride`-th frame.

    Pillow encodes each kept frame's changed rectangle as a one-frame GIF, whose colour
    table and image data are copied into this file; frames are not disposed, so each one
    paints over the previous. Colours are exact up to 256 in a rectangle (Atari screens
    have at most 128), quantized by Pillow beyond.
    """

    def __init__(self, path: Path, fps: float, stride: int) -> None:
        self._file = path.open("wb")
        self._stride = stride
        self._delay_centiseconds = gif_delay_centiseconds(fps, stride)
        self._count = 0
        self._previous: np.ndarray | None = None

    def append(self, frame: np.ndarray) -> None:
        self._count += 1
        if (self._count - 1) % self._stride:
            return
        height, width = frame.shape[:2]
        if self._previous is None:
            self._previous = frame.copy()
            self._file.write(b"GIF89a" + struct.pack("<HHBBB", width, height, 0, 0, 0))
            self._file.write(b"\x21\xff\x0bNETSCAPE2.0\x03\x01\x00\x00\x00")  # loop forever
            top, bottom, left, right = 0, height, 0, width
        else:
            changed = np.any(frame != self._previous, axis=2)
            rows, columns = np.flatnonzero(changed.any(axis=1)), np.flatnonzero(changed.any(axis=0))
            if rows.size:
                top, bottom, left, right = rows[0], rows[-1] + 1, columns[0], columns[-1] + 1
            else:  # one unchanged pixel: the frame still takes its time
                top, bottom, left, right = 0, 1, 0, 1
            np.copyto(self._previous, frame)
        color_table, image_flags, image_data = _one_frame_gif(frame[top:bottom, left:right])
        self._file.write(
            b"\x21\xf9\x04\x04"  # graphic control: disposal 1, leave the frame in place
            + struct.pack("<HBB", self._delay_centiseconds, 0, 0)
            + b"\x2c"
            + struct.pack("<HHHHB", left, top, right - left, bottom - top, image_flags)
            + color_table
            + image_data
        )

    def close(self) -> None:
        with self._file:
            if self._previous is not None:
                self._file.write(b"\x3b")


def _one_frame_gif(rgb: np.ndarray) -> tuple[bytes, int, bytes]:
    """(colour table, image descriptor flags with a local table, LZW image data) of `rgb`
    encoded by Pillow as a one-frame GIF."""
    packed = (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8)
    packed |= rgb[..., 2]
    colors, indices = np.unique(packed, return_inverse=True)
    if len(colors) <= 256:
        image = Image.fromarray(indices.reshape(rgb.shape[:2]).astype(np.uint8), mode="P")
        palette = np.stack([colors >> 16, (colors >> 8) & 255, colors & 255], axis=1)
        image.putpalette(palette.astype(np.uint8).tobytes())
    else:
        image = Image.fromarray(np.ascontiguousarray(rgb)).quantize(256)
    buffer = io.BytesIO()
    image.save(buffer, format="GIF", interlace=False, optimize=False)
    data = buffer.getvalue()
    # Header (6 bytes), logical screen descriptor (7) with the global colour table's size.
    table_end = 13 + (3 << ((data[10] & 7) + 1) if data[10] & 0x80 else 0)
    color_table, table_bits = data[13:table_end], data[10] & 7
    position = table_end
    while data[position] == 0x21:  # extensions: skip the label, then the sub-blocks
        position += 2
        while data[position]:
            position += data[position] + 1
        position += 1
    if data[position] != 0x2C:
        raise RuntimeError("unexpected GIF from Pillow: no image descriptor")
    flags = data[position + 9]
    position += 10
    if flags & 0x80:  # Pillow gave the image its own table
        table_bits = flags & 7
        table_end = position + (3 << (table_bits + 1))
        color_table, position = data[position:table_end], table_end
    return color_table, 0x80 | (flags & 0x40) | table_bits, data[position:-1]  # -1: trailer


# Recording -----------------------------------------------------------------------------


class _GameRecorder:
    """An environment as `play` sees it, filming each game into its own file.

    A file is opened at the first reset of a game and renamed with the score when the game
    ends (the score is summed as `play` sums it). A game left unfinished is deleted.
    """

    def __init__(
        self,
        env: AtariEnv | GymnasiumEnv,
        out_dir: Path,
        env_name: str,
        games: int,
        video_format: str,
        fps: float,
        scale: int,
    ) -> None:
        self.env = env
        self.num_actions = env.num_actions
        self.action_names = env.action_names
        self.observation_shape = env.observation_shape
        self.observation_dtype = env.observation_dtype
        self.frames = env.frames
        self.paths: list[Path] = []
        self.scores: list[float] = []
        self._out_dir, self._env_name, self._games = out_dir, env_name, games
        self._video_format, self._fps, self._scale = video_format, fps, scale
        self._writer: _Mp4Writer | _GifWriter | None = None
        self._partial_path = out_dir / "unused"  # the file being written
        self._score = 0.0
        self._frame_shape: tuple[int, ...] | None = None
        env.frame_callback = self._write_frame

    @property
    def game_ended(self) -> bool:
        return self.env.game_ended

    def reset(self, new_game: bool = False) -> np.ndarray:
        if self._writer is None:
            self._start_game()
        observation = self.env.reset(new_game)
        self.frames = self.env.frames
        return observation

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool]:
        observation, reward, terminated, truncated = self.env.step(action)
        self.frames = self.env.frames
        self._score += reward
        if self.env.game_ended:
            self._finish_game()
        return observation, reward, terminated, truncated

    def _start_game(self) -> None:
        stem = _game_stem(self._env_name, len(self.paths) + 1, self._games)
        self._partial_path = self._out_dir / f"{stem}.partial.{self._video_format}"
        if self._video_format == "mp4":
            self._writer = _Mp4Writer(self._partial_path, self._fps, self._scale)
        else:
            self._writer = _GifWriter(self._partial_path, self._fps, _gif_stride(self._fps))
        self._score = 0.0

    def _write_frame(self, frame: Any) -> None:
        if self._frame_shape is None:
            _check_frame(frame)
            self._frame_shape = frame.shape
        elif frame.shape != self._frame_shape:
            raise DqnlabError(f"frames changed size from {self._frame_shape} to {frame.shape}")
        if self._writer is not None:
            self._writer.append(frame[..., :3])

    def _finish_game(self) -> None:
        assert self._writer is not None
        self._writer.close()
        self._writer = None
        name = video_file_name(
            self._env_name, len(self.paths) + 1, self._games, self._score, self._video_format
        )
        path = self._out_dir / name
        os.replace(self._partial_path, path)
        self.paths.append(path)
        self.scores.append(self._score)

    def close(self) -> None:
        """Stop filming; a game not finished is deleted."""
        self.env.frame_callback = None
        if self._writer is not None:
            writer, self._writer = self._writer, None
            with contextlib.suppress(Exception):  # an error is already on its way up
                writer.close()
            self._partial_path.unlink(missing_ok=True)

    def state_dict(self) -> dict[str, Any]:
        return self.env.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.env.load_state_dict(state)


def _check_frame(frame: Any) -> None:
    if not (
        isinstance(frame, np.ndarray)
        and frame.dtype == np.uint8
        and frame.ndim == 3
        and frame.shape[2] in (3, 4)
    ):
        what = (
            f"an array of {frame.dtype} {frame.shape}"
            if isinstance(frame, np.ndarray)
            else repr(frame)
        )
        raise DqnlabError(
            f"the environment renders {what}, not an RGB image (uint8, height x width x 3)"
        )


def _filming_fps(env: AtariEnv | GymnasiumEnv, env_name: str) -> float:
    """The frame rate of `env`'s raw frames; an error if it cannot be filmed."""
    if isinstance(env, AtariEnv):
        return ATARI_FPS
    render_modes = env.env.metadata.get("render_modes") or ()
    if env.env.render_mode != "rgb_array" or "rgb_array" not in render_modes:
        raise DqnlabError(
            f"{env_name} cannot be filmed: videos need an environment that renders with "
            f"render_mode 'rgb_array' (it offers {list(render_modes)}, made with "
            f"{env.env.render_mode!r})"
        )
    return float(env.env.metadata.get("render_fps") or DEFAULT_RENDER_FPS)


def gif_delay_centiseconds(fps: float, stride: int) -> int:
    """A GIF frame's delay: whole hundredths of a second, 2 at least (browsers show
    shorter delays as 10)."""
    return max(2, round(100 * stride / fps))


def _gif_stride(fps: float) -> int:
    return max(1, math.ceil(fps / GIF_MAX_FPS))


def record_games(
    agent: Agent,
    config: Config,
    episodes: int,
    seed: int,
    out_dir: Path,
    *,
    epsilon: float,
    max_episode_frames: int,
    video_format: str = "auto",
) -> Recording:
    """Play `episodes` whole games as `play_games(..., num_envs=1)` does (the same seed,
    the same scores) and film each into `out_dir` as `video_file_name` names it.

    The games are `play(agent, env, ..., max_episodes=episodes)` on one environment seeded
    with child 0 of `seed`, wrapped to film them: ε-greedy at `epsilon`, random no-op
    starts, the `max_episode_frames` cap. An Atari video has one frame per emulator frame
    of its game: the screen after the reset, the no-ops, then every frame of every action
    repeat (1 + the game's frames); a Gymnasium video one per reset and step. A file is
    written as `*.partial.*` and renamed when its game ends; films of this environment
    from an earlier recording into `out_dir` are deleted first. `video_format`: "auto" (MP4, GIF
    where MP4 cannot be written), "mp4" or "gif".
    """
    if episodes <= 0:
        raise ValueError(f"episodes must be positive, got {episodes}")
    chosen_format, note = choose_video_format(video_format)
    env_seed = derive_seeds(seed, 1)[0]  # as play_games seeds its first environment
    env = _env_to_film(config, env_seed, max_episode_frames)
    try:
        assert isinstance(env, (AtariEnv, GymnasiumEnv))  # all that make_env builds
        fps = _filming_fps(env, config.env)
        if chosen_format == "gif":
            stride = _gif_stride(fps)
            shown = 100 / gif_delay_centiseconds(fps, stride)
            kept = f"1 frame in {stride} kept, {shown:.3g} frames/s"
            note = f"{note}; {kept}" if note else kept
        out_dir.mkdir(parents=True, exist_ok=True)
        _remove_earlier_films(out_dir, config.env)
        scale = ATARI_MP4_SCALE if isinstance(env, AtariEnv) else 1
        recorder = _GameRecorder(env, out_dir, config.env, episodes, chosen_format, fps, scale)
        try:
            result = play(agent, recorder, config.history_length, epsilon, max_episodes=episodes)
        finally:
            recorder.close()
    finally:
        env.close()
    if recorder.scores != result.scores:  # the names must carry the scores play counted
        raise RuntimeError(f"filmed scores {recorder.scores} != played {result.scores}")
    gif_fps = 100 / gif_delay_centiseconds(fps, _gif_stride(fps))
    file_fps = gif_fps if chosen_format == "gif" else fps
    return Recording(result, recorder.paths, chosen_format, file_fps, note)


def _env_to_film(config: Config, seed: int, max_episode_frames: int) -> Environment:
    """The evaluation environment, made to render RGB frames where it is not Atari's."""
    try:
        return make_env(
            config,
            training=False,
            seed=seed,
            max_episode_frames=max_episode_frames,
            render_mode=None if is_atari(config.env) else "rgb_array",
        )
    except TypeError as error:  # from gym.make: a constructor without render_mode
        raise DqnlabError(
            f"{config.env} cannot be filmed: it cannot be made with render_mode 'rgb_array' "
            f"({error})"
        ) from None


def filmed_final_evaluation(
    run_dir: Path,
    checkpoint: str,
    episodes: int | None,
    seed: int,
    device: torch.device,
    out_dir: Path,
    video_format: str,
    settings: dict[str, Any] | None = None,
) -> tuple[Recording, EvaluatedNetwork]:
    """`evaluate.final_evaluation`'s games of a run's network (played as `settings` say,
    where given), on one environment (as with num_envs=1) and filmed into `out_dir`."""
    if video_format not in VIDEO_FORMATS:
        raise DqnlabError(f"--video-format {video_format!r}: choose {', '.join(VIDEO_FORMATS)}")
    if episodes is not None and episodes <= 0:
        raise DqnlabError(f"--episodes {episodes} must be positive")
    network = load_evaluated_agent(run_dir, checkpoint, seed, device, settings)
    config = network.config
    recording = record_games(
        network.agent,
        config,
        episodes if episodes is not None else config.final_eval_episodes,
        network.env_seed,
        out_dir,
        epsilon=config.eval_epsilon,
        max_episode_frames=config.final_eval_max_episode_frames,
        video_format=video_format,
    )
    return recording, network
