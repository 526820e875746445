"""warp kernels launched on the CPU with torch tensors as arguments, for little per call.

``wp.launch`` checks and packs every argument on every call, and ``wp.from_torch`` builds a
warp array object for every tensor: 40 us of Python for the bone chain's four arrays, eight
times its kernel's 5 us, and a fit launches its kernels about two thousand times a frame.
A :class:`CpuKernel` records the launch once per thread and then only re-points the
tensors' descriptors (``from_torch(..., return_ctype=True)``): 16 us for the same call."""
from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from typing import Any

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
        command = getattr(self._recorded, "command", None)
        if command is None:
            configure_warp()
            command = wp.launch(self.kernel, dim=dim, device="cpu", record_cmd=True, inputs=[
                a if d is None else wp.from_torch(a, dtype=d, requires_grad=False)
                for a, d in zip(args, self.dtypes)])
            self._recorded.command, self._recorded.dim = command, dim
        else:
            if dim != self._recorded.dim:
                command.set_dim(dim)
                self._recorded.dim = dim
            for i, (a, d) in enumerate(zip(args, self.dtypes)):
                if d is None:
                    command.set_param_at_index(i, a)
                else:
                    command.set_param_at_index_from_ctype(i, wp.from_torch(
                        a, dtype=d, requires_grad=False, return_ctype=True))
        command.launch()

