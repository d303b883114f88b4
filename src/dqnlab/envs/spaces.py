"""Observation spaces: which parts an observation has and how each is stored and read.

dqnlab stores two kinds of observation as frames of their own (as it always did): a uint8
image of rank 2 or 3 (channels moved first) and a float vector (float32). Any other
Gymnasium observation is packed into one row of bytes per step: each part of a `Dict`
or `Tuple` (nested), in its own dtype, one after another. The replay keeps a row per slot
(frame-once, histories stacked when drawn, as for images), nothing is widened to float32
in memory, and the network unpacks the rows on its device (`algorithm/encoders.py`).

How a `Box` part is read (`images`, the `observation_images` setting):
- "auto": an image if its rank is 3 (H, W, C, or C, H, W when the first axis is the
  smallest), or its rank is 2 and its dtype uint8 or bool (a screen or a grid); else a
  vector (flattened);
- "all": every `Box` of rank 2 or 3 is an image; "none": every part is flattened.
`Discrete` and `MultiDiscrete` parts are one-hot encoded (their values are stored as
indices plus one, 0 meaning "no observation", in the smallest unsigned dtype that holds
them), `MultiBinary` parts are stored
as bool and read as a vector of 0s and 1s.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from dqnlab.errors import EnvError

IMAGE_MODES = ("auto", "all", "none")
_ROW_ALIGNMENT = 8  # bytes: every part starts at a multiple of its itemsize, rows of 8


@dataclass(frozen=True)
class Part:
    """One part of an observation: where it is in the observation (`path`, "" for the
    whole, else keys and tuple positions joined by "/"), how it is read (`kind`: image,
    vector or onehot) and stored (`shape`, `dtype`, at byte `offset` of a packed row).

    Images are stored as the environment gives them; `channels_last` says whether their
    channel axis is the last (rank 2 images have none). For one-hot parts, `categories`
    gives the number of values of each entry and `start` the smallest value."""

    path: str
    kind: str
    shape: tuple[int, ...]
    dtype: str
    offset: int = 0
    channels_last: bool = False
    categories: tuple[int, ...] = ()
    start: tuple[int, ...] = ()

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * np.dtype(self.dtype).itemsize

    @property
    def image_size(self) -> tuple[int, int, int]:
        """(channels, height, width) of an image part."""
        if len(self.shape) == 2:
            return 1, self.shape[0], self.shape[1]
        if self.channels_last:
            height, width, channels = self.shape
            return channels, height, width
        channels, height, width = self.shape
        return channels, height, width


@dataclass(frozen=True)
class ObservationLayout:
    """The parts of an observation and whether it is `packed` into rows of bytes (else
    the observation is a single frame stored as it is: a uint8 image or a float vector)."""

    parts: tuple[Part, ...]
    packed: bool
    row_bytes: int = 0
    # An unpacked channels-last image is stored channels-first: moved when packed.
    transpose: bool = False

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """The shape of one stored observation."""
        return (self.row_bytes,) if self.packed else self.parts[0].shape

    @property
    def frame_dtype(self) -> np.dtype:
        return np.dtype(np.uint8) if self.packed else np.dtype(self.parts[0].dtype)

    @property
    def images(self) -> tuple[Part, ...]:
        return tuple(part for part in self.parts if part.kind == "image")

    def to_dict(self) -> dict[str, Any]:
        """Plain values (a network file stores them; `from_dict` reads them back)."""
        return {
            "packed": self.packed,
            "row_bytes": self.row_bytes,
            "transpose": self.transpose,
            "parts": [
                {
                    **dataclasses.asdict(part),
                    "shape": list(part.shape),
                    "categories": list(part.categories),
                    "start": list(part.start),
                }
                for part in self.parts
            ],
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ObservationLayout:
        parts = tuple(
            Part(
                path=str(part["path"]),
                kind=str(part["kind"]),
                shape=tuple(int(n) for n in part["shape"]),
                dtype=str(part["dtype"]),
                offset=int(part["offset"]),
                channels_last=bool(part["channels_last"]),
                categories=tuple(int(n) for n in part["categories"]),
                start=tuple(int(n) for n in part["start"]),
            )
            for part in values["parts"]
        )
        return cls(
            parts, bool(values["packed"]), int(values["row_bytes"]), bool(values["transpose"])
        )

    def describe(self) -> str:
        """One line: each part's path, kind, shape and stored dtype."""
        return ", ".join(
            f"{part.path or 'observation'}: {part.kind} {'x'.join(map(str, part.shape)) or '1'}"
            f" {np.dtype(part.dtype).name}"
            for part in self.parts
        )

    def pack(self, observation: Any, out: np.ndarray) -> np.ndarray:
        """Write `observation` (as the environment gives it) into `out`, one stored frame."""
        if not self.packed:
            array = np.asarray(observation)
            out[...] = array.transpose(2, 0, 1) if self.transpose else array
            return out
        for part in self.parts:
            value = np.asarray(_at(observation, part.path))
            if part.kind == "onehot":  # stored plus one: 0 is the zero frame, no value
                value = value - np.asarray(part.start).reshape(value.shape) + 1
            stored = np.ascontiguousarray(value, dtype=part.dtype).reshape(-1)
            out[part.offset : part.offset + part.nbytes] = stored.view(np.uint8)
        return out

    def unpack(self, frame: np.ndarray) -> list[tuple[Part, np.ndarray]]:
        """Each part of one stored frame as the environment gave it (one-hot parts as their
        values; a zero frame's, from before an episode's start, as start - 1)."""
        if not self.packed:
            return [(self.parts[0], frame)]
        values = []
        for part in self.parts:
            raw = np.ascontiguousarray(frame[part.offset : part.offset + part.nbytes])
            value = raw.view(part.dtype).reshape(part.shape)
            if part.kind == "onehot":
                value = value.astype(np.int64) - 1 + np.asarray(part.start).reshape(part.shape)
            values.append((part, value))
        return values


