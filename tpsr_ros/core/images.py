"""Images to observation vectors: the one preprocessing of learner, tracking and filter node.

Decoded camera pixels ``(T, H, W, C)`` (``C`` = 3 for colour in RGB order, 1 for grey; uint8
or uint16) become float observation vectors ``(T, h * w * c)`` in ``[0, 1]``, row-major
``(row, column, channel)``:

1. resize by area averaging to ``h x w`` (each output pixel is the mean of the input area it
   covers, with fractional weights at its borders, exact for any size);
2. grey (``c = 1``): a colour image is converted to luma ``0.299 R + 0.587 G + 0.114 B``
   (ITU-R BT.601, as OpenCV's and Pillow's grey conversion); colour output needs colour input.
   Both steps are linear, so converting after resizing equals converting first;
3. divide by the largest pixel value (255 for 8-bit, 65535 for 16-bit).

Speed (a 1080p camera at 30 Hz leaves 33 ms per image): shrinking rows, the one pass over
the whole frame, sums the integer pixels of each output row's band exactly
(:func:`_shrink_rows`; 1920x1080 rgb8 to 16x16 takes 1.5-2 ms in all at load 1-3) and adds
the fractional border rows; no float copy of the frame is made. The columns of the few
rows left are then averaged with :func:`area_weights`. Growing an axis (output larger than
input) uses the weight matrix.

An image already of the target size and channels skips steps 1 and 2, so the simulator's
16x16 rgb8 images give exactly ``pixels / 255`` (the observations of every earlier model).
:func:`preprocess_images` handles a batch with the same per-image arithmetic as a batch of
one, so offline tracking and the filter node see identical observations.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from tpsr_ros.core.errors import ConfigError, MessageError

__all__ = ["LUMA", "Preprocessing", "area_weights", "preprocess_images"]

LUMA = np.array([0.299, 0.587, 0.114])
"""ITU-R BT.601 weights of R, G and B in the grey conversion."""
MAX_IMAGE_SIZE = 4096


@dataclass(frozen=True)
class Preprocessing:
    """Observation image size and colour.

    Attributes:
        height, width: observation pixels (``--image-size N`` or ``WxH``).
        grey: one luma channel instead of three colour channels.

    """

    height: int
    width: int
    grey: bool = False

    def __post_init__(self) -> None:
        for name in ("height", "width"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ConfigError(f"image {name} must be an integer, not {value!r}")
            if not 1 <= value <= MAX_IMAGE_SIZE:
                raise ConfigError(f"image {name} must be 1..{MAX_IMAGE_SIZE}, not {value}")
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "grey", bool(self.grey))

    @property
    def channels(self) -> int:
        """Values per observation pixel."""
        return 1 if self.grey else 3

    @property
    def size(self) -> int:
        """Length of an observation vector."""
        return self.height * self.width * self.channels

    def as_dict(self) -> dict[str, object]:
        """JSON form stored in model metadata."""
        return {"height": self.height, "width": self.width, "grey": self.grey}


@cache
def area_weights(n_in: int, n_out: int) -> np.ndarray:
    """``(n_out, n_in)`` matrix averaging the input cells each output cell covers.

    Output cell ``i`` covers input coordinates ``[i n_in / n_out, (i + 1) n_in / n_out)``;
    each input cell contributes the length of its overlap, rows sum to 1. Read-only.
    """
    edges = np.arange(n_out + 1) * (n_in / n_out)
    cells = np.arange(n_in)
    overlap = np.minimum(edges[1:, None], cells[None, :] + 1.0) - np.maximum(
        edges[:-1, None], cells[None, :]
    )
    weights = np.clip(overlap, 0.0, None) / (n_in / n_out)
    weights.setflags(write=False)
    return weights


def preprocess_images(pixels: np.ndarray, preprocessing: Preprocessing) -> np.ndarray:
    """Observation vectors ``(T, h w c)`` float64 of decoded images ``(T, H, W, C)``.

    ``pixels`` are uint8 or uint16 with ``C`` = 3 (RGB) or 1 (grey); see the module docstring.
    """
    arr = np.asarray(pixels)
    if arr.ndim != 4 or arr.shape[3] not in (1, 3) or arr.dtype not in (np.uint8, np.uint16):
        raise MessageError(
            f"images must be (T, H, W, 1 or 3) uint8 or uint16, got {arr.shape} {arr.dtype}"
        )
    count, height, width, channels = arr.shape
    scale = 255.0 if arr.dtype == np.uint8 else 65535.0
    if channels == 1 and not preprocessing.grey:
        raise MessageError("a grey image cannot give colour observations (use grey)")
    same_size = (height, width) == (preprocessing.height, preprocessing.width)
    if same_size and channels == preprocessing.channels:
        # one pass, one array: the same values as astype(float64) / scale
        return np.divide(arr.reshape(count, -1), scale, dtype=np.float64)
    values = _resize(arr, preprocessing.height, preprocessing.width)
    if preprocessing.grey and channels == 3:
        # elementwise, so every pixel's sum has one order whatever the batch size
        values = (
            LUMA[0] * values[..., 0] + LUMA[1] * values[..., 1] + LUMA[2] * values[..., 2]
        )[..., None]
    return np.ascontiguousarray(values).reshape(count, -1) / scale


def _resize(arr: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area-averaged ``(T, height, width, C)`` float64 of integer pixels ``(T, H, W, C)``."""
    if arr.shape[1] == height:
        values = arr.astype(np.float64)
    elif arr.shape[1] > height:
        values = _shrink_rows(arr, height)
    else:  # growing: the input is smaller than the output, so the float copy is small
        planes = np.ascontiguousarray(arr.astype(np.float64).transpose(0, 3, 1, 2))
        values = np.matmul(area_weights(arr.shape[1], height), planes).transpose(0, 2, 3, 1)
    if arr.shape[2] != width:
        # (T, C, h, W) stacks of 2-d products: each image is computed on its own.
        planes = np.ascontiguousarray(values.transpose(0, 3, 1, 2))
        values = np.matmul(planes, area_weights(arr.shape[2], width).T).transpose(0, 2, 3, 1)
    return values


