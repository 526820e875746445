"""The warp kernel that picks each point's nearest candidate triangle and its side."""
from __future__ import annotations

import pytest
import torch

from prox_engine.nearest_face import TIE, nearest_faces


def _closest_point(p, a, b, c):
    """Ericson's closest point on triangles (a, b, c) to points p, all (..., 3), as torch
    masks (vertex regions over edges over the face): the engine's code before the kernel,
    kept as the kernel's reference."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    tiny = torch.finfo(p.dtype).tiny
    denom = (va + vb + vc).clamp_min(tiny)
    result = a + ab * (vb / denom)[..., None] + ac * (vc / denom)[..., None]
    picks = [
        ((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
         b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)).clamp_min(tiny))[..., None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * (d2 / (d2 - d6).clamp_min(tiny))[..., None]),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * (d1 / (d1 - d3).clamp_min(tiny))[..., None]),
        ((d6 >= 0) & (d5 <= d6), c), ((d3 >= 0) & (d4 <= d3), b), ((d1 <= 0) & (d2 <= 0), a)]
    for mask, point in picks:
        result = torch.where(mask[..., None], point, result)
    return result


def _reference(points, cand, tri, normals, areas):
    """The candidates' choice as torch computed it (scene_sdf, before the kernel)."""
    p = points[:, None].expand(-1, cand.shape[1], -1)
    t = tri[cand]
    closest = _closest_point(p, t[:, :, 0], t[:, :, 1], t[:, :, 2])
    diff = p - closest
    dist = diff.pow(2).sum(-1).sqrt()
    plane = (diff * normals[cand]).sum(-1)
    best = dist.min(dim=1, keepdim=True).values
    score = torch.where(dist <= best + TIE, plane.abs(), torch.full_like(plane, -1.0))
    choice = score.argmax(dim=1, keepdim=True)
    if areas is None:
        sign = torch.sign(plane.gather(1, choice)).squeeze(1)
    else:
        sign = torch.sign((areas[cand] * plane / dist.clamp_min(1e-12)).sum(1))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    return closest[torch.arange(len(p)), choice.squeeze(1)], sign


def _triangles(count: int) -> torch.Tensor:
    """Random triangles, with slivers, needles and collapsed ones among them."""
    tri = torch.randn(count, 3, 3, dtype=torch.float64)
    tri[::7, 2] = tri[::7, 0] + 1e-9 * torch.randn(len(tri[::7]), 3, dtype=torch.float64)
    tri[1::7, 2] = (tri[1::7, 0] + tri[1::7, 1]) / 2  # collinear
    tri[2::7, 1] = tri[2::7, 0]  # two corners in one
    return tri


@pytest.mark.parametrize("vote", [False, True])
def test_the_kernel_chooses_as_the_torch_code_did_bit_for_bit(vote):
    """Points around random, degenerate and edge-sharing triangles (ties decided by the
    farthest plane, or the area vote): the same nearest points and signs to the last bit
    as the torch code the kernel replaced, so fits did not move."""
    torch.manual_seed(3)
    tri = _triangles(300)
    tri[200:250, :2] = tri[150:200, :2]  # pairs sharing an edge: tied candidates
    normals = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-12)
    areas = torch.rand(300, dtype=torch.float64) if vote else None
    points = torch.randn(2000, 3, dtype=torch.float64) * 1.5
    cand = torch.randint(0, 300, (2000, 6))
    cand[:500, 0], cand[:500, 1] = torch.arange(150, 200).repeat(10), torch.arange(200, 250
                                                                                   ).repeat(10)
    points[:500] = (tri[cand[:500, 0], 0] + tri[cand[:500, 0], 1]) / 2 + 0.1 * torch.randn(
        500, 3, dtype=torch.float64)  # near the shared edges
    closest, sign = nearest_faces(points, cand, tri, normals, areas)
    expected_closest, expected_sign = _reference(points, cand, tri, normals, areas)
    assert torch.equal(closest, expected_closest)
    assert torch.equal(sign, expected_sign)
    assert set(sign.unique().tolist()) == {-1.0, 1.0}


def test_the_nearest_point_is_the_nearest_of_the_candidates_surfaces():
    """Against brute force: the distance to the point found is no more than to any of
    10,000 points spread over each candidate triangle, and within their spacing of the
    least of them (proper triangles: Ericson's regions take a collapsed one's first
    corner)."""
    torch.manual_seed(4)
    tri = torch.randn(40, 3, 3, dtype=torch.float64)
    normals = torch.nn.functional.normalize(
        torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1)
    points = torch.randn(300, 3, dtype=torch.float64)
    cand = torch.randint(0, 40, (300, 4))
    closest, _ = nearest_faces(points, cand, tri, normals)
    u, v = torch.meshgrid(*[torch.linspace(0, 1, 100, dtype=torch.float64)] * 2,
                          indexing="ij")
    keep = (u + v) <= 1
    u, v = u[keep], v[keep]
    t = tri[cand]  # (N, k, 3, 3)
    spread = (t[:, :, None, 0] + (t[:, :, None, 1] - t[:, :, None, 0]) * u[:, None]
              + (t[:, :, None, 2] - t[:, :, None, 0]) * v[:, None])  # (N, k, S, 3)
    brute = (spread - points[:, None, None]).norm(dim=-1).flatten(1).min(1).values
    found = (closest - points).norm(dim=1)
    edge = (t - t.roll(1, 2)).norm(dim=-1).amax((1, 2))
    assert (found <= brute + 1e-12).all()
    assert (brute - found <= 2 * edge / 99).all()
