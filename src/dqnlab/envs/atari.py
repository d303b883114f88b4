"""Atari through ale-py, processed exactly as DeepMind's Lua code (alewrap + Scale.lua) did.

Timeline of one agent step with action repeat 4 (frames f1..f4 are raw 60 Hz frames):

    action a ─► f1 ─► f2 ─► f3 ─► f4        rewards of f1..f4 are summed
                             └─max─┘          RGB max of the last two painted frames,
                                │             then luminance, then area resize to 84x84
                          observation

The repeat stops early at game over and, in training with `life_loss_terminal`, at the
frame a life is lost (alewrap GameEnvironment:step). The two-frame pool is cleared at
every episode start (GameEnvironment:newGame calls GameScreen:clear) and then holds only
frames of the new episode, so with one painted frame the observation is that frame.

Episode starts follow GameEnvironment:nextRandomGame(k), k = torch.random(30) (alewrap
GameEnvironment.lua L131-156; docs/lua-sources.md section 1): newGame() clears the pool and
paints one `_step(0)`, then come k - 1 and one more `_step(0)`. After game over that first
`_step(0)` emulates nothing: AleEnv:envStep (AleEnv.lua L89-101) sees the game is over,
calls resetGame and returns the new game's first screen. After a lost life (training) it is
a real no-op frame. So a new game starts with exactly k raw no-op frames after the reset, and
a game that continues after a lost life with exactly k + 1; k is uniform in
1..noop_max_frames (Lua random_starts = 30), and 0 when noop_max_frames is 0 (Lua newGame()
alone). No-op frames are not repeated and their rewards are dropped.
"""

from __future__ import annotations

import io
import pickle
from collections.abc import Callable, Mapping
from typing import Any

import cv2
import numpy as np
from ale_py import Action, ALEInterface, ALEState, LoggerMode, roms

from dqnlab.config import CHOICES
from dqnlab.errors import EnvError

RAW_FRAME_SHAPE = (210, 160, 3)
# The accepted values are the configuration's (`config.CHOICES`).
FRAME_POOLINGS = CHOICES["frame_pooling"]
GRAYSCALES = CHOICES["grayscale"]
BYTE_CONVERSIONS = CHOICES["byte_conversion"]
_INTERPOLATIONS = {"area": cv2.INTER_AREA, "bilinear": cv2.INTER_LINEAR}
assert set(_INTERPOLATIONS) == set(CHOICES["resize_interpolation"])
# ITU-R BT.601 luminance, as torch's image.rgb2y in the Lua code (a 1x3 matrix for cv2).
_LUMINANCE = np.array([[0.299, 0.587, 0.114]], dtype=np.float32)
# ALE's getScreenGrayscale: rounded 0.2989 R + 0.5870 G + 0.1140 B (checked on real frames).
_ALE_GRAYSCALE = np.array([[0.2989, 0.5870, 0.1140]], dtype=np.float32)
_TRUNCATION_GUARD = np.float32(1e-3)


def game_names() -> list[str]:
    return sorted(roms.get_all_rom_ids())