def _shrink_rows(arr: np.ndarray, n_out: int) -> np.ndarray:
    """Rows of ``(T, H, W, C)`` integer pixels area-averaged to ``n_out < H``, float64.

    Output row ``i`` covers ``[e_i, e_(i+1))`` with ``e_i = i H / n_out``. Its area is the
    exact integer sum of the input rows ``floor(e_i) .. floor(e_(i+1)) - 1``, less the
    fraction ``e_i - floor(e_i)`` of row ``floor(e_i)`` (it belongs to the row before), plus
    the fraction ``e_(i+1) - floor(e_(i+1))`` of row ``floor(e_(i+1))``. The same weights as
    :func:`area_weights`, summed in another order. Band sums are exact integers in the
    narrowest type that holds a band of the largest pixels: uint16 (8-bit pixels, bands of
    up to 257 rows: faster), uint32 or uint64 (images of any height).
    """
    count, n_in, width, channels = arr.shape
    edges = np.arange(n_out + 1) * (n_in / n_out)
    first = np.floor(edges).astype(np.intp)
    first[-1] = n_in
    frac = edges - first
    band = int(np.max(np.diff(first)))
    need = band * int(np.iinfo(arr.dtype).max)
    exact = next(t for t in (np.uint16, np.uint32, np.uint64) if need <= np.iinfo(t).max)
    sums = np.empty((count, n_out, width, channels), dtype=np.float64)
    for i in range(n_out):  # one vectorised reduction per output row (16 for 16x16)
        sums[:, i] = arr[:, first[i] : first[i + 1]].sum(axis=1, dtype=exact)
    sums -= frac[:-1, None, None] * arr[:, first[:-1]]
    sums[:, :-1] += frac[1:-1, None, None] * arr[:, first[1:-1]]  # the last band ends at H
    return sums / (n_in / n_out)
