"""Training targets held compactly: integer pixels at the training size, one view made float per step.

A survey's targets as float32 are 12 bytes a pixel (300 views at 640x480: 1.1 GB, and every copy of the list
another); as 8-bit they are 3 (276 MB). Each image is stored as

- ``uint8`` when it is exactly an 8-bit image as the decoder gave it (every value ``k x float32(1/255)``,
  OpenImageIO's conversion): decoding gives back the very same float32 values, bit for bit;
- else ``uint16`` (area-averaged photos, 16-bit files, linear light): decoding is within ``0.5 / 65535``
  (7.6e-6) of the float it was made from, exact for a 16-bit file kept at its size. That is 500x finer than
  the 8-bit photos' own step; the sub-1/65535 part of an average carries no information.

:class:`PackedImages` is a ``Sequence`` of float32 ``[H, W, 3]`` tensors, so the trainer, the medium term and
the probe index it as they indexed the list of floats; only the view asked for is made float.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import overload

import numpy as np
import torch
from torch import Tensor

# the decoder's scale per stored dtype: float = k x float32(1 / top) (OpenImageIO's integer-to-float conversion)
_TOP = {torch.uint8: 255, torch.uint16: 65535}
UINT16_TOLERANCE = 0.5 / 65535  # largest |decoded - original| of an image stored as uint16 (plus float32 rounding)


def _scale(dtype: torch.dtype) -> Tensor:
    return torch.tensor(1.0 / _TOP[dtype], dtype=torch.float32)


def unpack_image(q: Tensor, device: torch.device | str | None = None) -> Tensor:
    """A packed image as float32 in [0, 1] on ``device`` (default: where ``q`` is).  # [H, W, 3]"""
    if q.dtype not in _TOP:
        raise TypeError(f"a packed image is uint8 or uint16, got {q.dtype}")
    q = q if device is None else q.to(device)
    return q.to(torch.float32) * _scale(q.dtype).to(q.device)


def pack_image(img: np.ndarray | Tensor) -> Tensor:
    """``img`` [H, W, 3] float in [0, 1] as uint8 when that is lossless, else uint16 (module docstring)."""
    x = torch.as_tensor(img).detach().to("cpu", torch.float32)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"a training image is [H, W, 3], got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError("a training image holds NaN or infinite values")
    x = x.clamp(0.0, 1.0)
    q8 = torch.round(x * 255).to(torch.uint8)
    if torch.equal(unpack_image(q8), x):
        return q8
    # torch has no uint16 arithmetic on CPU for every op, but it stores and converts it
    return torch.round(x * 65535).to(torch.int32).to(torch.uint16)


class PackedImages(Sequence[Tensor]):
    """Training images stored as packed integers (:func:`pack_image`); ``images[i]`` is view i as float32
    [H, W, 3] on ``device``, made when asked for."""

    def __init__(self, packed: Sequence[Tensor], device: torch.device | str = "cpu") -> None:
        for q in packed:
            if q.dtype not in _TOP or q.ndim != 3 or q.shape[2] != 3:
                raise ValueError(f"packed images are uint8/uint16 [H, W, 3], got {q.dtype} {tuple(q.shape)}")
        self.packed = list(packed)
        self.device = torch.device(device)

    @classmethod
    def pack(cls, images: Iterable[np.ndarray | Tensor], device: torch.device | str = "cpu") -> PackedImages:
        """Pack images one at a time (an iterator of decoded images never has two floats alive)."""
        return cls([pack_image(img).to(device) for img in images], device)

    def __len__(self) -> int:
        return len(self.packed)

    @overload
    def __getitem__(self, i: int) -> Tensor: ...

    @overload
    def __getitem__(self, i: slice) -> PackedImages: ...

    def __getitem__(self, i: int | slice) -> Tensor | PackedImages:
        if isinstance(i, slice):
            return PackedImages(self.packed[i], self.device)
        return unpack_image(self.packed[i], self.device)

    def subset(self, indices: Iterable[int]) -> PackedImages:
        """These views, still packed (no copy of the pixels)."""
        return PackedImages([self.packed[i] for i in indices], self.device)

    def to(self, device: torch.device | str) -> PackedImages:
        return PackedImages([q.to(device) for q in self.packed], device)

    @property
    def nbytes(self) -> int:
        """Bytes of pixel storage."""
        return sum(q.numel() * q.element_size() for q in self.packed)

    def dtypes(self) -> dict[str, int]:
        """How many images are stored as each dtype (``{"uint8": n, "uint16": m}``)."""
        out: dict[str, int] = {}
        for q in self.packed:
            name = str(q.dtype).removeprefix("torch.")
            out[name] = out.get(name, 0) + 1
        return out


class AsNumpy(Sequence[np.ndarray]):
    """``[t.cpu().numpy() for t in targets]`` made one item at a time (a survey's float copies never all alive)."""

    def __init__(self, targets: Sequence[Tensor]) -> None:
        self.targets = targets

    def __len__(self) -> int:
        return len(self.targets)

    @overload
    def __getitem__(self, i: int) -> np.ndarray: ...

    @overload
    def __getitem__(self, i: slice) -> list[np.ndarray]: ...

    def __getitem__(self, i: int | slice) -> np.ndarray | list[np.ndarray]:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        return self.targets[i].detach().cpu().numpy()


def take(images: Sequence[Tensor] | Sequence[np.ndarray], indices: Sequence[int]) -> Sequence:
    """``[images[i] for i in indices]``, kept packed when ``images`` is :class:`PackedImages`."""
    if isinstance(images, PackedImages):
        return images.subset(indices)
    return [images[i] for i in indices]


__all__ = ["AsNumpy", "PackedImages", "UINT16_TOLERANCE", "pack_image", "take", "unpack_image"]
