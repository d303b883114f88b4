"""Acting while learning (`concurrency = "actor-learner"`): a thread steps the training
environments while the training thread updates, a departure from the Lua code, which
alternates the two (docs/benchmark.md, "Acting while learning", says what changes and why
it is safe).

The run is a function of the seed alone, not of the threads' timing:

- The actor acts for agent steps t+1..t+N (one round, one batched forward) with the
  online network as it was after update m, where m is the last multiple of
  `actor_refresh_updates` (K) at least K updates before the u updates that the sequential
  loop would have made by step t (m = max(0, (u // K - 1) K)): K to 2K - 1 updates old.
  The learner copies the online network out after every K-th update; two copies are kept,
  the one the actor uses and the next.
- The learner stores round r's transitions, then makes the updates of its steps exactly as
  `TrainingState.advance` does: each update samples the replay holding the transitions up
  to its own step, so the replay ratio is Nature's. The learner waits when no round is
  ready; the actor waits when the copy it needs is not out yet, or when `pending` rounds
  are queued.
- The actor chooses with a generator of its own (and noise of its own, for noisy nets):
  the periodic evaluation, on the training thread, draws from the agent's as before, at
  whatever step the actor is.
- A checkpoint pauses the actor between two rounds and saves, besides the learner's
  state, the actor's (its step, emulators, histories, generators), the two network copies
  and the rounds acted but not yet learned from: a resumed run carries on exactly.

With `threaded=False` the same rounds are acted on the training thread, each when the
learner asks for it: the sequential reference the threaded run equals bit for bit.
"""

from __future__ import annotations

import copy
import threading
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from time import perf_counter
from typing import Any

import numpy as np
import torch
from torch import nn

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.config import Config, derive_seeds
from dqnlab.run.determinism import set_threads
from dqnlab.run.state import FinishedGame, TrainingState, choose_actions

# PyTorch's intra-op thread count is per thread (OpenMP's): on CPU the actor's batched
# forward of a few states takes one, and the training thread one fewer than it had, so
# that the two together do not ask for more cores than before (oversubscribed OpenMP
# threads wait for each other). The sequential reference switches the same way.
ACTOR_THREADS = 1


