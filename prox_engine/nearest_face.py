"""The nearest of each point's candidate triangles and the sign it gives, in one warp kernel.

Ericson's closest point on a triangle and the choice of
:func:`scene_sdf.triangle_signed_distance`, in float64, per point in one pass: torch spent
18 of a 30 ms query of 17,000 points (the k-d tree the rest) on about forty elementwise
passes over their (N, k, 3) candidates, and this takes 2.3. warp is anny's own kernel
compiler; ``prox setup`` warms its cache."""
from __future__ import annotations

import torch
import warp as wp

from .warp_launch import CpuKernel

# Candidates whose distance is within this (m) of the nearest tie: the one whose plane the
# point is farthest from decides the sign (right on convex and concave edges alike).
TIE = 1e-6


@wp.func
def _closest(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec3d:
    """Ericson's closest point on triangle abc, its regions tried in the order the torch
    code before this kernel let them override each other (vertices a, b, c, then edges
    ab, ac, bc, then the face; tests/test_nearest_face.py keeps that code)."""
    tiny = wp.float64(2.2250738585072014e-308)
    zero = wp.float64(0.0)
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    if d1 <= zero and d2 <= zero:
        return a
    if d3 >= zero and d4 <= d3:
        return b
    if d6 >= zero and d5 <= d6:
        return c
    if vc <= zero and d1 >= zero and d3 <= zero:
        return a + ab * (d1 / wp.max(d1 - d3, tiny))
    if vb <= zero and d2 >= zero and d6 <= zero:
        return a + ac * (d2 / wp.max(d2 - d6, tiny))
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        return b + (c - b) * ((d4 - d3) / wp.max((d4 - d3) + (d5 - d6), tiny))
    denom = wp.max(va + vb + vc, tiny)
    return a + ab * (vb / denom) + ac * (vc / denom)


MAX_K = 8  # candidates a point may have
FacesK = wp.types.vector(length=MAX_K, dtype=wp.int64)  # a point's candidate faces
_lengths_k = wp.types.vector(length=MAX_K, dtype=wp.float64)


@wp.func
def nearest_face(p: wp.vec3d, faces: FacesK, k: int, corners: wp.array2d(dtype=wp.vec3d),
                 normals: wp.array(dtype=wp.vec3d), areas: wp.array(dtype=wp.float64),
                 vote: int) -> tuple[wp.vec3d, wp.float64]:
    """The nearest point on the nearest of the first ``k`` candidate ``faces`` of ``p``,
    and the sign of its side (see :func:`nearest_faces`)."""
    lengths = _lengths_k()
    best = wp.float64(1e300)
    xs = _lengths_k()  # the candidates' closest points, coordinate by coordinate
    ys = _lengths_k()
    zs = _lengths_k()
    for j in range(k):
        f = faces[j]
        q = _closest(p, corners[f, 0], corners[f, 1], corners[f, 2])
        xs[j] = q[0]
        ys[j] = q[1]
        zs[j] = q[2]
        lengths[j] = wp.length(p - q)
        best = wp.min(best, lengths[j])
    score = wp.float64(-2.0)
    chosen = wp.vec3d()
    plane_of_chosen = wp.float64(0.0)
    ballot = wp.float64(0.0)
    for j in range(k):
        f = faces[j]
        q = wp.vec3d(xs[j], ys[j], zs[j])
        dist = lengths[j]
        plane = wp.dot(p - q, normals[f])
        tied = wp.where(dist <= best + wp.float64(TIE), wp.abs(plane), wp.float64(-1.0))
        if tied > score:
            score = tied
            chosen = q
            plane_of_chosen = plane
        if vote != 0:
            ballot += areas[f] * plane / wp.max(dist, wp.float64(1e-12))
    decided = wp.where(vote != 0, ballot, plane_of_chosen)
    return chosen, wp.where(decided < wp.float64(0.0), wp.float64(-1.0), wp.float64(1.0))


@wp.kernel
def _nearest(points: wp.array(dtype=wp.vec3d), candidates: wp.array2d(dtype=wp.int64),
             corners: wp.array2d(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d),
             areas: wp.array(dtype=wp.float64), vote: int,
             closest: wp.array(dtype=wp.vec3d), sign: wp.array(dtype=wp.float64)):
    i = wp.tid()
    faces = FacesK()
    k = candidates.shape[1]
    for j in range(k):
        faces[j] = candidates[i, j]
    q, side = nearest_face(points[i], faces, k, corners, normals, areas, vote)
    closest[i] = q
    sign[i] = side


_NEAREST = CpuKernel(_nearest, (wp.vec3d, wp.int64, wp.vec3d, wp.vec3d, wp.float64, None,
                                wp.vec3d, wp.float64))


def nearest_faces(points: torch.Tensor, candidates: torch.Tensor, triangles: torch.Tensor,
                  normals: torch.Tensor, areas: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """For points (N, 3) float64 and their ``candidates`` (N, k) int64 indices into
    ``triangles`` (F, 3, 3) float64 with unit ``normals`` (F, 3): the nearest point (N, 3)
    on the nearest candidate, and the sign (N,) of the point's side, read from that
    candidate's plane (of the candidates tied within TIE, the farthest plane) or, with face
    ``areas`` (F,), by every candidate's vote weighted by its area and by how squarely it
    faces the point; a point exactly on the plane is outside (+1)."""
    if candidates.shape[1] > MAX_K:
        raise ValueError(f"{candidates.shape[1]} candidates a point: at most {MAX_K}")
    n = len(points)
    closest = torch.empty((n, 3), dtype=torch.float64)
    sign = torch.empty(n, dtype=torch.float64)
    vote = areas is not None
    unread = sign[:0]  # the kernel reads no areas without a vote
    _NEAREST(n, points.double().contiguous(), candidates.contiguous(), triangles.contiguous(),
             normals.contiguous(), areas.contiguous() if vote else unread, int(vote), closest,
             sign)
    return closest, sign