class FramePreprocessor:
    """`preprocess` with its intermediate images preallocated: no allocation per call.

    The defaults are the Lua code's; the alternatives are the other sources' choices:
    `pooling="max_gray"` takes the max after grayscale (Dopamine), `grayscale="ale"` is
    ALE's own grayscale (0.2989/0.5870/0.1140, rounded to integers; Dopamine, Gymnasium),
    `byte_conversion="round"` rounds instead of truncating (OpenCV, PIL).
    """

    def __init__(
        self,
        size: int = 84,
        interpolation: str = "area",
        pooling: str = "max_rgb",
        grayscale: str = "luminance",
        byte_conversion: str = "truncate",
    ) -> None:
        for name, value, accepted in (
            ("interpolation", interpolation, tuple(_INTERPOLATIONS)),
            ("pooling", pooling, FRAME_POOLINGS),
            ("grayscale", grayscale, GRAYSCALES),
            ("byte_conversion", byte_conversion, BYTE_CONVERSIONS),
        ):
            if value not in accepted:
                raise ValueError(f"{name} {value!r} is not one of {list(accepted)}")
        self.size = size
        self._interpolation = _INTERPOLATIONS[interpolation]
        self._pooling = pooling
        self._weights = _ALE_GRAYSCALE if grayscale == "ale" else _LUMINANCE
        self._round_gray = grayscale == "ale"
        self._truncate = byte_conversion == "truncate"
        self._pooled = np.empty(RAW_FRAME_SHAPE, dtype=np.uint8)
        self._rgb_float = np.empty(RAW_FRAME_SHAPE, dtype=np.float32)
        self._gray = np.empty(RAW_FRAME_SHAPE[:2], dtype=np.float32)
        self._gray_previous = np.empty(RAW_FRAME_SHAPE[:2], dtype=np.float32)
        self._resized = np.empty((size, size), dtype=np.float32)

    def _to_gray(self, rgb: np.ndarray, out: np.ndarray) -> None:
        np.copyto(self._rgb_float, rgb)
        cv2.transform(self._rgb_float, self._weights, dst=out)
        if self._round_gray:
            np.rint(out, out=out)

    def __call__(
        self, previous_rgb: np.ndarray, last_rgb: np.ndarray, out: np.ndarray
    ) -> np.ndarray:
        if self._pooling == "max_rgb":
            cv2.max(previous_rgb, last_rgb, dst=self._pooled)
            self._to_gray(self._pooled, self._gray)
        elif self._pooling == "max_gray":
            self._to_gray(previous_rgb, self._gray_previous)
            self._to_gray(last_rgb, self._gray)
            np.maximum(self._gray, self._gray_previous, out=self._gray)
        else:
            self._to_gray(last_rgb, self._gray)
        cv2.resize(
            self._gray,
            (self.size, self.size),
            dst=self._resized,
            interpolation=self._interpolation,
        )
        # Both kernels average with non-negative weights summing to one: no clipping needed.
        if self._truncate:
            # The Lua code's (uint8)(255 * y). The 1/1000 grey level keeps float noise (an
            # exact 142 computed as 141.99998) from costing a level, as it often did in the
            # Lua code's float32 arithmetic (docs/nature.md, "Where dqnlab departs from the
            # Lua code").
            np.add(self._resized, _TRUNCATION_GUARD, out=self._resized)
            np.floor(self._resized, out=self._resized)
        else:
            np.rint(self._resized, out=self._resized)
        np.copyto(out, self._resized, casting="unsafe")
        return out


def preprocess(
    previous_rgb: np.ndarray,
    last_rgb: np.ndarray,
    size: int = 84,
    interpolation: str = "area",
    out: np.ndarray | None = None,
) -> np.ndarray:
    """One agent observation from the last two raw RGB frames of an action repeat.

    Pixel-wise max per RGB channel, then luminance in floating point, then the whole
    210x160 frame resized to `size`x`size` (area averaging when shrinking), truncated to
    uint8 as the Lua code stores it, `(uint8)(255 * y)` (TransitionTable.lua L290, L302).
    """
    if out is None:
        out = np.empty((size, size), dtype=np.uint8)
    return FramePreprocessor(size, interpolation)(previous_rgb, last_rgb, out)


