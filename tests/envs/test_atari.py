"""The Atari pipeline (envs/atari.py) against ALE driven frame by frame and values by hand.

The reference ALE below gets the same seed and the same calls as the environment's own
(sticky actions off, so ALE is deterministic), and the test replays by hand what DeepMind's
Lua code (alewrap GameEnvironment.lua) does with it.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from ale_py import Action, ALEInterface, LoggerMode, roms

from dqnlab.config import Config
from dqnlab.envs import make_env
from dqnlab.envs.atari import AtariEnv, FramePreprocessor, preprocess

ALEInterface.setLoggerMode(LoggerMode.Error)
LUMINANCE = (0.299, 0.587, 0.114)


# Independent references ---------------------------------------------------------------


def area_weights(source_length: int, target_length: int) -> np.ndarray:
    """(target, source) matrix: the exact overlap of each source pixel with each target pixel.

    Target pixel i covers [i * s, (i + 1) * s) of the source with s = source / target
    (2.5 for 210 -> 84 rows, 160/84 for columns); each weight is the overlap length / s.
    """
    scale = source_length / target_length
    weights = np.zeros((target_length, source_length))
    for i in range(target_length):
        low, high = i * scale, (i + 1) * scale
        for j in range(int(np.floor(low)), int(np.ceil(high))):
            weights[i, j] = max(0.0, min(high, j + 1) - max(low, j)) / scale
    return weights


ROW_WEIGHTS = area_weights(210, 84)
COLUMN_WEIGHTS = area_weights(160, 84)


def exact_luminance_average(previous_rgb: np.ndarray, last_rgb: np.ndarray) -> np.ndarray:
    """Max per RGB channel, luminance, explicit area averaging, in float64 (0..255 scale).

    Works on one pair of frames or on a batch (leading axes)."""
    pooled = np.maximum(previous_rgb.astype(np.float64), last_rgb.astype(np.float64))
    luminance = (
        LUMINANCE[0] * pooled[..., 0]
        + LUMINANCE[1] * pooled[..., 1]
        + LUMINANCE[2] * pooled[..., 2]
    )
    return ROW_WEIGHTS @ luminance @ COLUMN_WEIGHTS.T


def reference_observation(previous_rgb: np.ndarray, last_rgb: np.ndarray) -> np.ndarray:
    """The exact-arithmetic value truncated to a byte."""
    return np.floor(exact_luminance_average(previous_rgb, last_rgb) + 1e-6)


def _lua_shrink(source: np.ndarray, target_length: int, axis: int) -> np.ndarray:
    """torch/image Main_scaleLinear_rowcol, its shrinking branch, float by float in float32."""
    f32 = np.float32
    source = np.moveaxis(source, axis, 0)
    source_length = source.shape[0]
    target = np.empty((target_length, *source.shape[1:]), np.float32)
    scale = f32(source_length) / f32(target_length)
    si0_i, si0_f = 0, f32(0)
    for di in range(target_length):
        si1_f = f32(di + 1) * scale
        si1_i = int(si1_f)
        si1_f = f32(si1_f - f32(si1_i))
        acc = (f32(1) - si0_f) * source[si0_i]
        n = f32(1) - si0_f
        for si in range(si0_i + 1, si1_i):
            acc = acc + source[si]
            n = n + f32(1)
        if si1_i < source_length:
            acc = acc + si1_f * source[si1_i]
            n = n + si1_f
        target[di] = acc / n
        si0_i, si0_f = si1_i, si1_f
    return np.moveaxis(target, 0, axis)


def lua_float32_observation(previous_rgb: np.ndarray, last_rgb: np.ndarray) -> np.ndarray:
    """The bytes DeepMind's Lua code stored, its float32 arithmetic replayed operation by
    operation (one pair of frames or a batch): GameScreen:paint divides the RGB bytes by 255
    in float32 (alewrap GameScreen.lua L134) and pools with a max; image.rgb2y sums
    0.299 r + 0.587 g + 0.114 b in double and casts to float (torch/image Main_rgb2y);
    image.scale shrinks every row 160 -> 84, then every column 210 -> 84, accumulating in
    float32 (Main_scaleBilinear); TransitionTable multiplies by 255 in float32 and casts to
    a byte (TransitionTable.lua L290, L302)."""
    previous = previous_rgb.astype(np.float32) / np.float32(255)
    last = last_rgb.astype(np.float32) / np.float32(255)
    red, green, blue = np.moveaxis(np.maximum(previous, last).astype(np.float64), -1, 0)
    luminance = (0.299 * red + 0.587 * green + 0.114 * blue).astype(np.float32)
    rows_shrunk = _lua_shrink(luminance, 84, axis=-1)
    resized = _lua_shrink(rows_shrunk, 84, axis=-2)
    return (resized * np.float32(255)).astype(np.uint8)


def reference_ale(game: str, seed: int) -> ALEInterface:
    ale = ALEInterface()
    ale.setInt("random_seed", seed)
    ale.setFloat("repeat_action_probability", 0.0)
    ale.setInt("frame_skip", 1)
    ale.setInt("max_num_frames_per_episode", 0)
    ale.loadROM(roms.get_rom_path(game))
    return ale


def real_frames(game: str, seed: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Two consecutive raw frames after `frames` frames of random play."""
    ale = reference_ale(game, seed)
    actions = ale.getMinimalActionSet()
    rng = np.random.default_rng(seed)
    for _ in range(frames):
        ale.act(actions[rng.integers(len(actions))])
    previous = ale.getScreenRGB()
    ale.act(actions[rng.integers(len(actions))])
    return previous, ale.getScreenRGB()


