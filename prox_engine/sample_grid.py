"""The k nearest surface samples of points near a scene's surfaces, exactly, from a grid
of cells in a warp kernel.

The exact distances of the penetration term and the scale search start from the faces of
each point's k nearest surface samples. scipy's k-d tree took 0.7 ms for the 900 points
a scene evaluation asks about (0.8 us each on a 300,000-sample room), some 60 ms a frame.
Here each point scans the cells around its own, ring by ring, until its k-th nearest
sample so far is nearer than any sample outside the rings can be; a point with fewer than
k samples within one ring (far from every surface), one that needs more than two rings,
or one outside the grid is left to the tree (a third ring cost ten times what it saved).
The answer is the tree's: the same samples in the same order (up to exact ties)."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp
from scipy.spatial import cKDTree

from .warp_launch import CpuKernel

MAX_K = 8
CELL = 0.05  # m: 2.5 samples' spacings: a few samples a cell, most points done in one ring
MAX_CELLS = 1 << 24  # a larger room gets larger cells (the grid holds an int32 per cell)
RINGS = 2  # rings of cells around a point's own scanned before it is left to the tree

_nearest_k = wp.types.vector(length=MAX_K, dtype=wp.float64)
_index_k = wp.types.vector(length=MAX_K, dtype=wp.int32)


@wp.func
def _face_gap(position: wp.float64, low: int, high: int, count: int, cell: wp.float64
              ) -> wp.float64:
    """How far a point at ``position`` (grid units) is from the nearer face of the cells
    low..high that has grid cells beyond it (a face at the grid's edge has none)."""
    gap = wp.float64(1.0e30)
    if low > 0:
        gap = wp.min(gap, (position - wp.float64(low)) * cell)
    if high < count - 1:
        gap = wp.min(gap, (wp.float64(high + 1) - position) * cell)
    return gap


@wp.func
def k_nearest(p: wp.vec3d, samples: wp.array(dtype=wp.vec3d), starts: wp.array(dtype=wp.int32),
              origin: wp.vec3d, cell: wp.float64, dims: wp.vec3i, k: int, rings: int
              ) -> tuple[_index_k, _nearest_k, int]:
    """The first ``k`` slots of the grid order's indices and squared distances of the
    samples nearest to ``p``, nearest first, and whether they are certain (1; else 0: the
    point is left to the tree)."""
    best = _nearest_k()
    index = _index_k()
    for j in range(MAX_K):
        best[j] = wp.float64(1.0e300)
        index[j] = -1
    u = (p - origin) / cell
    cx = int(wp.floor(u[0]))
    cy = int(wp.floor(u[1]))
    cz = int(wp.floor(u[2]))
    if cx < 0 or cy < 0 or cz < 0 or cx >= dims[0] or cy >= dims[1] or cz >= dims[2]:
        return index, best, 0
    for r in range(rings + 1):
        for dx in range(-r, r + 1):
            x = cx + dx
            if x < 0 or x >= dims[0]:
                continue
            for dy in range(-r, r + 1):
                y = cy + dy
                if y < 0 or y >= dims[1]:
                    continue
                for dz in range(-r, r + 1):
                    z = cz + dz
                    if z < 0 or z >= dims[2]:
                        continue
                    if wp.max(wp.max(wp.abs(dx), wp.abs(dy)), wp.abs(dz)) != r:
                        continue  # scanned in an inner ring
                    c = (x * dims[1] + y) * dims[2] + z
                    for s in range(starts[c], starts[c + 1]):
                        d = samples[s] - p
                        distance = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                        if distance < best[k - 1]:
                            slot = k - 1
                            while slot > 0 and best[slot - 1] > distance:
                                best[slot] = best[slot - 1]
                                index[slot] = index[slot - 1]
                                slot -= 1
                            best[slot] = distance
                            index[slot] = s
        gap = wp.min(wp.min(_face_gap(u[0], cx - r, cx + r, dims[0], cell),
                            _face_gap(u[1], cy - r, cy + r, dims[1], cell)),
                     _face_gap(u[2], cz - r, cz + r, dims[2], cell))
        if index[k - 1] < 0 and r > 0:
            return index, best, 0  # far from every surface: the tree is quicker
        if best[k - 1] <= gap * gap:
            return index, best, 1
    return index, best, 0


@wp.kernel
def _nearest(points: wp.array(dtype=wp.vec3d), samples: wp.array(dtype=wp.vec3d),
             starts: wp.array(dtype=wp.int32), origin: wp.vec3d, cell: wp.float64,
             dims: wp.vec3i, k: int, rings: int, found: wp.array2d(dtype=wp.int64),
             squared: wp.array2d(dtype=wp.float64), certain: wp.array(dtype=wp.int32)):
    i = wp.tid()
    index, best, sure = k_nearest(points[i], samples, starts, origin, cell, dims, k, rings)
    certain[i] = sure
    if sure != 0:
        for j in range(k):
            found[i, j] = wp.int64(index[j])
            squared[i, j] = best[j]


_NEAREST = CpuKernel(_nearest, (wp.vec3d, wp.vec3d, wp.int32, None, None, None, None, None,
                                wp.int64, wp.float64, wp.int32))


@dataclass
class SampleGrid:
    """Surface samples in cells of about :data:`CELL`, with the k-d ``tree`` of the same
    samples for the points the cells cannot answer (:meth:`build` makes one)."""

    samples: torch.Tensor  # (S, 3) float64, in grid order
    order: np.ndarray  # (S,) grid slot -> sample index
    starts: torch.Tensor  # (cells + 1,) int32: each cell's first grid slot
    origin: np.ndarray  # (3,) the grid's corner
    dims: np.ndarray  # (3,) cells along x, y, z
    cell: float  # m
    tree: cKDTree

    @classmethod
    def build(cls, samples: np.ndarray, tree: cKDTree) -> SampleGrid:
        """The grid of surface ``samples`` (S, 3); ``tree`` is their k-d tree."""
        samples = np.asarray(samples, dtype=np.float64)
        low, high = samples.min(0), samples.max(0)
        cell = max(CELL, float(np.prod(high - low + 2 * CELL) / MAX_CELLS) ** (1 / 3))
        origin = low - cell
        dims = (np.floor((high - origin) / cell).astype(np.int64) + 2)
        cells = np.floor((samples - origin) / cell).astype(np.int64)
        flat = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        order = np.argsort(flat, kind="stable")
        counts = np.bincount(flat, minlength=int(np.prod(dims)))
        starts = torch.from_numpy(np.concatenate([[0], np.cumsum(counts)]).astype(np.int32))
        return cls(torch.from_numpy(samples[order]), order, starts, origin, dims, cell, tree)

    def arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays (no pickle) of everything, the tree's own state included, for
        :meth:`from_arrays`: a scene's cache keeps them, and a work-horse then restores
        the tree of a 120,000-sample room in 5 ms instead of building it in 30-48."""
        (buffer, data, _, _, leafsize, maxes, mins, indices,
         boxsize, _) = self.tree.__getstate__()
        if boxsize is not None:
            raise ValueError("a periodic k-d tree is not a scene's")
        return {"tree_buffer": buffer, "tree_data": data, "tree_indices": indices,
                "tree_maxes": maxes, "tree_mins": mins, "tree_leafsize": np.int64(leafsize),
                "order": self.order, "starts": self.starts.numpy(), "origin": self.origin,
                "dims": self.dims, "cell": np.float64(self.cell)}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> SampleGrid:
        """The grid :meth:`arrays` gave; a ValueError, KeyError or TypeError if they are
        damaged or a scipy of another layout wrote them."""
        data = np.asarray(arrays["tree_data"], dtype=np.float64)
        order = arrays["order"]
        if data.ndim != 2 or data.shape[1] != 3 or order.shape != (len(data),):
            raise ValueError("the samples and their grid order disagree")
        tree = cKDTree.__new__(cKDTree)
        tree.__setstate__((arrays["tree_buffer"], data, len(data), 3,
                           int(arrays["tree_leafsize"]), arrays["tree_maxes"],
                           arrays["tree_mins"], arrays["tree_indices"], None, None))
        return cls(torch.from_numpy(data[order]), order, torch.from_numpy(arrays["starts"]),
                   arrays["origin"], arrays["dims"], float(arrays["cell"]), tree)

    def query(self, points: np.ndarray, k: int, workers: int = 1
              ) -> tuple[np.ndarray, np.ndarray]:
        """Distances and indices (N, k) of the ``k`` (at most :data:`MAX_K`) nearest
        samples of finite ``points`` (N, 3), nearest first, as ``cKDTree.query`` gives
        them (``workers``: the tree's threads for the points left to it)."""
        if not 0 < k <= MAX_K:
            raise ValueError(f"k = {k}: the grid finds 1 to {MAX_K} nearest samples")
        points = np.ascontiguousarray(points, dtype=np.float64)
        found = torch.zeros(len(points), k, dtype=torch.int64)
        squared = torch.zeros(len(points), k, dtype=torch.float64)
        certain = torch.empty(len(points), dtype=torch.int32)
        _NEAREST(len(points), torch.from_numpy(points), self.samples, self.starts,
                 wp.vec3d(*self.origin), wp.float64(self.cell), wp.vec3i(*self.dims.tolist()),
                 k, RINGS, found, squared, certain)
        found, distance = found.numpy(), np.sqrt(squared.numpy())
        found = self.order[found]
        left = np.flatnonzero(certain.numpy() == 0)
        if len(left):
            near, which = self.tree.query(points[left], k=k, workers=workers)
            distance[left], found[left] = np.reshape(near, (-1, k)), np.reshape(which, (-1, k))
        return distance, found
