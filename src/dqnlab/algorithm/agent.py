"""The DQN agent: acting, the update and the target network.

One update for every member of the family: the loss part (`losses.build_loss`: the TD loss
of Nature and Double DQN, C51's cross-entropy, or a user's own) gives a loss and a priority
per transition; the agent weights them (prioritized replay's importance weights), reduces
them (`loss_reduction`), back-propagates, clips the gradient norm (`max_gradient_norm`) and
steps the optimizer. Networks with noisy layers get fresh noise from the agent's own
generator for every action in training and for both networks at every update.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from dqnlab.algorithm.augmentation import build_augmentation
from dqnlab.algorithm.encoders import torch_dtype
from dqnlab.algorithm.heads import evaluates_with_noise, has_noise, sample_noise
from dqnlab.algorithm.losses import TDLoss, build_loss
from dqnlab.algorithm.minibatch import Batch, Minibatch, Transitions
from dqnlab.algorithm.networks import (
    build_q_network,
    computes_a_function,
    recorded_network_name,
)
from dqnlab.algorithm.optim import build_optimizer, clip_gradient_norm_, step_function
from dqnlab.algorithm.part_generators import (
    attach_generators,
    generator_states,
    random_parts,
    restore_generators,
)
from dqnlab.algorithm.policies import build_policy
from dqnlab.algorithm.samplers import needs_priorities
from dqnlab.algorithm.update_graph import CapturedUpdate, HostToDevice
from dqnlab.config import Config, derive_seeds
from dqnlab.envs import Environment
from dqnlab.envs.spaces import ObservationLayout
from dqnlab.errors import ConfigError


def epsilon_at(step: int, config: Config) -> float:
    """Exploration rate for the action after `step` agent steps.

    `epsilon_start` during replay start (1.0: the uniform random policy), then linear to
    `epsilon_end` over `epsilon_decay_steps` (Lua NeuralQLearner:perceive, L369-371).
    """
    steps_learning = max(0, step - config.replay_start_steps)
    if config.epsilon_decay_steps == 0:
        return config.epsilon_end if steps_learning > 0 else config.epsilon_start
    progress = min(1.0, steps_learning / config.epsilon_decay_steps)
    return config.epsilon_start + (config.epsilon_end - config.epsilon_start) * progress


class Agent:
    """Owns the online and target networks, the optimizer and the loss part; acts and learns."""

    def __init__(
        self,
        network: nn.Module,
        num_actions: int,
        config: Config,
        device: torch.device,
        seed: int,
        compile_update: bool = False,
        *,
        update_graph: str = "off",
        input_shape: tuple[int, ...] | None = None,
        observation_dtype: np.dtype | None = None,
        action_names: Sequence[str] | None = None,
        observation_layout: ObservationLayout | None = None,
    ) -> None:
        """`input_shape`, `observation_dtype`, `action_names`, `observation_layout`: what
        the network takes and chooses among, where known (players of several environments
        need them; network files record them).

        `compile_update` (opt-in): compile the loss with its backward pass and the
        optimizer step with `torch.compile`. The same arithmetic, fused into fewer passes
        over memory, so results agree up to float rounding; the first update then takes
        tens of seconds to compile and needs a C++ compiler (on CPU).

        `update_graph` = "cuda" (opt-in, a CUDA device): the update captured as a CUDA
        graph after a few eager ones and replayed (`update_graph.CapturedUpdate`)."""
        if update_graph == "cuda" and device.type != "cuda":
            raise ConfigError(
                f'update_graph = "cuda" needs a CUDA device; the training device is {device}'
            )
        self.config = config
        self.device = device
        self.num_actions = num_actions
        self.online = network.to(device)
        self.target = copy.deepcopy(self.online).requires_grad_(False)
        self.optimizer = self._build_optimizer(capturable=update_graph == "cuda")
        self.loss = build_loss(config)
        self.policy = build_policy(config, num_actions)
        self.rng = np.random.default_rng(seed)
        # Noisy layers draw from a generator of their own (on the device), saved with the
        # agent so that a resumed run draws the same noise.
        self.noisy = has_noise(self.online)
        self.noisy_evaluation = evaluates_with_noise(config, self.online)
        self.noise_generator = torch.Generator(device=device)
        self.noise_generator.manual_seed(seed)
        self.updates = 0
        self.input_shape = tuple(input_shape) if input_shape is not None else None
        self.observation_dtype = (
            np.dtype(observation_dtype) if observation_dtype is not None else None
        )
        self.action_names = list(action_names) if action_names is not None else None
        self.observation_layout = observation_layout
        self.needs_priorities = needs_priorities(config)
        self._check_priorities()
        self._build_drawing_parts(seed)
        self._build_update(compile_update, update_graph)

    def _build_optimizer(self, capturable: bool) -> torch.optim.Optimizer:
        config = self.config
        return build_optimizer(
            config.optimizer,
            self.online.parameters(),
            learning_rate=config.learning_rate,
            rmsprop_decay=config.rmsprop_decay,
            rmsprop_epsilon=config.rmsprop_epsilon,
            adam_epsilon=config.adam_epsilon,
            capturable=capturable,
        )

    def _build_drawing_parts(self, seed: int) -> None:
        """The augmentation part, with a generator of its own, and a generator for each part
        that draws random numbers (`dqnlab.parts.RandomPart`); all saved with the agent."""
        is_image = self.input_shape is not None and is_image_observation(
            self.input_shape[1:], np.dtype(self.observation_dtype or np.float32)
        )
        self.augmentation = build_augmentation(self.config, is_image)
        self.augmentation_generator = torch.Generator(device=self.device)
        self.augmentation_generator.manual_seed(derive_seeds(seed, 1)[0])
        self.part_generators = attach_generators(
            random_parts({"online": self.online, "target": self.target, "loss": self.loss}),
            self.device,
            seed,
        )

    def _build_update(self, compile_update: bool, update_graph: str) -> None:
        """The update as it runs: eager, compiled (`compile_update`), or replayed as a CUDA
        graph (`update_graph`), its inputs staged into buffers that stay put."""
        self._optimizer_step: Callable[[], object] = step_function(self.optimizer)
        if compile_update:
            self._loss_and_backward = torch.compile(self._loss_and_backward)  # type: ignore[method-assign]
            self._optimizer_step = torch.compile(self.optimizer.step)
        self._staging = HostToDevice(self.device)
        self._graph = (
            CapturedUpdate(self._graph_step, self._staging.owns) if update_graph == "cuda" else None
        )
        self._online_stands_for_target = (
            not compile_update and update_graph == "off" and _online_may_stand_for_target(self)
        )
        # A network of modules whose forward ignores the mode needs no switch between acting
        # (eval) and updating (train): `Module.train` walks every module, a walk at each
        # switch, 6% of a CartPole step.
        self._mode_matters = not computes_a_function(self.online)

    def _check_priorities(self) -> None:
        """A user's loss part must give priorities for prioritized replay: ask it once, on a
        minibatch of zeros, before the run starts rather than at its first update."""
        if not self.needs_priorities or self.config.loss == "auto":
            return  # the shipped losses give them
        if self.input_shape is None or self.observation_dtype is None:
            return
        zeros = torch.zeros((2, *self.input_shape), dtype=torch_dtype(self.observation_dtype))
        zeros = zeros.to(self.device)
        scalars = torch.zeros(2, device=self.device)
        batch = Transitions(
            observations=zeros,
            actions=scalars.long(),
            rewards=scalars,
            terminals=scalars,
            discounts=torch.full((2,), self.config.discount, device=self.device),
            next_observations=zeros,
        )
        with torch.no_grad():
            output = self.loss(self.online, self.target, batch)
        if output.priorities is None:
            raise self._no_priorities()

    def _no_priorities(self) -> ConfigError:
        return ConfigError(
            f"loss = {self.config.loss!r} gives no priorities, which replay_sampling = "
            f"{self.config.replay_sampling!r} needs"
        )

    def act(self, stacked_observation: np.ndarray, epsilon: float, training: bool = False) -> int:
        """The policy's action on one stacked observation (`choose`). A network with noisy
        layers acts with fresh noise in `training`, and otherwise as `eval_noise` says
        (`acting_q_values`)."""
        return self.act_batch(stacked_observation[None], [epsilon], training)[0]

    def act_batch(
        self, stacked_observations: np.ndarray, epsilons: Sequence[float], training: bool = False
    ) -> list[int]:
        """The policy's actions on a batch of stacked observations (one per environment,
        `num_envs`), chosen in order with the agent's generator: the first choice that
        needs Q-values computes them for the whole batch in one forward pass
        (`acting_q_values`: one noise draw for the batch where noise applies), and the
        others reuse it. One observation: `act`."""
        computed: list[np.ndarray] = []

        def values(row: int) -> np.ndarray:
            if not computed:
                computed.append(self.acting_q_values(stacked_observations, training))
            return computed[0][row]

        return [
            self.choose(epsilon, functools.partial(values, row))
            for row, epsilon in enumerate(epsilons)
        ]

    def choose(self, epsilon: float, q_values: np.ndarray | Callable[[], np.ndarray]) -> int:
        """The policy part's action (`policies.build_policy`: epsilon-greedy unless `policy`
        says otherwise), with the agent's generator. `q_values` may be a function, called
        only when the policy needs them (a random action needs no forward pass)."""
        return self.policy.choose(q_values, epsilon, self.rng)

    def q_values(self, stacked_observations: np.ndarray) -> np.ndarray:
        """Q-values of the online network in eval mode (matters for dropout/batch norm, and
        gives noisy layers their mean weights); left as it is for a network whose forward
        ignores the mode (`networks.computes_a_function`)."""
        if self._mode_matters:
            set_mode(self.online, training=False)
        with torch.inference_mode():
            inputs = torch.from_numpy(stacked_observations).to(self.device)
            return self.online(inputs).float().cpu().numpy()

    def acting_q_values(self, stacked_observations: np.ndarray, training: bool) -> np.ndarray:
        """The Q-values the policy acts on: with fresh noise in the noisy layers (one draw
        for the whole batch) in `training`, or when evaluating with eval_noise = "sampled";
        otherwise `q_values`, the mean weights."""
        if self.noisy and (training or self.noisy_evaluation):
            return self._noisy_q_values(stacked_observations)
        return self.q_values(stacked_observations)

    def _noisy_q_values(self, stacked_observations: np.ndarray) -> np.ndarray:
        set_mode(self.online, training=True)
        sample_noise(self.online, self.noise_generator, weights=False)  # composed if need be
        with torch.inference_mode():
            inputs = torch.from_numpy(stacked_observations).to(self.device)
            return self.online(inputs).float().cpu().numpy()

    def update(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor | None]:
        """One gradient step on a sampled minibatch; returns the loss and the priorities
        the loss part gives (for prioritized replay), neither synchronised (with
        update_graph, the graph's own tensors: read them before the next update)."""
        # Both networks in train mode for every update, whatever ran before (acting and the
        # held-out statistics use eval mode): a part whose forward depends on the mode
        # (noisy layers, a user's dropout or random draws) then computes the same after a
        # resume as in a run left alone. A network whose forward ignores the mode keeps its.
        if self._mode_matters:
            set_mode(self.online, training=True)
            set_mode(self.target, training=True)
        transitions = self._on_device(batch)
        if self.noisy:  # fresh noise for each network (Fortunato et al. 2018, Algorithm 1)
            # Drawn in place into the layers' buffers, outside a graph: each update's own.
            sample_noise(self.online, self.noise_generator)
            sample_noise(self.target, self.noise_generator)
        if self._graph is None:
            loss, priorities = self._update_step(transitions)
        else:
            loss, priorities = self._graph(*transitions.update_inputs())
        if priorities is None and self.needs_priorities:
            raise self._no_priorities()  # an agent built without its input shape checks here
        self.updates += 1
        return loss, priorities

    def _on_device(self, batch: Batch) -> Transitions:
        """The minibatch on the training device: the frames moved (the shared window
        once, a no-op for frames already there), the small arrays in one copy that does not
        wait for the device (on a GPU), into buffers that stay put (`HostToDevice`)."""
        if batch.window is not None:  # the shared frames cross to the device once
            frames, next_frames = _on_device(batch.window, self.device), None
        else:
            frames = _on_device(batch.observations, self.device)
            next_frames = _on_device(batch.next_observations, self.device)
        small = self._staging.upload(
            (batch.actions, batch.rewards, batch.terminals, batch.discounts, batch.weights)
        )
        return Minibatch.from_update_inputs((frames, next_frames, *small), batch.indices)

    def _graph_step(self, *inputs: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The update on the tensors a CUDA graph keeps (`Minibatch.update_inputs`)."""
        return self._update_step(Minibatch.from_update_inputs(inputs))

    def _update_step(self, batch: Transitions) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The update on a minibatch on the device, all of it on the device (what a graph
        captures)."""
        if self.augmentation is not None:  # each drawn on its own (augmentation.py)
            batch = dataclasses.replace(
                batch,
                observations=self.augmentation(batch.observations, self.augmentation_generator),
                next_observations=self.augmentation(
                    batch.next_observations, self.augmentation_generator
                ),
                window=None,
            )
        target = self.online if self.target_is_a_copy() else self.target
        self._clear_gradients()
        loss, priorities = self._loss_and_backward(batch, target)
        if self.config.max_gradient_norm > 0:
            clip_gradient_norm_(self.online.parameters(), self.config.max_gradient_norm)
        self._optimizer_step()
        return loss, priorities

    def _clear_gradients(self) -> None:
        """The optimizer's gradients set to None, as `optimizer.zero_grad()` does by default,
        so backward writes fresh ones instead of adding to zeros: the same bits, 3-4% of a
        Nature update saved at one thread (19.8 against 20.5 ms, 2026-12-05, quiet AMD), with
        glibc's thresholds raised or not. A CUDA graph replays the addresses it captured, so
        under one they are zeroed in place, in one foreach call (`zero_grad`'s per-call Python
        work is 25 us of a 1 ms CartPole update)."""
        parameters = [p for group in self.optimizer.param_groups for p in group["params"]]
        if self._graph is None:
            for param in parameters:
                param.grad = None
            return
        gradients = [param.grad for param in parameters if param.grad is not None]
        if gradients:
            torch._foreach_zero_(gradients)

    def target_is_a_copy(self) -> bool:
        """Whether the online network may stand in for the target in this update: both
        compute the same function of the input (see `_online_may_stand_for_target`) and the
        target's weights and buffers are the online network's, bit for bit. Double DQN's loss
        then values s' with one pass instead of two, the same bits: `drq_epsilon` copies the
        target after every update. Compared at every update, whatever changed them (an
        optimizer's step, fused or not, a load, a user's code): the first weights differ
        where the target is not a fresh copy (microseconds), and the whole comparison of
        equal Nature networks takes about a millisecond (a `drq_epsilon` update saves 3)."""
        if not self._online_stands_for_target:
            return False
        online = [*self.online.parameters(), *self.online.buffers()]
        target = [*self.target.parameters(), *self.target.buffers()]
        return len(online) == len(target) and all(
            _same_bits(a, b) for a, b in zip(online, target, strict=True)
        )

    def _loss_and_backward(
        self, batch: Transitions, target: nn.Module
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        output = self.loss(self.online, target, batch)
        losses = output.losses if batch.weights is None else output.losses * batch.weights
        # Summed as the Lua code accumulates gradients over the minibatch (its RMSProp
        # epsilon assumes that scale), or averaged (loss_reduction).
        loss = losses.sum() if self.config.loss_reduction == "sum" else losses.mean()
        loss.backward()
        return loss.detach(), output.priorities

    def sync_target(self) -> None:
        self.target.load_state_dict(self.online.state_dict())

    def state_dict(self) -> dict[str, Any]:
        return {
            "online": self.online.state_dict(),
            "target": self.target.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "rng": self.rng.bit_generator.state,
            "noise_rng": self.noise_generator.get_state(),
            "augmentation_rng": self.augmentation_generator.get_state(),
            "part_rngs": generator_states(self.part_generators),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.online.load_state_dict(state["online"])
        self.target.load_state_dict(state["target"])
        self.optimizer.load_state_dict(state["optimizer"])  # new state tensors:
        if self._graph is not None:  # a graph of the old ones would update those
            self._graph.reset()
        self.rng.bit_generator.state = state["rng"]
        if "noise_rng" in state:  # checkpoints from before the family have none
            self.noise_generator.set_state(state["noise_rng"].cpu())
        if "augmentation_rng" in state:  # nor from before the augmentation part
            self.augmentation_generator.set_state(state["augmentation_rng"].cpu())
        restore_generators(self.part_generators, state.get("part_rngs", {}))
        self.updates = int(state["updates"])


def _online_may_stand_for_target(agent: Agent) -> bool:
    """Whether a target network that is a fresh copy of the online network may be replaced
    by the online network itself: the shipped TD loss with Double DQN's target, on a network
    whose forward is a function of weights and input (`networks.computes_a_function`), so
    the two networks' passes on s' are the same bits and `TDLoss.next_values` takes one."""
    return (
        type(agent.loss) is TDLoss
        and agent.config.target == "double"
        and computes_a_function(agent.online)
    )


# Integers of each float's size: two tensors viewed as them are equal only where every
# element has the same bits (torch.equal on floats takes -0.0 for 0.0, and NaN for no NaN).
_BITS = {torch.float64: torch.int64, torch.float32: torch.int32,
         torch.float16: torch.int16, torch.bfloat16: torch.int16}  # fmt: skip


def _same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    bits = _BITS.get(a.dtype)
    return torch.equal(a, b) if bits is None else torch.equal(a.view(bits), b.view(bits))


def set_mode(network: nn.Module, training: bool) -> None:
    """`network.train(training)`, skipped when every module is in that mode already and
    none has a `train` of its own (a user's part may act in it, and is called as before):
    `Module.train` walks and sets every module (30 us for the CartPole MLP, three times a
    step), the check reads them (8 us)."""
    if any(
        module.training != training or type(module).train is not nn.Module.train
        for module in network.modules()
    ):
        network.train(training)


def _on_device(frames: np.ndarray | torch.Tensor, device: torch.device) -> torch.Tensor:
    """A batch's frames as a tensor on `device` (a no-op for frames already there)."""
    tensor = frames if isinstance(frames, torch.Tensor) else torch.from_numpy(frames)
    return tensor.to(device)


def is_image_observation(observation_shape: tuple[int, ...], dtype: np.dtype) -> bool:
    return np.dtype(dtype) == np.uint8 and len(observation_shape) >= 2


def build_agent(config: Config, env: Environment, device: torch.device, seed: int) -> Agent:
    """The configured network for this environment, wrapped in an agent."""
    input_shape = (config.history_length, *env.observation_shape)
    return agent_for_input(
        config,
        input_shape,
        env.observation_dtype,
        env.action_names,
        device,
        seed,
        getattr(env, "observation_layout", None),
    )


def agent_for_input(
    config: Config,
    input_shape: tuple[int, ...],
    observation_dtype: np.dtype,
    action_names: Sequence[str],
    device: torch.device,
    seed: int,
    layout: ObservationLayout | None = None,
) -> Agent:
    """The configured network for inputs of `input_shape` (history, *observation shape)
    and one Q-value per action of `action_names`, wrapped in an agent. `layout`: how the
    observations are stored (`envs/spaces.py`); None for a single frame (Atari's)."""
    network = build_q_network(
        config,
        input_shape,
        len(action_names),
        is_image_observation(input_shape[1:], observation_dtype),
        layout,
    )
    return Agent(
        network,
        len(action_names),
        config,
        device,
        seed,
        config.compile_update,
        update_graph=config.update_graph,
        input_shape=input_shape,
        observation_dtype=observation_dtype,
        action_names=action_names,
        observation_layout=layout,
    )


def recorded_network(config: Config, agent: Agent) -> str:
    """The network setting a new run records for this agent (`recorded_network_name`)."""
    if agent.input_shape is None or agent.observation_dtype is None:
        return config.network
    is_image = is_image_observation(agent.input_shape[1:], agent.observation_dtype)
    return recorded_network_name(config.network, is_image, agent.observation_layout)