def random_play(game: str, seed: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """The last two raw frames of each of `steps` agent steps of a uniformly random policy
    (action repeat 4, a new game after game over), stacked: two (steps, 210, 160, 3)."""
    ale = reference_ale(game, seed)
    actions = ale.getMinimalActionSet()
    rng = np.random.default_rng(seed)
    screens = np.empty((2, steps, 210, 160, 3), np.uint8)
    for step in range(steps):
        action = actions[rng.integers(len(actions))]
        for frame in range(4):
            ale.act(action)
            if frame >= 2:
                ale.getScreenRGB(screens[frame - 2, step])
        if ale.game_over():
            ale.reset_game()
    return screens[0], screens[1]


class LuaReplay:
    """A second ALE driven by hand as GameEnvironment.lua drives its emulator."""

    def __init__(self, game: str, seed: int, training: bool) -> None:
        self.ale = reference_ale(game, seed)
        self.actions = self.ale.getMinimalActionSet()
        self.training = training
        self.pool: list[np.ndarray] = []
        self.lives = 0

    def paint(self) -> None:
        self.pool = [*self.pool[-1:], self.ale.getScreenRGB()]

    def start(self, noop_frames: int, new_game: bool) -> np.ndarray:
        """newGame (clear; reset after game over, else one real no-op) and the no-ops."""
        self.pool = [np.zeros((210, 160, 3), np.uint8)]
        if new_game:
            self.ale.reset_game()
            self.paint()
        for _ in range(noop_frames):
            self.ale.act(Action.NOOP)
            self.paint()
        self.lives = self.ale.lives()
        return preprocess(self.pool[0], self.pool[1])

    def step(self, action: int, repeat: int = 4) -> tuple[np.ndarray, float, bool, int]:
        reward, terminal, frames = 0.0, False, 0
        for _ in range(repeat):
            reward += self.ale.act(self.actions[action])
            frames += 1
            self.paint()
            terminal = self.ale.game_over() or (self.training and self.ale.lives() < self.lives)
            if terminal:
                break
        self.lives = self.ale.lives()
        return preprocess(self.pool[0], self.pool[1]), reward, terminal, frames


# Preprocessing --------------------------------------------------------------------------


@pytest.mark.parametrize(("game", "seed"), [("breakout", 1), ("pong", 2), ("seaquest", 3)])
def test_preprocess_matches_an_independent_implementation_on_real_frames(game, seed):
    previous, last = random_play(game, seed, steps=40)
    assert (previous != last).any(), "need frames that differ"
    observations = np.stack([preprocess(p, q) for p, q in zip(previous, last, strict=True)])
    assert observations.shape == (40, 84, 84)
    assert observations.dtype == np.uint8
    stored = observations.astype(np.int64)
    # Exact arithmetic: the same byte, or (float32 cannot tell a value 1e-5 below a level
    # from the level) one more where the exact value is within 1/1000 below it.
    exact = exact_luminance_average(previous, last)
    above = stored - reference_observation(previous, last)
    assert set(np.unique(above)) <= {0, 1}
    assert (above == 0).mean() > 0.99
    assert (stored[above == 1] - exact[above == 1] < 1e-3).all()
    # The Lua code's float32 arithmetic stored exact levels such as Breakout's wall (142)
    # one lower where its float noise fell below the level: dqnlab is one above there, and
    # equal elsewhere (README, "Where dqnlab departs from the Lua code").
    over_lua = stored - lua_float32_observation(previous, last)
    assert set(np.unique(over_lua)) <= {0, 1}
    assert (np.abs(exact[over_lua == 1] - stored[over_lua == 1]) < 1e-3).all()
    if game != "pong":  # Pong's greys are no exact levels
        assert (over_lua == 1).mean() > 0.02


def test_lua_float32_arithmetic_stores_a_uniform_grey_one_lower_in_places():
    grey = np.full((210, 160, 3), 142, np.uint8)  # Breakout's wall, Y = 142 exactly
    assert (preprocess(grey, grey) == 142).all()
    lua = lua_float32_observation(grey, grey)
    assert set(np.unique(lua)) == {141, 142}  # 142 / 255 * 255 in float32, cell by cell
    black = np.zeros_like(grey)
    assert (lua_float32_observation(black, black) == 0).all()
    white = np.full_like(grey, 255)
    assert (lua_float32_observation(white, white) == 255).all()


@pytest.mark.slow
def test_share_of_pixels_one_level_above_the_lua_codes_bytes():
    """The README's figures: 2,000 observations of random play per game (half a minute)."""
    # % of pixels one level above the Lua code's bytes, and above the exact-arithmetic level.
    expected = {"breakout": (8.63, 0.0), "pong": (0.0, 0.0), "seaquest": (6.88, 0.06)}
    for game, (over_lua_percent, over_exact_percent) in expected.items():
        previous, last = random_play(game, seed=0, steps=2000)
        over_lua = over_exact = 0
        for start in range(0, 2000, 250):
            batch = slice(start, start + 250)
            pairs = zip(previous[batch], last[batch], strict=True)
            stored = np.stack([preprocess(p, q) for p, q in pairs]).astype(np.int64)
            difference = stored - lua_float32_observation(previous[batch], last[batch])
            assert set(np.unique(difference)) <= {0, 1}
            over_lua += int((difference == 1).sum())
            over_exact += int((stored > reference_observation(previous[batch], last[batch])).sum())
        pixels = 2000 * 84 * 84
        assert 100 * over_lua / pixels == pytest.approx(over_lua_percent, abs=0.01), game
        assert 100 * over_exact / pixels == pytest.approx(over_exact_percent, abs=0.01), game


def test_area_weights_by_hand():
    # 210 -> 84 rows: output rows 0 and 1 share source row 2 half and half.
    assert np.allclose(ROW_WEIGHTS[0, :3], [0.4, 0.4, 0.2])
    assert np.allclose(ROW_WEIGHTS[1, 2:5], [0.2, 0.4, 0.4])
    assert np.allclose(ROW_WEIGHTS.sum(axis=1), 1.0)
    # 160 -> 84 columns: each output column covers 40/21 source columns.
    assert np.allclose(COLUMN_WEIGHTS[0, :2], [21 / 40, 19 / 40])
    assert np.allclose(COLUMN_WEIGHTS.sum(axis=1), 1.0)


def test_preprocess_pools_rgb_before_luminance():
    red = np.zeros((210, 160, 3), np.uint8)
    red[..., 0] = 255
    green = np.zeros((210, 160, 3), np.uint8)
    green[..., 1] = 255
    # max in RGB is yellow (255, 255, 0): 0.299 * 255 + 0.587 * 255 = 225.93, stored 225.
    assert (preprocess(red, green) == 225).all()
    assert (preprocess(green, red) == 225).all()
    # Grey first, then max (Dopamine's order): max(76.245, 149.685) -> 149 instead.
    red_gray = red.astype(np.float64) @ LUMINANCE
    green_gray = green.astype(np.float64) @ LUMINANCE
    assert (np.floor(np.maximum(red_gray, green_gray)) == 149).all()


@pytest.mark.parametrize("in_previous", [True, False])
def test_flickering_object_in_one_frame_appears(in_previous):
    background, _ = real_frames("pong", 3, frames=60)
    with_object = background.copy()
    with_object[100:120, 80:100] = 255  # a white object drawn on one frame only
    previous, last = (with_object, background) if in_previous else (background, with_object)
    observation = preprocess(previous, last)
    # Rows 100..120 / 2.5 = 40..48, columns 80..100 / (160/84) = 42..52.5, fully covered.
    assert (observation[40:48, 42:52] == 255).all()
    assert (preprocess(background, background)[40:48, 42:52] < 255).all()
    difference = np.abs(observation.astype(np.int64) - reference_observation(previous, last))
    assert difference.max() <= 1


def test_preprocess_writes_into_out():
    previous, last = real_frames("breakout", 4, frames=20)
    out = np.full((84, 84), 7, np.uint8)
    assert preprocess(previous, last, out=out) is out
    assert np.array_equal(out, preprocess(previous, last))


# No-op starts ---------------------------------------------------------------------------


def test_noop_starts_are_uniform_in_1_to_noop_max_frames():
    env = AtariEnv("pong", seed=5, training=True, noop_max_frames=30)
    counts = []
    for _ in range(300):
        before = env.frames
        env.reset(new_game=True)
        counts.append(env.frames - before)
        assert env.ale.getEpisodeFrameNumber() == counts[-1]
    assert min(counts) == 1
    assert max(counts) == 30
    assert len(set(counts)) == 30
    # Roughly uniform: each value 10 times on average.
    assert max(np.bincount(counts)) < 25


def test_no_noops_when_noop_max_frames_is_zero():
    env = AtariEnv("pong", seed=5, training=True, noop_max_frames=0)
    replay = LuaReplay("pong", seed=5, training=True)
    for _ in range(3):
        before = env.frames
        observation = env.reset(new_game=True)
        assert env.frames == before
        # The observation is the new game's first screen alone (the pool was cleared).
        assert np.array_equal(observation, replay.start(0, new_game=True))


def test_noop_starts_differ_between_seeds_and_repeat_with_a_seed():
    def counts(seed):
        env = AtariEnv("pong", seed=seed, training=True)
        result = []
        for _ in range(10):
            before = env.frames
            env.reset(new_game=True)
            result.append(env.frames - before)
        return result

    assert counts(11) == counts(11)
    assert counts(11) != counts(12)


# Action repeat and pooling against the frame-by-frame replay ------------------------------


@pytest.mark.parametrize("frame_pooling", ["max_rgb", "none"])
def test_action_repeat_and_pooling_match_frame_by_frame_replay(frame_pooling):
    seed = 21
    env = AtariEnv("pong", seed=seed, training=True, frame_pooling=frame_pooling)
    replay = LuaReplay("pong", seed=seed, training=True)
    rng = np.random.default_rng(0)
    rewards = []
    before = env.frames
    observation = env.reset()
    noops = env.frames - before
    assert 1 <= noops <= 30
    expected = replay.start(noops, new_game=True)
    if frame_pooling == "max_rgb":
        assert np.array_equal(observation, expected)
    for _ in range(400 if frame_pooling == "max_rgb" else 60):
        action = int(rng.integers(env.num_actions))
        before = env.frames
        observation, reward, terminated, truncated = env.step(action)
        expected, expected_reward, expected_terminal, frames = replay.step(action)
        assert env.frames - before == frames == 4  # Pong has no lives and lasts long
        assert reward == expected_reward
        assert not terminated and not truncated and not expected_terminal
        if frame_pooling == "max_rgb":
            assert np.array_equal(observation, expected)
        else:
            last = replay.pool[1]
            assert np.array_equal(observation, preprocess(last, last))
        rewards.append(reward)
    if frame_pooling == "max_rgb":
        assert any(r != 0 for r in rewards), "the replay should see points scored"


# Life loss -------------------------------------------------------------------------------


def test_life_loss_is_terminal_in_training_and_the_game_continues():
    seed = 3
    env = AtariEnv("breakout", seed=seed, training=True)
    replay = LuaReplay("breakout", seed=seed, training=True)
    rng = np.random.default_rng(1)
    before = env.frames
    observation = env.reset()
    assert np.array_equal(observation, replay.start(env.frames - before, new_game=True))
    life_losses = games = short_steps = 0
    continue_noops = []
    while games < 2:
        lives = env.ale.lives()
        action = int(rng.integers(env.num_actions))
        before = env.frames
        observation, reward, terminated, truncated = env.step(action)
        expected, expected_reward, expected_terminal, frames = replay.step(action)
        assert env.frames - before == frames
        assert reward == expected_reward
        assert terminated == expected_terminal
        assert np.array_equal(observation, expected)
        assert not truncated
        short_steps += frames < 4
        if not terminated:
            assert frames == 4
            continue
        if env.game_ended:  # game over: the next reset starts a new game
            assert env.ale.game_over()
            games += 1
            before = env.frames
            observation = env.reset()
            noops = env.frames - before
            assert 1 <= noops <= 30
            assert env.ale.lives() == 5
            assert env.ale.getEpisodeFrameNumber() == noops
            assert np.array_equal(observation, replay.start(noops, new_game=True))
            continue
        # A life lost, at exactly the frame the replay saw it.
        life_losses += 1
        assert not env.ale.game_over()
        assert env.ale.lives() == lives - 1
        episode_frame = env.ale.getEpisodeFrameNumber()
        before = env.frames
        observation = env.reset()
        noops = env.frames - before
        continue_noops.append(noops)
        # Lua newGame's one no-op frame, then nextRandomGame's k in 1..30: 2..31 frames.
        assert 2 <= noops <= 31
        assert env.ale.lives() == lives - 1, "reset must not restore the lives"
        assert env.ale.getEpisodeFrameNumber() == episode_frame + noops, "no ALE reset"
        assert np.array_equal(observation, replay.start(noops, new_game=False))
    assert life_losses >= 8
    assert short_steps > 0


def test_pool_is_cleared_when_the_game_continues_after_a_lost_life():
    # With noop_max_frames 0 only newGame's one no-op frame is played after a lost life,
    # so the observation shows that frame alone, not pooled with the frame the life was lost.
    env = AtariEnv("breakout", seed=8, training=True, noop_max_frames=0)
    rng = np.random.default_rng(2)
    env.reset()
    checked = 0
    while not env.game_ended:
        _, _, terminated, _ = env.step(int(rng.integers(env.num_actions)))
        if terminated and not env.game_ended:
            frame_of_life_loss = env.ale.getScreenRGB()
            before = env.frames
            observation = env.reset()
            assert env.frames - before == 1
            first = env.ale.getScreenRGB()
            assert np.array_equal(observation, preprocess(first, first))
            checked += not np.array_equal(observation, preprocess(frame_of_life_loss, first))
    assert checked > 0, "some life-loss frame should differ from the next one"


def test_evaluation_plays_whole_games():
    env = AtariEnv("breakout", seed=4, training=False)
    rng = np.random.default_rng(3)
    env.reset()
    lives_seen = {env.ale.lives()}
    steps = 0
    while True:
        before = env.frames
        _, _, terminated, truncated = env.step(int(rng.integers(env.num_actions)))
        steps += 1
        lives_seen.add(env.ale.lives())
        assert not truncated
        if terminated:
            break
        assert env.frames - before == 4
    assert env.game_ended and env.ale.game_over()
    assert lives_seen == {5, 4, 3, 2, 1, 0}
    before = env.frames
    env.reset()
    assert env.ale.lives() == 5
    assert env.ale.getEpisodeFrameNumber() == env.frames - before


def test_life_loss_not_terminal_in_training_without_life_loss_terminal():
    env = AtariEnv("breakout", seed=4, training=True, life_loss_terminal=False)
    rng = np.random.default_rng(3)
    env.reset()
    while True:
        _, _, terminated, _ = env.step(int(rng.integers(env.num_actions)))
        if terminated:
            break
    assert env.ale.game_over() and env.ale.lives() == 0


# Episode cap ----------------------------------------------------------------------------


def test_episode_cap_truncates_and_the_next_reset_starts_a_new_game():
    cap = 101  # not a multiple of 4: the cap cuts an action repeat short
    env = AtariEnv("pong", seed=6, training=True, max_episode_frames=cap)
    rng = np.random.default_rng(4)
    for _ in range(2):
        game_start = env.frames
        env.reset()
        while True:
            _, _, terminated, truncated = env.step(int(rng.integers(env.num_actions)))
            assert not terminated
            if truncated:
                break
            assert not env.game_ended
        assert env.frames - game_start == cap
        assert env.ale.getEpisodeFrameNumber() == cap
        assert env.game_ended and not env.ale.game_over()
    env.reset()
    assert env.ale.getEpisodeFrameNumber() <= 30, "a new game after the cap"


def test_life_lost_on_the_cap_frame_ends_the_game():
    def play(cap):
        env = AtariEnv("breakout", seed=9, training=True, max_episode_frames=cap)
        rng = np.random.default_rng(5)
        env.reset()
        while True:
            _, _, terminated, truncated = env.step(int(rng.integers(env.num_actions)))
            if terminated or truncated:
                return env, (terminated, truncated)

    env, result = play(0)
    assert result == (True, False) and not env.game_ended  # the first life lost
    life_lost_frame = env.ale.getEpisodeFrameNumber()
    env, result = play(life_lost_frame)
    assert result == (True, False)  # no bootstrap: the life is lost
    assert env.game_ended, "but the cap ends the game"
    env.reset()
    assert env.ale.lives() == 5


def test_episode_cap_in_evaluation():
    env = AtariEnv("breakout", seed=6, training=False, max_episode_frames=40, noop_max_frames=0)
    env.reset()
    results = [env.step(1)[2:] for _ in range(10)]
    assert results == [(False, False)] * 9 + [(False, True)]
    assert env.frames == 40


# ALE settings -----------------------------------------------------------------------------


def test_action_sets_and_sticky_actions_reach_ale():
    minimal = AtariEnv("pong", seed=0, training=True)
    assert minimal.num_actions == 6
    assert minimal.action_names == ["NOOP", "FIRE", "RIGHT", "LEFT", "RIGHTFIRE", "LEFTFIRE"]
    assert minimal.ale.getFloat("repeat_action_probability") == 0.0
    full = AtariEnv(
        "pong", seed=0, training=True, full_action_space=True, sticky_action_probability=0.25
    )
    assert full.num_actions == 18
    assert full.action_names[:3] == ["NOOP", "FIRE", "UP"]
    assert full.ale.getFloat("repeat_action_probability") == pytest.approx(0.25)


def test_make_env_passes_the_atari_settings():
    config = Config(
        env="pong",
        sticky_action_probability=0.25,
        full_action_space=True,
        noop_max_frames=7,
        action_repeat_frames=3,
        max_episode_frames=500,
    )
    env = make_env(config, training=True, seed=1)
    assert isinstance(env, AtariEnv)
    assert env.num_actions == 18
    assert env.ale.getFloat("repeat_action_probability") == pytest.approx(0.25)
    assert (env.noop_max_frames, env.action_repeat_frames) == (7, 3)
    assert env.max_episode_frames == 500 and env.life_loss_terminal
    assert env.observation_shape == (84, 84) and env.observation_dtype == np.uint8
    evaluation = make_env(config, training=False, seed=1, max_episode_frames=18_000)
    assert evaluation.max_episode_frames == 18_000 and not evaluation.life_loss_terminal


def test_unknown_game_raises():
    from dqnlab.errors import EnvError

    with pytest.raises(EnvError):
        AtariEnv("pongg", seed=0, training=True)


def test_other_sources_preprocessing_choices() -> None:

    red = np.zeros((210, 160, 3), np.uint8)
    red[..., 0] = 255
    green = np.zeros((210, 160, 3), np.uint8)
    green[..., 1] = 255
    out = np.empty((84, 84), np.uint8)
    # Dopamine's order, grey then max: max(0.299 * 255, 0.587 * 255) = 149.685.
    assert (FramePreprocessor(pooling="max_gray")(red, green, out) == 149).all()
    # Rounding instead of the Lua code's truncation: 225.93 -> 226.
    assert (FramePreprocessor(byte_conversion="round")(red, green, out) == 226).all()
    # Only the last frame.
    assert (FramePreprocessor(pooling="none")(red, green, out) == 149).all()


def test_ale_grayscale_matches_ales_own() -> None:

    ale = reference_ale("breakout", 4)
    actions = ale.getMinimalActionSet()
    for t in range(120):
        ale.act(actions[t % len(actions)])
    rgb, gray = ale.getScreenRGB(), ale.getScreenGrayscale()
    expected = np.rint(cv2.resize(gray.astype(np.float32), (84, 84), interpolation=cv2.INTER_AREA))
    preprocess = FramePreprocessor(pooling="none", grayscale="ale", byte_conversion="round")
    np.testing.assert_array_equal(preprocess(rgb, rgb, np.empty((84, 84), np.uint8)), expected)
