"""Observations of any layout (`envs/spaces.py`) read into one feature vector.

A network input is a batch of stacked observations, (batch, history, *frame_shape), as
the replay and the acting history give them. For a packed layout the frames are rows of
bytes; `unpack` cuts each part out of them and views it in its own dtype, on whatever
device the batch is. `ObservationEncoder` then reads each part (SB3's
CombinedExtractor does the same per key of a Dict) and concatenates the results:
- an image: its history's frames stacked as planes, uint8 scaled by 1/255, through the
  Nature CNN's convolutions when both sides are at least 36 pixels, else through one 3x3
  convolution of 16 channels (MinAtar's network: Young & Tian 2019, "MinAtar: An
  Atari-inspired testbed", section 4: conv 16 3x3 stride 1, then 128 units);
- a vector: flattened, as float;
- a one-hot part: each entry's value as a one-hot of its categories. Indices are stored
  plus one, so the zero frames before an episode's start read as no category at all.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from dqnlab.envs.spaces import ObservationLayout, Part

NATURE_MIN_SIDE = 36  # the Nature CNN's three convolutions need 36x36 pixels at least
SMALL_CNN_CHANNELS = 16  # MinAtar (Young & Tian 2019), section 4
SMALL_CNN_HIDDEN_WIDTH = 128  # MinAtar: the fully connected layer after the convolution


def torch_dtype(dtype: np.dtype | str) -> torch.dtype:
    """The torch dtype of a NumPy dtype."""
    return torch.from_numpy(np.zeros(0, dtype=dtype)).dtype


def nature_convolutions(channels: int) -> nn.Sequential:
    """The Nature CNN's three convolutions with ReLU, flattened (Mnih et al. 2015, Methods).

    Every ReLU of dqnlab's networks works in place, on the output of the layer before it
    (which nothing else reads): the same values and gradients, one activation's allocation
    and pass fewer (a Nature update about 4% faster on two threads, a dueling one 5%). A
    forward hook that keeps a layer's output must clone it: the ReLU after it overwrites it."""
    return nn.Sequential(
        nn.Conv2d(channels, 32, kernel_size=8, stride=4),
        nn.ReLU(inplace=True),
        nn.Conv2d(32, 64, kernel_size=4, stride=2),
        nn.ReLU(inplace=True),
        nn.Conv2d(64, 64, kernel_size=3, stride=1),
        nn.ReLU(inplace=True),
        nn.Flatten(),
    )


def unpack(
    observations: torch.Tensor,
    layout: ObservationLayout,
    dtypes: list[torch.dtype] | None = None,
) -> list[torch.Tensor]:
    """Each part of `observations` (batch, history, *frame_shape) as a tensor (batch,
    history, *part.shape) of its stored dtype (`dtypes`: the parts' torch dtypes, when the
    caller has them already)."""
    if not layout.packed:
        return [observations]
    dtypes = dtypes or [torch_dtype(part.dtype) for part in layout.parts]
    leading = observations.shape[:-1]
    values = []
    for part, dtype in zip(layout.parts, dtypes, strict=True):
        raw = observations[..., part.offset : part.offset + part.nbytes].contiguous()
        values.append(raw.view(dtype).reshape(*leading, *part.shape))
    return values


def is_small(part: Part) -> bool:
    _, height, width = part.image_size
    return min(height, width) < NATURE_MIN_SIDE


class ImageEncoder(nn.Module):
    """An image part's history as planes, through the Nature CNN's convolutions or, for a
    small image, one 3x3 convolution (the module's docstring)."""

    def __init__(self, part: Part, history: int, small: bool | None = None) -> None:
        super().__init__()
        channels, height, width = part.image_size
        self.channels_last = part.channels_last
        self.scale = 1 / 255 if part.dtype == "|u1" else 1.0
        planes = history * channels
        small = is_small(part) if small is None else small
        if small:
            self.convolutions = nn.Sequential(
                nn.Conv2d(planes, SMALL_CNN_CHANNELS, kernel_size=3, stride=1),
                nn.ReLU(inplace=True),
                nn.Flatten(),
            )
        else:
            if min(height, width) < NATURE_MIN_SIDE:
                raise ValueError(
                    f"the Nature CNN needs images of at least 36x36 pixels, got {height}x{width}"
                )
            self.convolutions = nature_convolutions(planes)
        with torch.no_grad():
            probe = torch.zeros(1, planes, height, width)
            self.output_size = int(self.convolutions(probe).shape[1])

    def forward(self, values: torch.Tensor) -> torch.Tensor:
        if self.channels_last:  # (batch, history, H, W, C) -> (batch, history, C, H, W)
            values = values.movedim(-1, 2)
        planes = values.flatten(1, -3).float()
        if self.scale != 1.0:
            planes = planes * self.scale
        return self.convolutions(planes)


class OneHotEncoder(nn.Module):
    """Each entry's stored index (value - start + 1; 0: no observation) as a one-hot of its
    categories, entries and history concatenated."""

    offsets: torch.Tensor
    kept_columns: torch.Tensor

    def __init__(self, part: Part, history: int) -> None:
        super().__init__()
        categories = torch.tensor(part.categories, dtype=torch.int64)
        offsets = torch.cumsum(categories + 1, 0) - (categories + 1)
        self.register_buffer("offsets", offsets, persistent=False)
        self.width = int((categories + 1).sum())
        self.output_size = history * int(categories.sum())
        keep = torch.ones(self.width, dtype=torch.bool)
        keep[offsets] = False  # the "no observation" columns
        # As indices, not a mask: indexing by a mask waits for the device to count it.
        self.register_buffer("kept_columns", keep.nonzero().flatten(), persistent=False)

    def forward(self, values: torch.Tensor) -> torch.Tensor:
        indices = values.reshape(*values.shape[:2], -1).long() + self.offsets
        one_hot = F.one_hot(indices, self.width).sum(dim=2)  # (batch, history, width)
        return one_hot.index_select(-1, self.kept_columns).flatten(1).float()


class VectorEncoder(nn.Module):
    """A part's history flattened, as float."""

    def __init__(self, part: Part, history: int) -> None:
        super().__init__()
        size = 1
        for n in part.shape:
            size *= n
        self.output_size = history * size

    def forward(self, values: torch.Tensor) -> torch.Tensor:
        return values.flatten(1).float()


class ObservationEncoder(nn.Module):
    """Every part of a layout read by its encoder, the features concatenated:
    `output_size` features per stacked observation. `small_images`: force the one-convolution
    encoder (True) or the Nature convolutions (False) on every image; None: by size."""

    def __init__(
        self, layout: ObservationLayout, history: int, small_images: bool | None = None
    ) -> None:
        super().__init__()
        self.layout = layout
        encoders: list[ImageEncoder | OneHotEncoder | VectorEncoder] = []
        for part in layout.parts:
            if part.kind == "image":
                encoders.append(ImageEncoder(part, history, small_images))
            elif part.kind == "onehot":
                encoders.append(OneHotEncoder(part, history))
            else:
                encoders.append(VectorEncoder(part, history))
        self.encoders = nn.ModuleList(encoders)
        self.dtypes = [torch_dtype(part.dtype) for part in layout.parts]  # once, not per call
        self.output_size = sum(encoder.output_size for encoder in encoders)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        values = unpack(observations, self.layout, self.dtypes)
        features = [encoder(value) for encoder, value in zip(self.encoders, values, strict=True)]
        return features[0] if len(features) == 1 else torch.cat(features, dim=1)
