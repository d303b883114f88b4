"""How a Gymnasium environment is made (envs/__init__.py, envs/registry.py): its
`env_kwargs`, its `env_wrappers` in order, ids that installed packages provide through
`gymnasium.envs` entry points, and each bad input as one line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.envs import registration

from dqnlab import envs
from dqnlab.config import Config, resolve_config
from dqnlab.envs import _make_gymnasium, check_env, check_env_name, make_env, registry
from dqnlab.errors import EnvError
from tests.helpers import dqnlab

MODULE = __name__
REPOSITORY = Path(__file__).parents[2]


class CountEnv(gym.Env):
    """A game of `length` steps (no default: it must be given), +1 a step; the observation
    is `width` copies of the step."""

    def __init__(self, length: int, width: int = 2) -> None:
        self.length = length
        self.observation_space = gym.spaces.Box(0.0, 1e3, (width,), np.float32)
        self.action_space = gym.spaces.Discrete(2)
        self.t = 0
        self.trail: list[str] = []  # the wrappers, in the order they were applied

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(self.observation_space.shape, np.float32), {}

    def step(self, action):
        self.t += 1
        observation = np.full(self.observation_space.shape, self.t, np.float32)
        return observation, 1.0, self.t >= self.length, False, {}


COUNT = f"{MODULE}:CountEnv"


class Marked(gym.Wrapper):
    def __init__(self, env: gym.Env, mark: str) -> None:
        super().__init__(env)
        self.mark = mark
        env.unwrapped.trail.append(mark)


def first(env: gym.Env) -> gym.Env:
    return Marked(env, "first")


def second(env: gym.Env) -> gym.Env:
    return Marked(env, "second")


class DoubleReward(gym.RewardWrapper):
    def reward(self, reward):
        return 2 * reward


def not_an_env(env: gym.Env) -> int:
    return 42


def raises(env: gym.Env) -> gym.Env:
    raise ValueError("no wrapping today\non two lines")


NOT_CALLABLE = 3


def test_env_kwargs_reach_a_gymnasium_id() -> None:
    env = _make_gymnasium("FrozenLake-v1", None, {"map_name": "8x8", "is_slippery": False})
    assert env.observation_space == gym.spaces.Discrete(64)
    assert env.unwrapped.desc.shape == (8, 8)
    # Not slippery: each action of each state leads to exactly one next state.
    transitions = env.unwrapped.P
    assert all(len(outcomes) == 1 for state in transitions.values() for outcomes in state.values())
    slippery = _make_gymnasium("FrozenLake-v1")
    assert slippery.observation_space == gym.spaces.Discrete(16)
    assert len(slippery.unwrapped.P[0][0]) == 3


def test_env_kwargs_reach_the_environment_through_make_env() -> None:
    plain = make_env(Config(env="CartPole-v1"), training=True, seed=0)
    config = Config(env="CartPole-v1", env_kwargs={"sutton_barto_reward": True})
    sutton_barto = make_env(config, training=True, seed=0)
    plain.reset(), sutton_barto.reset()
    assert plain.step(0)[1] == 1.0 and sutton_barto.step(0)[1] == 0.0  # 0 until the pole falls
    counted = make_env(Config(env=COUNT, env_kwargs={"length": 3, "width": 5}), training=True,
                       seed=0)  # fmt: skip
    assert counted.observation_shape == (5,)
    counted.reset()
    assert [counted.step(0)[2] for _ in range(3)] == [False, False, True]


def test_an_environment_that_rejects_its_kwargs_says_so_in_one_line() -> None:
    with pytest.raises(EnvError) as error:
        _make_gymnasium("FrozenLake-v1", None, {"slippery": False})
    assert str(error.value) == (
        "FrozenLake-v1: env_kwargs rejected: TypeError: FrozenLakeEnv.__init__() got an "
        "unexpected keyword argument 'slippery'"
    )
    with pytest.raises(EnvError, match=r"^FrozenLake-v1: env_kwargs rejected: KeyError: '9x9'$"):
        check_env_name("FrozenLake-v1", env_kwargs={"map_name": "9x9"})
    with pytest.raises(EnvError) as error:
        make_env(Config(env=COUNT, env_kwargs={"length": 3, "height": 2}), training=True, seed=0)
    message = str(error.value)
    assert message.startswith(f"{COUNT}: env_kwargs rejected: TypeError: ")
    assert "unexpected keyword argument 'height'" in message and "\n" not in message
    # Without env_kwargs, a constructor's TypeError is the factory failing, as before.
    with pytest.raises(EnvError, match=f"environment factory '{COUNT}' failed"):
        check_env_name(COUNT)


@pytest.mark.filterwarnings("ignore::UserWarning")  # Gymnasium's, about a render_mode
def test_env_kwargs_and_the_render_mode_of_videos_go_together() -> None:
    filmed = _make_gymnasium("CartPole-v1", "rgb_array", {"sutton_barto_reward": True})
    assert filmed.render_mode == "rgb_array" and filmed.unwrapped._sutton_barto_reward
    if "DqnlabArgsTest/Count-v0" not in gym.registry:
        gym.register("DqnlabArgsTest/Count-v0", entry_point=CountEnv)
    # A constructor without render_mode: gym.make's TypeError, which videos turn into their
    # own message ("cannot be filmed"), not the kwargs' fault.
    with pytest.raises(TypeError, match="render_mode"):
        _make_gymnasium("DqnlabArgsTest/Count-v0", "rgb_array", {"length": 2})
    # A factory is given env_kwargs only, as it was given no argument before.
    assert _make_gymnasium(COUNT, "rgb_array", {"length": 2}).unwrapped.length == 2


def test_wrappers_are_applied_in_order() -> None:
    wrappers = (f"{MODULE}:first", f"{MODULE}:second", f"{MODULE}:DoubleReward")
    env = _make_gymnasium(COUNT, None, {"length": 2}, wrappers)
    assert env.unwrapped.trail == ["first", "second"]
    assert isinstance(env, DoubleReward) and env.env.mark == "second"
    assert env.env.env.mark == "first"
    reversed_order = _make_gymnasium(COUNT, None, {"length": 2}, wrappers[1::-1])
    assert reversed_order.unwrapped.trail == ["second", "first"]
    config = Config(env=COUNT, env_kwargs={"length": 2}, env_wrappers=wrappers)
    game = make_env(config, training=False, seed=0)
    game.reset()
    assert game.step(1)[1] == 2.0  # DoubleReward, the outermost wrapper
    check_env(config)


@pytest.mark.parametrize(
    ("wrapper", "message"),
    [
        ("no_such_module_for_dqnlab.wrappers:Clip",
         "wrapper 'no_such_module_for_dqnlab.wrappers:Clip': cannot import "
         "no_such_module_for_dqnlab.wrappers: No module named 'no_such_module_for_dqnlab'"),
        (f"{MODULE}:missing", f"wrapper '{MODULE}:missing': module {MODULE} has no missing"),
        (f"{MODULE}:NOT_CALLABLE",
         f"wrapper '{MODULE}:NOT_CALLABLE': module {MODULE} has no callable NOT_CALLABLE"),
        (f"{MODULE}:not_an_env",
         f"wrapper '{MODULE}:not_an_env' did not return a gymnasium.Env (got int)"),
        (f"{MODULE}:raises",
         f"wrapper '{MODULE}:raises' failed: ValueError: no wrapping today on two lines"),
    ],
)  # fmt: skip
def test_a_wrapper_that_cannot_be_used_is_one_line_naming_it(wrapper: str, message: str) -> None:
    with pytest.raises(EnvError) as error:
        make_env(Config(env="CartPole-v1", env_wrappers=(wrapper,)), training=True, seed=0)
    assert str(error.value) == message
    with pytest.raises(EnvError):
        check_env_name("CartPole-v1", env_wrappers=[wrapper])


def test_atari_games_take_dqnlab_settings_not_env_kwargs_or_wrappers() -> None:
    config = resolve_config("nature", env="pong", env_kwargs={"mode": 1})
    with pytest.raises(EnvError) as error:
        make_env(config, training=True, seed=0)
    assert str(error.value).startswith(
        "pong: env_kwargs apply to Gymnasium environments; an Atari game runs dqnlab's own "
        "ale-py pipeline, whose options are dqnlab settings (--set, e.g. "
    )
    with pytest.raises(EnvError, match="^breakout: env_kwargs and env_wrappers apply to"):
        check_env_name("breakout", env_kwargs={"mode": 1}, env_wrappers=[f"{MODULE}:first"])
    with pytest.raises(EnvError, match="^pong: env_wrappers apply to"):
        check_env(resolve_config("nature", env="pong", env_wrappers=[f"{MODULE}:first"]))
    check_env_name("pong")  # without them, as before


def test_observation_images_reaches_the_gymnasium_env(monkeypatch: pytest.MonkeyPatch) -> None:
    seen = []

    class Recorder(envs.GymnasiumEnv):
        def __init__(self, env: gym.Env, **kwargs) -> None:  # noqa: ANN003
            seen.append(kwargs.pop("observation_images", "auto"))
            super().__init__(env, **kwargs)

    monkeypatch.setattr(envs, "GymnasiumEnv", Recorder)
    make_env(Config(env="CartPole-v1", observation_images="none"), training=True, seed=0)
    check_env(Config(env="CartPole-v1", observation_images="all"))
    make_env(Config(env="CartPole-v1"), training=True, seed=0)
    assert seen == ["none", "all", "auto"]


# Ids from installed packages ------------------------------------------------------------

PLUGIN = "dqnlab_test_plugin"
PLUGIN_CODE = """
import gymnasium as gym
import numpy as np