class AtariEnv:
    """One Atari game, stepped one agent action at a time.

    `training=True` makes a lost life terminal for the TD target (when
    `life_loss_terminal`) while the game itself goes on; `reset()` then continues the same
    game after fresh no-ops, as the Lua code's nextRandomGame does. Evaluation
    (`training=False`) plays whole games.
    """

    def __init__(
        self,
        game: str,
        *,
        seed: int,
        training: bool,
        action_repeat_frames: int = 4,
        frame_pooling: str = "max_rgb",
        grayscale: str = "luminance",
        byte_conversion: str = "truncate",
        resize_interpolation: str = "area",
        screen_size: int = 84,
        noop_max_frames: int = 30,
        sticky_action_probability: float = 0.0,
        full_action_space: bool = False,
        life_loss_terminal: bool = True,
        max_episode_frames: int = 0,
    ) -> None:
        if game not in roms.get_all_rom_ids():
            raise EnvError(f"unknown Atari game {game!r}")
        if frame_pooling not in FRAME_POOLINGS:
            raise ValueError(f"frame_pooling {frame_pooling!r} is not one of {FRAME_POOLINGS}")
        self.ale = _emulator(game, seed, sticky_action_probability)
        actions = (
            self.ale.getLegalActionSet() if full_action_space else self.ale.getMinimalActionSet()
        )
        self.game = game
        self.actions = list(actions)
        self.action_names = [a.name for a in self.actions]
        self.num_actions = len(self.actions)
        self.observation_shape: tuple[int, ...] = (screen_size, screen_size)
        self.observation_dtype = np.dtype(np.uint8)
        self.training = training
        self.action_repeat_frames = action_repeat_frames
        self.resize_interpolation = resize_interpolation
        self.screen_size = screen_size
        self.noop_max_frames = noop_max_frames
        self.life_loss_terminal = life_loss_terminal and training
        self.max_episode_frames = max_episode_frames
        self.rng = np.random.default_rng(seed)
        self._preprocess = FramePreprocessor(
            screen_size, resize_interpolation, frame_pooling, grayscale, byte_conversion
        )
        # Two raw frames, written alternately: the pool of GameScreen (size 2).
        self._screens = np.zeros((2, *RAW_FRAME_SHAPE), dtype=np.uint8)
        self._newest = 0
        self._observation = np.zeros(self.observation_shape, dtype=np.uint8)
        self._lives = 0  # lives after the previous agent step (Lua _state.lives)
        self._game_frames = 0
        self.frames = 0  # raw frames emulated by this environment, no-ops included
        self.game_over = True  # no game started yet
        self.truncated = False
        # Called with every raw frame painted, no-ops included: the RGB screen (210, 160, 3)
        # in a buffer that a later frame overwrites. For videos; None costs one test a frame.
        self.frame_callback: Callable[[np.ndarray], None] | None = None

    # Raw frames ---------------------------------------------------------------------

    def _paint(self) -> None:
        """Put the current screen in the pool (GameScreen:paint)."""
        self._newest ^= 1
        screen = self._screens[self._newest]
        self.ale.getScreenRGB(screen)
        if self.frame_callback is not None:
            self.frame_callback(screen)

    def _act_frame(self, action: Action) -> float:
        reward = self.ale.act(action)
        self._paint()
        self._game_frames += 1
        self.frames += 1
        return float(reward)

    def _observe(self) -> np.ndarray:
        return self._preprocess(
            self._screens[self._newest ^ 1], self._screens[self._newest], self._observation
        )

    # Agent steps --------------------------------------------------------------------

    def reset(self, new_game: bool = False) -> np.ndarray:
        """Start an agent episode, as GameEnvironment:nextRandomGame does.

        A new game after game over or the episode cap (or when `new_game`): reset, paint its
        first screen, then k raw no-op frames. Otherwise (a life was lost in training) the
        game continues: one no-op frame, then k more. k is uniform in 1..noop_max_frames
        (Lua random_starts = 30, `torch.random(30)`), 0 when noop_max_frames is 0.
        """
        self._screens.fill(0)  # GameScreen:clear
        if new_game or self.game_ended:
            self.ale.reset_game()
            self._game_frames = 0
            self.game_over = False
            self.truncated = False
            self._paint()
        else:
            self._act_frame(Action.NOOP)
        noops = int(self.rng.integers(1, self.noop_max_frames + 1)) if self.noop_max_frames else 0
        for _ in range(noops):
            self._act_frame(Action.NOOP)
            if self.ale.game_over():  # a game cannot normally end during no-ops
                self.ale.reset_game()
                self._game_frames = 0
        self._lives = self.ale.lives()
        return self._observe()

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool]:
        """Repeat `action`; return (observation, summed raw reward, terminated, truncated).

        `terminated` means no bootstrap: game over, or a lost life in training with
        `life_loss_terminal`. `truncated` means the episode cap was reached.
        """
        ale_action = self.actions[action]
        reward = 0.0
        terminated = False
        for _ in range(self.action_repeat_frames):
            reward += self._act_frame(ale_action)
            if self.ale.game_over():
                self.game_over = terminated = True
                break
            # Against the lives before this step, as GameEnvironment:step compares with
            # self._state.lives.
            if self.life_loss_terminal and self.ale.lives() < self._lives:
                terminated = True
                break
            if self.max_episode_frames and self._game_frames >= self.max_episode_frames:
                break
        self._lives = self.ale.lives()
        if self.max_episode_frames and self._game_frames >= self.max_episode_frames:
            self.truncated = not self.game_over
        return self._observe(), reward, terminated, self.truncated and not terminated

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly: the emulator (with its RNG), the pool."""
        import torch  # kept out of the environment workers' imports

        return {
            # ale-py's own serialisation, read back by ALEState(bytes): no pickle.
            "ale_state": self.ale.cloneState(include_rng=True).serialize(),
            "rng": self.rng.bit_generator.state,
            "screens": torch.from_numpy(self._screens.copy()),
            "newest": self._newest,
            "lives": self._lives,
            "game_frames": self._game_frames,
            "frames": self.frames,
            "game_over": self.game_over,
            "truncated": self.truncated,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.ale.restoreState(_emulator_state(state))
        self.rng.bit_generator.state = state["rng"]
        self._screens[...] = state["screens"].numpy()
        self._newest = int(state["newest"])
        self._lives = int(state["lives"])
        self._game_frames = int(state["game_frames"])
        self.frames = int(state["frames"])
        self.game_over = bool(state["game_over"])
        self.truncated = bool(state["truncated"])

    @property
    def game_ended(self) -> bool:
        """The scored game is over (game over or episode cap), not just a life."""
        return self.game_over or self.truncated

    def close(self) -> None:
        pass


def _emulator(game: str, seed: int, sticky_action_probability: float) -> ALEInterface:
    """ale-py's emulator with `game` loaded."""
    ALEInterface.setLoggerMode(LoggerMode.Error)
    ale = ALEInterface()
    ale.setInt("random_seed", int(seed) % (2**31))
    ale.setFloat("repeat_action_probability", float(sticky_action_probability))
    ale.setInt("frame_skip", 1)  # `AtariEnv.step` repeats, to pool and watch lives
    ale.setInt("max_num_frames_per_episode", 0)  # `AtariEnv.step` applies the cap
    rom = roms.get_rom_path(game)
    if rom is None:  # game_names() lists only the ROMs ale-py ships
        raise EnvError(f"ale-py ships no ROM for {game!r}")
    ale.loadROM(rom)
    return ale


class _EmulatorStateUnpickler(pickle.Unpickler):
    """Unpickles an ALEState and refuses every other class or function: a pickle can call
    only what `find_class` returns (Python's pickle docs, "Restricting Globals")."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == (ALEState.__module__, ALEState.__name__):
            return ALEState
        raise pickle.UnpicklingError(f"{module}.{name} is not an emulator state")


def _emulator_state(state: Mapping[str, Any]) -> ALEState:
    """The emulator state of `AtariEnv.state_dict`, or of an earlier checkpoint's."""
    try:
        if "ale_state" in state:
            return ALEState(state["ale_state"])
        # Earlier checkpoints hold pickle.dumps(ALEState): unpickling one calls
        # ALEState.__setstate__ on the same serialised bytes, and nothing else is allowed.
        emulator = _EmulatorStateUnpickler(io.BytesIO(state["ale"])).load()
    except Exception as error:  # noqa: BLE001 - ale-py raises SystemError for bad bytes
        raise EnvError(f"the checkpoint's emulator state cannot be restored ({error})") from None
    if not isinstance(emulator, ALEState):
        raise EnvError(f"the checkpoint's emulator state is a {type(emulator).__name__}")
    return emulator
