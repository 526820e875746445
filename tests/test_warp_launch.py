"""Recorded warp launches re-point what changed between calls, and only that."""
import torch
import warp as wp

from prox_engine.assets import configure_warp
from prox_engine.warp_launch import CpuKernel

configure_warp()


@wp.kernel
def _fill(out: wp.array(dtype=wp.float32), source: wp.array(dtype=wp.float32),
          scale: float, shift: wp.vec2):
    i = wp.tid()
    out[i] = source[i] * scale + shift[0] - shift[1]


_FILL = CpuKernel(_fill, (wp.float32, wp.float32, None, None))


def test_changed_values_and_tensors_are_seen_and_kept_ones_reused():
    source = torch.arange(5.0)
    first, second = torch.zeros(5), torch.zeros(5)
    _FILL(5, first, source, 2.0, wp.vec2(1.0, 0.0))
    assert first.tolist() == [1.0, 3.0, 5.0, 7.0, 9.0]
    _FILL(5, second, source, 2.0, wp.vec2(1.0, 0.0))  # a new output, the same values
    assert second.tolist() == first.tolist()
    _FILL(5, first, source, -1.0, wp.vec2(0.0, 0.5))  # new values, the first output again
    assert first.tolist() == [-0.5, -1.5, -2.5, -3.5, -4.5]
    source.mul_(10.0)  # the same tensor changed in place: read afresh
    _FILL(3, second, source[:3], -1.0, wp.vec2(0.0, 0.5))  # a view, another size
    assert second.tolist() == [-0.5, -10.5, -20.5, 7.0, 9.0]