@dataclass
class ActedSteps:
    """One call's agent steps, acted and not yet learned from: what the replay is given."""

    first: int  # the agent step of its first environment
    observations: np.ndarray  # (environments, *frame shape): o_t of each, the newest frame
    actions: list[int]
    rewards: list[float]  # clipped as the replay stores them
    terminals: list[bool]
    last_observations: dict[int, np.ndarray]  # environment -> an ended episode's last frame
    finished: list[FinishedGame]
    frames: int  # training frames of all the environments after it
    epsilon: float  # of its last step

    def state_dict(self) -> dict[str, Any]:
        return {
            "first": self.first,
            "observations": torch.from_numpy(self.observations.copy()),
            "actions": list(self.actions),
            "rewards": list(self.rewards),
            "terminals": list(self.terminals),
            "last": [(i, torch.from_numpy(o.copy())) for i, o in self.last_observations.items()],
            "finished": [tuple(game) for game in self.finished],
            "frames": self.frames,
            "epsilon": self.epsilon,
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> ActedSteps:
        return cls(
            int(state["first"]),
            state["observations"].numpy(),
            [int(a) for a in state["actions"]],
            [float(r) for r in state["rewards"]],
            [bool(t) for t in state["terminals"]],
            {int(i): o.numpy() for i, o in state["last"]},
            [FinishedGame(*game) for game in state["finished"]],
            int(state["frames"]),
            float(state["epsilon"]),
        )


def actor_seed(config: Config) -> int:
    """The actor's own generator's seed: the eighth stream of the run seed (the training
    state's seven come first, unchanged)."""
    return derive_seeds(config.seed, 8)[7]


def training_state(
    config: Config, device: torch.device, replay: ReplayMemory | None = None
) -> TrainingState:
    """The training state `concurrency` asks for."""
    if config.concurrency == "actor-learner":
        return ActorLearnerState(config, device, replay)
    return TrainingState(config, device, replay)


class ActorLearnerState(TrainingState):
    """`TrainingState` with its environments stepped by an actor thread (module docstring).
    The actor starts at the first `advance` and stops at `close`; only the training thread
    touches the replay and the agent."""

    def __init__(
        self,
        config: Config,
        device: torch.device,
        replay: ReplayMemory | None = None,
        threaded: bool = True,
    ) -> None:
        super().__init__(config, device, replay)
        self.threaded = threaded
        self.refresh = config.actor_refresh_updates
        # The agent as the actor sees it: its policy, with the network copy, generator and
        # noise of the actor's own (a shallow copy: the networks it holds are not used).
        self.acting = copy.copy(self.agent)
        self.acting.rng = np.random.default_rng(actor_seed(config))
        self.acting.noise_generator = torch.Generator(device=device)
        self.acting.noise_generator.manual_seed(actor_seed(config))
        self.actor_steps = 0  # the agent steps acted (the learner's count is `steps`)
        # The update count u(t) is counted from where the actor starts: (step, updates).
        self.update_base = (0, 0)
        self.snapshots: dict[int, nn.Module] = {}  # update number -> the online net then
        self.pending: deque[ActedSteps] = deque()
        period = config.update_period_steps
        self.capacity = max(2, -(-2 * self.refresh * period // len(self.envs)))  # rounds
        self.learner_frames = sum(env.frames for env in self.envs)
        self.seconds["wait"] = 0.0  # the learner's, for a round
        self._lock = threading.Condition()
        self._thread: threading.Thread | None = None
        self._started = False
        self._pause = self._busy = self._stop = False
        self._acting_on: int | None = None  # the copy the actor is using, by update number
        self._error: BaseException | None = None
        self._threads: tuple[int, int] | None = None  # on CPU: (before, the learner's)
        self._threads_set = threading.Event()

    @property
    def frames(self) -> int:
        """Training frames of the rounds learned from (the actor may be ahead)."""
        return self.learner_frames

    @property
    def learner_threads(self) -> int | None:
        """The PyTorch threads the training thread runs with once started, on CPU (it sets
        them for the process: a benchmark that interleaves several states sets them back
        for the others); None on another device or before the first round."""
        return None if self._threads is None else self._threads[1]

    # The learner ----------------------------------------------------------------------

    def advance(self, max_steps: int | None = None) -> list[FinishedGame]:
        """The next round's transitions stored and its agent steps learned (`_learn`, as
        `TrainingState.advance`); returns its finished games."""
        start = perf_counter()
        self._start()
        round_ = self._next_round()
        waited = perf_counter()
        count = len(round_.actions)
        expected = len(self.envs) if max_steps is None else min(len(self.envs), max_steps)
        if count != expected or round_.first != self.steps + 1:
            raise ValueError(
                f"the actor's round is steps {round_.first}..{round_.first + count - 1}; "
                f"the learner asked for {expected} from step {self.steps + 1}"
            )
        for index in range(count):
            self.replay.add(
                round_.observations[index],
                round_.actions[index],
                round_.rewards[index],
                round_.terminals[index],
                index,
            )
            if index in round_.last_observations:
                self.replay.add_last(round_.last_observations[index], index)
        self.learner_frames, self.epsilon = round_.frames, round_.epsilon
        stored = perf_counter()
        for step in range(round_.first, round_.first + count):
            self.steps = step
            updates = self.agent.updates
            self._learn(step)
            if self.agent.updates != updates and self.agent.updates % self.refresh == 0:
                self._publish(self.agent.updates)
        seconds = self.seconds
        seconds["wait"] += waited - start
        seconds["store"] += stored - waited
        seconds["total"] += perf_counter() - start
        return round_.finished

    def _next_round(self) -> ActedSteps:
        if not self.threaded:
            if not self.pending:
                if self._threads is not None:
                    set_threads(ACTOR_THREADS)
                self.pending.append(self._act_round(self._snapshot_for(self.actor_steps)))
                if self._threads is not None:
                    set_threads(self._threads[1])
            return self.pending.popleft()
        with self._lock:
            while not self.pending:
                self._raise_actor_error()
                self._lock.wait()
            round_ = self.pending.popleft()
            self._lock.notify_all()
            return round_

    def _publish(self, update: int) -> None:
        """The online network as it is after update `update`, copied for the actor into
        the older of the two copies (which the actor no longer needs: the learner is past
        the round that used it, so the actor acts with this one or the one before)."""
        online = self.agent.online
        with self._lock:
            if len(self.snapshots) < 2:
                network = copy.deepcopy(online).requires_grad_(False)
            else:
                oldest = min(self.snapshots)
                if self._busy and self._acting_on == oldest:
                    raise RuntimeError(f"the actor still acts with update {oldest}'s network")
                network = self.snapshots.pop(oldest)
                with torch.no_grad():
                    for mine, theirs in zip(
                        network.state_dict().values(), online.state_dict().values(), strict=True
                    ):
                        mine.copy_(theirs)
            self.snapshots[update] = network
            self._lock.notify_all()

    # The actor ------------------------------------------------------------------------

    def _updates_before(self, step: int) -> int:
        """The updates the learner has made when it starts learning step `step` + 1."""
        config = self.config
        period, start = config.update_period_steps, config.replay_start_steps

        def update_steps_until(last: int) -> int:  # the steps in 1..last that update
            return last // period - start // period if last > start else 0

        base_step, base_updates = self.update_base
        return base_updates + update_steps_until(step) - update_steps_until(base_step)

    def _snapshot_for(self, step: int) -> nn.Module:
        """The network copy the round after agent step `step` acts with."""
        return self.snapshots[self._snapshot_update(step)]

    def _snapshot_update(self, step: int) -> int:
        """The update number of that copy: the last multiple of K at least K updates
        back, or the network the actor started with (update_base's) before there is one."""
        refresh = self.refresh
        newest = (self._updates_before(step) // refresh - 1) * refresh
        return max(self.update_base[1], newest)

    def _start(self) -> None:
        """At the first round: the first copy (the network as it is now), and the thread."""
        if self._started:
            return
        self._started = True
        if not self.snapshots:  # a new run (a resumed one brings its copies)
            self.update_base = (self.steps, self.agent.updates)
            self.actor_steps = self.steps
            self._publish(self.agent.updates)
        if self.agent.device.type == "cpu":
            before = torch.get_num_threads()
            self._threads = (before, max(1, before - ACTOR_THREADS))
        if self.threaded:
            self._thread = threading.Thread(target=self._actor, name="dqnlab-actor", daemon=True)
            self._thread.start()
            self._threads_set.wait()  # MKL's count is the process's: the learner's last
        if self._threads is not None:
            set_threads(self._threads[1])

    def _actor(self) -> None:
        try:
            if self._threads is not None:
                set_threads(ACTOR_THREADS)  # OpenMP's count: this thread's alone
            self._threads_set.set()
            while True:
                with self._lock:
                    while not self._ready():
                        if self._stop:
                            return
                        self._lock.wait()
                    self._busy, self._acting_on = True, self._snapshot_update(self.actor_steps)
                    network = self.snapshots[self._acting_on]
                round_ = self._act_round(network)
                with self._lock:
                    self.pending.append(round_)
                    self._busy = False
                    self._lock.notify_all()
        except BaseException as error:  # handed to the learner, which raises it
            with self._lock:
                self._error, self._busy = error, False
                self._lock.notify_all()
            self._threads_set.set()

    def _ready(self) -> bool:
        """Whether the actor may act its next round now (called holding the lock)."""
        return (
            not (self._pause or self._stop)
            and self.actor_steps < self.config.total_steps
            and len(self.pending) < self.capacity
            and self._snapshot_update(self.actor_steps) in self.snapshots
        )

    def _act_round(self, network: nn.Module) -> ActedSteps:
        """One agent step in each environment (fewer at the end of the budget), acted with
        `network`: the acting half of `TrainingState.advance`, handing the transitions on."""
        config, seconds = self.config, self.seconds
        count = min(len(self.envs), config.total_steps - self.actor_steps)
        first = self.actor_steps + 1
        start = perf_counter()
        self.acting.online = network
        actions, epsilons = choose_actions(self.acting, self.stacked, first, count, config)
        acted = perf_counter()
        # The observations acted on, copied at once: the histories move on as they step.
        observations = self.stacked[:count, -1].copy()
        rewards: list[float] = []
        terminals: list[bool] = []
        last: dict[int, np.ndarray] = {}

        def store(
            index: int, acted_on: np.ndarray, action: int, reward: float, terminal: bool
        ) -> None:
            rewards.append(reward)
            terminals.append(terminal)

        def store_last(index: int, observation: np.ndarray) -> None:
            last[index] = np.array(observation, copy=True)

        finished, _ = self.step_environments(actions, first, store, store_last)
        self.actor_steps = first + count - 1
        seconds["act"] += acted - start
        seconds["env"] += perf_counter() - acted
        frames = sum(env.frames for env in self.envs)
        return ActedSteps(
            first, observations, actions, rewards, terminals, last, finished, frames,
            epsilons[-1],
        )  # fmt: skip

    # Pausing, saving, resuming, closing ---------------------------------------------

    @contextmanager
    def _paused(self) -> Iterator[None]:
        """The actor held between two rounds (its state consistent) for the duration."""
        with self._lock:
            self._pause = True
            while self._busy:
                self._lock.wait()
            self._raise_actor_error()
        try:
            yield
        finally:
            with self._lock:
                self._pause = False
                self._lock.notify_all()

    def _raise_actor_error(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"the actor thread failed: {self._error!r}") from self._error

    def state_dict(self) -> dict[str, Any]:
        """`TrainingState.state_dict` (the environments as the actor left them) and the
        actor's own: its step, generators, the network copies and the pending rounds."""
        with self._paused():
            state = super().state_dict()
            state["actor"] = {
                "steps": self.actor_steps,
                "update_base": list(self.update_base),
                "rng": self.acting.rng.bit_generator.state,
                "noise_rng": self.acting.noise_generator.get_state(),
                "snapshots": [
                    (update, network.state_dict()) for update, network in self.snapshots.items()
                ],
                "pending": [round_.state_dict() for round_ in self.pending],
                "learner_frames": self.learner_frames,
            }
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if self._started:
            raise RuntimeError("the actor's state is loaded before the first round")
        super().load_state_dict(state)
        actor = state["actor"]
        self.actor_steps = int(actor["steps"])
        self.update_base = (int(actor["update_base"][0]), int(actor["update_base"][1]))
        self.acting.rng.bit_generator.state = actor["rng"]
        self.acting.noise_generator.set_state(actor["noise_rng"].cpu())
        self.snapshots = {}
        for update, weights in actor["snapshots"]:
            network = copy.deepcopy(self.agent.online).requires_grad_(False)
            network.load_state_dict(weights)
            self.snapshots[int(update)] = network
        self.pending = deque(ActedSteps.from_state_dict(saved) for saved in actor["pending"])
        self.learner_frames = int(actor["learner_frames"])

    def close(self) -> None:
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        if self._thread is not None:
            self._thread.join()
        if self._threads is not None:
            set_threads(self._threads[0])
            self._threads = None
        super().close()
