"""warp kernels launched on the CPU with torch tensors as arguments, for little per call.

``wp.launch`` checks and packs every argument on every call, and ``wp.from_torch`` builds a
warp array object for every tensor: 40 us of Python for the bone chain's four arrays, eight
times its kernel's 5 us, and a fit launches its kernels about two thousand times a frame.
A :class:`CpuKernel` records the launch once per thread and then only re-points the
arguments that differ from last time's: a tensor's descriptor (``from_torch(...,
return_ctype=True)``) is its data pointer, shape and strides, so a tensor at the same
address with the same layout (a constant, or memory torch reused) keeps its own, one with
the layout of the last only moves the descriptor's pointer, and a value equal to the last
is kept. 16 us for the same call, 10 with the constants kept, 7 with the pointers moved."""
from __future__ import annotations

import ctypes
import math
import threading
from collections.abc import Sequence
from typing import Any

import torch
import warp as wp

from .assets import configure_warp


class CpuKernel:
    """``kernel`` launched on the CPU with its arguments in order: torch tensors (read as
    the warp dtype given for that position in ``dtypes``) or, where ``dtypes`` holds None,
    values passed as they are (ints, floats, warp vectors, warp arrays)."""

    def __init__(self, kernel: wp.Kernel, dtypes: Sequence[Any]) -> None:
        self.kernel, self.dtypes = kernel, list(dtypes)
        self._recorded = threading.local()  # a recorded launch is one mutable argument list

    def __call__(self, dim: int | tuple[int, ...], *args: Any) -> None:
        if math.prod(dim if isinstance(dim, tuple) else (dim,)) == 0:
            return
        recorded = self._recorded
        keys = [_value_key(a) if d is None else (a.data_ptr(), a.shape, a.stride(), a.dtype)
                for a, d in zip(args, self.dtypes)]
        command = getattr(recorded, "command", None)
        if command is None:
            configure_warp()
            command = wp.launch(self.kernel, dim=dim, device="cpu", record_cmd=True, inputs=[
                a if d is None else wp.from_torch(a, dtype=d, requires_grad=False)
                for a, d in zip(args, self.dtypes)])
            recorded.command, recorded.dim, recorded.keys = command, dim, keys
        if dim != recorded.dim:
            command.set_dim(dim)
            recorded.dim = dim
        for i, (a, d, key) in enumerate(zip(args, self.dtypes, keys)):
            last = recorded.keys[i]
            if _same(key, last):
                continue
            if d is None:
                command.set_param_at_index(i, a)
            elif key[1:] == last[1:]:  # the same layout elsewhere: only the pointer moves
                descriptor = command.params[i + 1]
                descriptor.data, descriptor._ref = key[0], a
            else:
                command.set_param_at_index_from_ctype(i, wp.from_torch(
                    a, dtype=d, requires_grad=False, return_ctype=True))
            recorded.keys[i] = key
        command.launch()


def rigid(frame: torch.Tensor) -> tuple[wp.mat33, wp.vec3]:
    """A rigid transform ``frame`` (4, 4) as a kernel reads it: rotation and shift."""
    return (wp.mat33(*frame[:3, :3].float().flatten().tolist()),
            wp.vec3(*frame[:3, 3].float().tolist()))


def _value_key(value: Any) -> tuple:
    """A value argument as compared with the last launch's: a warp vector or matrix by
    its bytes (warp's own comparison of two 3 x 3 matrices costs 54 us, of two vectors 2),
    anything else as it is."""
    return (bytes(value) if isinstance(value, ctypes.Array) else value, type(value))


def _same(key: tuple, last: tuple) -> bool:
    """Whether an argument's ``key`` (a value and its type, or a tensor's layout) is the
    one it had last launch; values that do not compare as a bool (warp arrays) never are."""
    try:
        return (key == last) is True
    except (TypeError, ValueError, RuntimeError):
        return False
