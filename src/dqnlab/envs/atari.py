"""Atari through ale-py, processed exactly as DeepMind's Lua code (alewrap + Scale.lua) did.

Timeline of one agent step with action repeat 4 (frames f1..f4 are raw 60 Hz frames):

    action a ─► f1 ─► f2 ─► f3 ─► f4        rewards of f1..f4 are summed
                             └─max─┘          RGB max of the last two painted frames,
                                │             then luminance, then area resize to 84x84
                          observation

The repeat stops early at game over and, in training with `life_loss_terminal`, at the
frame a life is lost (alewrap GameEnvironment:step). The two-frame buffer is cleared at
every episode start (GameEnvironment:newGame calls GameScreen:clear), so the first
observation of an episode is the last no-op frame pooled with zeros, i.e. itself.
"""

from __future__ import annotations

import cv2
import numpy as np
from ale_py import Action, ALEInterface, LoggerMode, roms

from dqnlab.errors import EnvironmentError_

RAW_FRAME_SHAPE = (210, 160, 3)
_INTERPOLATIONS = {"area": cv2.INTER_AREA, "bilinear": cv2.INTER_LINEAR}
# ITU-R BT.601 luminance, as torch's image.rgb2y in the Lua code.
_LUMINANCE = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def game_names() -> list[str]:
    return sorted(roms.get_all_rom_ids())


def preprocess(
    previous_rgb: np.ndarray,
    last_rgb: np.ndarray,
    size: int = 84,
    interpolation: str = "area",
    out: np.ndarray | None = None,
) -> np.ndarray:
    """One agent observation from the last two raw RGB frames of an action repeat.

    Pixel-wise max per RGB channel, then luminance in floating point, then the whole
    210x160 frame resized to `size`x`size` (area averaging when shrinking), rounded to uint8.
    """
    pooled = np.maximum(previous_rgb, last_rgb).astype(np.float32)
    luminance = pooled @ _LUMINANCE
    resized = cv2.resize(luminance, (size, size), interpolation=_INTERPOLATIONS[interpolation])
    if out is None:
        out = np.empty((size, size), dtype=np.uint8)
    np.clip(np.rint(resized), 0, 255, out=resized)
    out[...] = resized
    return out


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
        resize_interpolation: str = "area",
        screen_size: int = 84,
        noop_max_frames: int = 30,
        sticky_action_probability: float = 0.0,
        full_action_space: bool = False,
        life_loss_terminal: bool = True,
        max_episode_frames: int = 0,
    ) -> None:
        if game not in roms.get_all_rom_ids():
            raise EnvironmentError_(f"unknown Atari game {game!r}")
        ALEInterface.setLoggerMode(LoggerMode.Error)
        self.ale = ALEInterface()
        self.ale.setInt("random_seed", int(seed) % (2**31))
        self.ale.setFloat("repeat_action_probability", float(sticky_action_probability))
        self.ale.setInt("frame_skip", 1)  # the repeat is done here, to pool and watch lives
        self.ale.setInt("max_num_frames_per_episode", 0)  # the cap is applied here
        self.ale.loadROM(roms.get_rom_path(game))
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
        self.pool = frame_pooling == "max_rgb"
        self.resize_interpolation = resize_interpolation
        self.screen_size = screen_size
        self.noop_max_frames = noop_max_frames
        self.life_loss_terminal = life_loss_terminal and training
        self.max_episode_frames = max_episode_frames
        self.rng = np.random.default_rng(seed)
        # Two raw frames, written alternately: the pool of GameScreen (size 2).
        self._screens = np.zeros((2, *RAW_FRAME_SHAPE), dtype=np.uint8)
        self._newest = 0
        self._observation = np.zeros(self.observation_shape, dtype=np.uint8)
        self._lives = 0
        self._game_frames = 0
        self.frames = 0  # raw frames emulated by this environment, no-ops included
        self.game_over = True  # no game started yet
        self.truncated = False

    # Raw frames ---------------------------------------------------------------------

    def _act_frame(self, action: object) -> float:
        reward = self.ale.act(action)
        self._newest ^= 1
        self.ale.getScreenRGB(self._screens[self._newest])
        self._game_frames += 1
        self.frames += 1
        return float(reward)

    def _clear_screens(self) -> None:
        self._screens.fill(0)

    def _observe(self) -> np.ndarray:
        newest = self._screens[self._newest]
        previous = self._screens[self._newest ^ 1] if self.pool else newest
        return preprocess(
            previous, newest, self.screen_size, self.resize_interpolation, self._observation
        )

    # Agent steps --------------------------------------------------------------------

    def reset(self, new_game: bool = False) -> np.ndarray:
        """Start an agent episode: a new game after game over (or when `new_game`), else
        continue the game after a lost life.

        Then a random number of raw no-op frames, uniform in 1..noop_max_frames (Lua
        random_starts; `torch.random(30)`), on a cleared frame pool.
        """
        if new_game or self.game_over or self.truncated:
            self.ale.reset_game()
            self._game_frames = 0
            self.game_over = False
            self.truncated = False
        self._clear_screens()
        noops = int(self.rng.integers(1, self.noop_max_frames + 1)) if self.noop_max_frames else 0
        for _ in range(noops):
            self._act_frame(Action.NOOP)
            if self.ale.game_over():  # a game cannot normally end during no-ops
                self.ale.reset_game()
                self._game_frames = 0
        if noops == 0:
            self.ale.getScreenRGB(self._screens[self._newest])
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
            lives = self.ale.lives()
            if self.life_loss_terminal and lives < self._lives:
                terminated = True
                break
            self._lives = lives
            if self.max_episode_frames and self._game_frames >= self.max_episode_frames:
                self.truncated = True
                break
        return self._observe(), reward, terminated, self.truncated and not terminated

    @property
    def game_ended(self) -> bool:
        """The scored game is over (game over or episode cap), not just a life."""
        return self.game_over or self.truncated

    def close(self) -> None:
        pass