class GridEnv(gym.Env):
    def __init__(self, side=3):
        self.observation_space = gym.spaces.Box(0.0, 1.0, (side,), np.float32)
        self.action_space = gym.spaces.Discrete(4)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(self.observation_space.shape, np.float32), {}

    def step(self, action):
        return np.zeros(self.observation_space.shape, np.float32), 0.0, True, False, {}


CALLS = []


def register():
    CALLS.append("register")
    gym.register(id="Grid-v0", entry_point=GridEnv)  # under the entry point's name


def broken():
    raise RuntimeError("this plugin is broken")
"""


@pytest.fixture
def plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):  # noqa: ANN201
    """A package installed into a temporary directory that registers DqnlabPlugin/Grid-v0
    only through its `gymnasium.envs` entry point, as a package installed by pip does."""
    (tmp_path / PLUGIN).mkdir()
    (tmp_path / PLUGIN / "__init__.py").write_text(PLUGIN_CODE)
    info = tmp_path / f"{PLUGIN}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: dqnlab-test-plugin\nVersion: 1.0\n"
    )
    (info / "entry_points.txt").write_text(
        f"[gymnasium.envs]\nDqnlabPlugin = {PLUGIN}:register\nDqnlabBroken = {PLUGIN}:broken\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "_loaded", set())
    yield
    gym.registry.pop("DqnlabPlugin/Grid-v0", None)
    sys.modules.pop(PLUGIN, None)


@pytest.mark.usefixtures("plugin")
def test_an_id_of_an_installed_package_is_found_through_its_entry_point() -> None:
    assert "DqnlabPlugin/Grid-v0" not in gym.registry  # Gymnasium 1.x does not load it
    env = _make_gymnasium("DqnlabPlugin/Grid-v0", None, {"side": 5})
    assert env.observation_space.shape == (5,)
    assert "DqnlabPlugin/Grid-v0" in gym.registry
    check_env_name("DqnlabPlugin/Grid-v0")  # loaded once: its function ran once
    assert sys.modules[PLUGIN].CALLS == ["register"]
    assert make_env(Config(env="DqnlabPlugin/Grid-v0"), training=True, seed=0).num_actions == 4


@pytest.mark.usefixtures("plugin")
def test_an_id_still_missing_names_close_matches_and_where_it_looked() -> None:
    with pytest.raises(EnvError) as error:
        check_env_name("DqnlabPlugin/Gird-v0")
    message = str(error.value)
    assert message.startswith("unknown environment 'DqnlabPlugin/Gird-v0': not an ale-py Atari")
    assert "close matches: DqnlabPlugin/Grid-v0" in message
    assert "looked in the gymnasium.envs entry points of: dqnlab-test-plugin" in message
    assert "broken" not in message  # only the entry point named after the namespace
    with pytest.raises(EnvError) as error:
        check_env_name("NoSuchNamespace/Game-v1")  # no entry point of its name: all of them
    message = str(error.value)
    assert (
        "DqnlabBroken = dqnlab_test_plugin:broken failed: RuntimeError('this plugin is" in message
    )
    assert "\n" not in message
    assert registration.current_namespace is None  # ids registered later keep their names


def test_without_entry_points_the_message_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(registry, "_entry_points", list)
    with pytest.raises(EnvError) as error:
        check_env_name("CartPole-v9")
    message = str(error.value)
    assert "close matches: CartPole-v1" in message
    assert "no installed package has gymnasium.envs entry points" in message


# The command line ------------------------------------------------------------------------


def test_train_with_env_kwargs_and_wrappers_then_evaluate_and_resume(tmp_path: Path) -> None:
    """The run's config.toml holds them, so evaluate and resume build the same environment:
    CountEnv cannot be made without `length`, and its score says which length and wrapper."""
    run = tmp_path / "count"
    trained = dqnlab(
        "train", "--env", COUNT, "--env-kwarg", "length=7", "--env-kwarg", "width=3",
        "--wrapper", f"{MODULE}:DoubleReward", "--steps", "300", "--run-dir", str(run),
        "--set", "replay_start_steps=100", "--set", "eval_period_steps=150",
        "--set", "eval_steps=50", "--set", "mlp_hidden_sizes=[8]", "--set", "batch_size=8",
        "--no-progress", cwd=REPOSITORY,
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    text = (run / "config.toml").read_text()
    assert "env_kwargs = {length = 7, width = 3}" in text
    assert f'env_wrappers = ["{MODULE}:DoubleReward"]' in text
    out = tmp_path / "eval.json"
    evaluated = dqnlab("evaluate", str(run), "--episodes", "2", "--json", str(out), cwd=REPOSITORY)
    assert evaluated.returncode == 0, evaluated.stderr
    assert json.loads(out.read_text())["scores"] == [14.0, 14.0]  # 7 steps, reward doubled
    inspected = dqnlab("inspect", str(run), "--frames", "2", "--checkpoints", "best",
                       cwd=REPOSITORY)  # fmt: skip
    assert inspected.returncode == 0, inspected.stderr
    resumed = dqnlab("resume", str(run), "--steps", "400", "--no-progress", cwd=REPOSITORY)
    assert resumed.returncode == 0, resumed.stderr
    assert "400 steps" in resumed.stdout


def test_bad_env_kwargs_and_wrappers_on_the_command_line(tmp_path: Path) -> None:
    """(The training test above shows `length=7` read as the integer it is.)"""
    rejected = dqnlab(
        "train", "--env", "FrozenLake-v1", "--env-kwarg", "is_slippery=false",
        "--env-kwarg", "map_name=9x9", "--run-dir", str(tmp_path / "lake"),
    )  # fmt: skip
    assert rejected.returncode == 2  # 9x9 not being TOML, FrozenLake got the string "9x9"
    assert rejected.stderr == "dqnlab: error: FrozenLake-v1: env_kwargs rejected: KeyError: '9x9'\n"
    bad = dqnlab("train", "--env", "CartPole-v1", "--env-kwarg", "sutton_barto_reward",
                 "--run-dir", str(tmp_path / "pole"))  # fmt: skip
    assert bad.returncode == 2 and "--env-kwarg expects KEY=VALUE" in bad.stderr
    unimportable = dqnlab("train", "--env", "CartPole-v1", "--wrapper", "no_such_dqnlab_mod:W",
                          "--run-dir", str(tmp_path / "pole"))  # fmt: skip
    assert unimportable.returncode == 2
    assert unimportable.stderr.startswith(
        "dqnlab: error: wrapper 'no_such_dqnlab_mod:W': cannot import no_such_dqnlab_mod"
    )
    assert not (tmp_path / "lake").exists() and not (tmp_path / "pole").exists()
