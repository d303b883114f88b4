"""The augmentation part of the update: the sampled observations changed before the loss
sees them (DrQ, Kostrikov, Yarats & Fergus 2020, "Image Augmentation Is All You Need").

An augmentation part is a class built as `Class(config)` and called as
`part(observations, generator) -> observations`: a minibatch of stacked observations
(batch, history, *frame_shape) in their stored dtype, on the training device, in; the same
shape and dtype out. `generator` is the agent's own (on the device, saved in every
checkpoint), so a resumed run draws the same augmentations. The agent calls it twice per
update, once for the observations and once for the next observations, so the two are
augmented independently, as DrQ does (its K = M = 1 Atari setting: one augmentation of
each) and Dopamine's DrQ(ε) (`labs/atari_100k/atari_100k_rainbow_agent.py`: one key for
the states, another for the next states). The shipped part:

    RandomShift  pad 4 pixels on every side by repeating the border, then crop back to
                 the frame's size at an offset drawn uniformly from 0..8 on each axis,
                 one offset per observation, the same for all its stacked frames
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from dqnlab.config import Config
from dqnlab.errors import ConfigError
from dqnlab.parts import load_part

# DrQ's Atari setting (Kostrikov et al. 2020, Appendix, "image padding: 4"; its code:
# nn.ReplicationPad2d(4) then kornia's RandomCrop back to 84x84).
RANDOM_SHIFT_PAD = 4


class Augmentation:
    """The interface of an augmentation part (and the base of the shipped one)."""

    def __init__(self, config: Config) -> None:
        self.config = config

    def __call__(self, observations: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        raise NotImplementedError


class RandomShift(Augmentation):
    """Each observation moved by up to `pad` pixels on each axis, the border repeated into
    the space it leaves: the replicate-padded image (H + 2 pad, W + 2 pad) cropped back to
    H x W at offsets (dy, dx) drawn uniformly from 0..2 pad, in the stored dtype (`shift`:
    slices of the padded batch on the CPU, gathers elsewhere). Offsets 0..2 pad inclusive
    as kornia's RandomCrop in DrQ's code; Dopamine's JAX port draws 0..2 pad - 1
    (`jax.random.randint`'s maxval is exclusive), so it never shifts by +pad."""

    def __init__(self, config: Config, pad: int = RANDOM_SHIFT_PAD) -> None:
        super().__init__(config)
        self.pad = pad

    def __call__(self, observations: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        offsets = torch.randint(
            0, 2 * self.pad + 1, (observations.shape[0], 2), generator=generator,
            device=observations.device,
        )  # fmt: skip
        return shift(observations, offsets, self.pad)


def shift(observations: torch.Tensor, offsets: torch.Tensor, pad: int) -> torch.Tensor:
    """Each observation (batch, ..., H, W) cropped out of its border-replicated padding
    of `pad` pixels at `offsets` (batch, 2): (dy, dx) in 0..2 pad, (pad, pad) leaving it
    as it is. Output pixel (i, j) is input pixel (clamp(i + dy - pad), clamp(j + dx - pad)),
    in the stored dtype, every stacked frame of an observation alike.

    Two ways to the same pixels (moved, never computed: the same bytes either way): on the
    CPU one slice copy per observation out of the padded batch (`shift_by_slices`), on
    other devices a gather without host synchronisation, which a CUDA graph can capture
    (`shift_by_gather`). On the CPU the gathers took 2.7 ms for a 32 x 4 x 84 x 84 batch
    and the slices 0.5 ms (one thread, 2026-12-05, AMD EPYC): DrQ(eps) shifts two such
    batches in every update."""
    if observations.device.type == "cpu":
        return shift_by_slices(observations, offsets, pad)
    return shift_by_gather(observations, offsets, pad)


def shift_by_gather(observations: torch.Tensor, offsets: torch.Tensor, pad: int) -> torch.Tensor:
    """`shift` as two gathers, of each output pixel's source row and then its column."""
    batch = observations.shape[0]
    height, width = observations.shape[-2:]
    device = observations.device
    rows = torch.arange(height, device=device) + (offsets[:, :1] - pad)
    columns = torch.arange(width, device=device) + (offsets[:, 1:] - pad)
    rows = rows.clamp_(0, height - 1)  # (batch, height)
    columns = columns.clamp_(0, width - 1)  # (batch, width)
    planes = observations.reshape(batch, -1, height, width)
    shape = planes.shape
    shifted = planes.gather(2, rows[:, None, :, None].expand(shape))
    shifted = shifted.gather(3, columns[:, None, None, :].expand(shape))
    return shifted.reshape(observations.shape)


def shift_by_slices(observations: torch.Tensor, offsets: torch.Tensor, pad: int) -> torch.Tensor:
    """`shift` as the padded batch, written once, and one slice of it copied per
    observation (the offsets read on the host). Boolean frames move as the bytes
    they are stored in: `F.pad` has no replicate kernel for bool."""
    if observations.dtype == torch.bool:
        return shift_by_slices(observations.view(torch.uint8), offsets, pad).view(torch.bool)
    batch = observations.shape[0]
    height, width = observations.shape[-2:]
    planes = observations.reshape(batch, -1, height, width)
    padded = F.pad(planes, (pad, pad, pad, pad), mode="replicate")
    shifted = torch.empty(planes.shape, dtype=planes.dtype, device=planes.device)
    for index, (dy, dx) in enumerate(offsets.tolist()):
        shifted[index] = padded[index, :, dy : dy + height, dx : dx + width]
    return shifted.reshape(observations.shape)


def build_augmentation(config: Config, is_image: bool) -> Augmentation | None:
    """The augmentation part `augmentation` names (None for none), for observations that
    are images (`is_image`) or not: a shipped augmentation needs images."""
    if config.augmentation == "none":
        return None
    if config.augmentation == "random_shift":
        if not is_image:
            raise ConfigError(
                "augmentation = 'random_shift' shifts images; this environment's observations "
                "are not images (uint8, two or more axes): use augmentation = 'none'"
            )
        return RandomShift(config)
    part = load_part("augmentation", config.augmentation, config)
    if not callable(part):
        raise ConfigError(
            f"augmentation = {config.augmentation!r} built {type(part).__name__}, not callable"
        )
    return part  # type: ignore[no-any-return]
