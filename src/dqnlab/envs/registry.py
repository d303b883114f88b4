"""Gymnasium ids that installed packages provide through `gymnasium.envs` entry points,
and the one-line message for an id that is still unknown.

Gymnasium before 1.0 loaded every `gymnasium.envs` entry point when it was imported;
Gymnasium 1.x no longer does, so `SomePackage/Game-v1` is unknown until its package is
imported. dqnlab loads those entry points when an id is missing, the way Gymnasium did:
an entry point's name is the namespace its ids are registered under (`__root__`: none),
and its object, if a function, is called to register them.
"""

from __future__ import annotations

import contextlib
import difflib
from collections.abc import Iterator, Sequence
from importlib import metadata

import gymnasium as gym
from gymnasium.envs import registration
from gymnasium.envs.registration import parse_env_id

from dqnlab.envs.atari import game_names

ENTRY_POINT_GROUP = "gymnasium.envs"
ROOT_NAMESPACES = ("__root__", "__internal__")  # register their ids without a namespace
# Entry points loaded in this process (name, value), each once: loading one again would
# register its ids again.
_loaded: set[tuple[str, str]] = set()


def _namespace_of(env_id: str) -> str | None:
    try:
        return parse_env_id(env_id)[0]
    except gym.error.Error:  # not an id Gymnasium can parse: no namespace to look for
        return None


def _entry_points() -> list[metadata.EntryPoint]:
    return list(metadata.entry_points(group=ENTRY_POINT_GROUP))


def _source(entry_point: metadata.EntryPoint) -> str:
    """Where an entry point comes from: its distribution, else its module."""
    dist = getattr(entry_point, "dist", None)
    return dist.name if dist is not None else entry_point.module


@contextlib.contextmanager
def _namespace(name: str) -> Iterator[None]:
    """Gymnasium's `registration.namespace`, but restored also when an entry point raises
    (Gymnasium 1.x's is not: every id registered later in the process would get the
    broken plugin's namespace)."""
    before = registration.current_namespace
    registration.current_namespace = name
    try:
        yield
    finally:
        registration.current_namespace = before


def load_entry_points(env_id: str) -> tuple[list[str], list[str]]:
    """Load the `gymnasium.envs` entry points that may register `env_id`: those named
    after its namespace, or, when none is, every one not loaded yet. Returns the sources
    looked in (distributions or modules) and one-line notes of entry points that failed."""
    wanted = _namespace_of(env_id)
    candidates = _entry_points()
    named = [ep for ep in candidates if wanted is not None and ep.name == wanted]
    chosen = named or candidates
    sources, failures = [], []
    for entry_point in chosen:
        sources.append(_source(entry_point))
        key = (entry_point.name, entry_point.value)
        if key in _loaded:
            continue
        _loaded.add(key)
        scope = (
            contextlib.nullcontext()
            if entry_point.name in ROOT_NAMESPACES
            else _namespace(entry_point.name)
        )
        try:
            with scope:
                loaded = entry_point.load()  # importing the module may register the ids
                if entry_point.attr and callable(loaded):
                    loaded()
        except Exception as error:  # noqa: BLE001 - a broken plugin: say so, go on
            failures.append(f"{entry_point.name} = {entry_point.value} failed: {error!r}")
    return sorted(set(sources)), failures


def unknown_env_message(
    name: str, error: Exception, sources: Sequence[str] = (), failures: Sequence[str] = ()
) -> str:
    """One line: `name` is neither an Atari game nor a Gymnasium id, with the close
    matches, the packages whose entry points were looked in, and what to pass instead."""
    games = difflib.get_close_matches(name.lower().replace("-", "_"), game_names(), n=3)
    ids = difflib.get_close_matches(name, list(gym.registry.keys()), n=3, cutoff=0.5)
    close = games + [i for i in ids if i not in games]
    hint = f"; close matches: {', '.join(close)}" if close else ""
    looked = (
        f"; looked in the {ENTRY_POINT_GROUP} entry points of: {', '.join(sources)}"
        if sources
        else f"; no installed package has {ENTRY_POINT_GROUP} entry points"
    )
    broken = f"; {'; '.join(failures)}" if failures else ""
    reason = " ".join(str(error).split())
    return (
        f"unknown environment {name!r}: not an ale-py Atari game nor a registered Gymnasium id"
        f" ({reason}){hint}{looked}{broken}. Accepted: an Atari game (`dqnlab games` lists "
        "them), a Gymnasium id such as CartPole-v1 (also one an installed package provides), "
        "module:Env-id or module:EnvClass"
    )