def frame_layout(shape: tuple[int, ...], dtype: np.dtype) -> ObservationLayout:
    """The layout of a single stored frame: a uint8 image (already channels-first) or a
    float vector; what Atari games and observations stored as before packing have."""
    dtype = np.dtype(dtype)
    kind = "image" if dtype == np.uint8 and len(shape) >= 2 else "vector"
    return ObservationLayout((Part("", kind, tuple(shape), dtype.str),), packed=False)


def observation_layout(space: gym.Space, images: str = "auto") -> ObservationLayout:
    """How observations of `space` are stored and read (the module's docstring)."""
    if images not in IMAGE_MODES:
        raise EnvError(f"observation_images = {images!r} is not one of: {', '.join(IMAGE_MODES)}")
    parts = _parts(space, "", images)
    single = parts[0] if len(parts) == 1 else None
    if single is not None and isinstance(space, gym.spaces.Box):
        if single.kind == "image" and single.dtype == np.dtype(np.uint8).str:
            channels, height, width = single.image_size
            shape = (height, width) if len(single.shape) == 2 else (channels, height, width)
            return ObservationLayout(
                (dataclasses.replace(single, shape=shape, channels_last=False),),
                packed=False,
                transpose=single.channels_last,
            )
        if single.kind == "vector" and len(single.shape) == 1 and single.dtype.startswith("<f"):
            float32 = dataclasses.replace(single, dtype=np.dtype(np.float32).str)
            return ObservationLayout((float32,), packed=False)
    return _packed(parts)


def _packed(parts: list[Part]) -> ObservationLayout:
    placed = []
    offset = 0
    for part in parts:
        itemsize = np.dtype(part.dtype).itemsize
        offset = -(-offset // itemsize) * itemsize
        placed.append(dataclasses.replace(part, offset=offset))
        offset += part.nbytes
    row_bytes = max(-(-offset // _ROW_ALIGNMENT) * _ROW_ALIGNMENT, _ROW_ALIGNMENT)
    return ObservationLayout(tuple(placed), packed=True, row_bytes=row_bytes)


def _parts(space: gym.Space, path: str, images: str) -> list[Part]:
    if isinstance(space, gym.spaces.Dict):
        return [
            part
            for key, subspace in space.spaces.items()
            for part in _parts(subspace, _join(path, str(key)), images)
        ]
    if isinstance(space, gym.spaces.Tuple):
        return [
            part
            for index, subspace in enumerate(space.spaces)
            for part in _parts(subspace, _join(path, str(index)), images)
        ]
    if isinstance(space, gym.spaces.Box):
        return [_box_part(space, path, images)]
    if isinstance(space, gym.spaces.Discrete):
        n = int(space.n)
        return [
            Part(path, "onehot", (1,), _index_dtype(n), categories=(n,), start=(int(space.start),))
        ]
    if isinstance(space, gym.spaces.MultiDiscrete):
        counts = np.asarray(space.nvec, dtype=np.int64).reshape(-1)
        starts = np.asarray(getattr(space, "start", np.zeros_like(counts))).reshape(-1)
        return [
            Part(
                path,
                "onehot",
                tuple(int(n) for n in np.shape(space.nvec)),
                _index_dtype(int(counts.max())),
                categories=tuple(int(n) for n in counts),
                start=tuple(int(n) for n in starts),
            )
        ]
    if isinstance(space, gym.spaces.MultiBinary):
        shape = tuple(int(n) for n in np.atleast_1d(space.n))
        return [Part(path, "vector", shape, np.dtype(np.bool_).str)]
    where = f" (at {path!r} of the observation)" if path else ""
    raise EnvError(
        f"observation space {type(space).__name__}{where} cannot be encoded: dqnlab reads Box, "
        "Discrete, MultiDiscrete and MultiBinary spaces, and Dict and Tuple of them"
    )


def _box_part(space: gym.spaces.Box, path: str, images: str) -> Part:
    shape = tuple(int(n) for n in space.shape)
    dtype = np.dtype(space.dtype)
    if dtype.kind == "f" and dtype.itemsize > 4:
        dtype = np.dtype(np.float32)  # float64 observations are read as float32 (the network's)
    rank = len(shape)
    if images == "none" or rank not in (2, 3):
        is_image = False
    elif images == "all":
        is_image = True
    else:
        is_image = rank == 3 or dtype in (np.dtype(np.uint8), np.dtype(np.bool_))
    if not is_image:
        return Part(path, "vector", shape, dtype.str)
    # Gymnasium's images are channels-last; a first axis smaller than the last reads as
    # channels-first (frames stacked by a wrapper, say).
    channels_last = rank == 3 and not shape[0] < shape[2]
    return Part(path, "image", shape, dtype.str, channels_last=channels_last)


def _index_dtype(count: int) -> str:
    """The smallest unsigned dtype for indices 0..count (a value's index plus one)."""
    for dtype in (np.uint8, np.uint16, np.uint32):
        if count <= np.iinfo(dtype).max:
            return np.dtype(dtype).str
    return np.dtype(np.int64).str


def _join(path: str, key: str) -> str:
    return f"{path}/{key}" if path else key


def _at(observation: Any, path: str) -> Any:
    """The part of `observation` at `path` (keys of dicts, positions of tuples)."""
    if not path:
        return observation
    for key in path.split("/"):
        observation = observation[int(key)] if isinstance(observation, tuple) else observation[key]
    return observation
