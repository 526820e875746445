"""Small geometry kernels: body normals, axis-angle rotations, camera rays."""
from __future__ import annotations

import torch
import warp as wp

from .warp_launch import CpuKernel


def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit normals (F, 3) of triangles, or (B, F, 3) for batched vertices (B, V, 3)."""
    tri = vertices[..., faces, :]
    n = torch.linalg.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals, (B, V, 3) for (B, V, 3) vertices."""
    tri = vertices[:, faces]  # B, F, 3, 3
    n = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    out = sum_into(n.repeat(1, 3, 1), faces.T.reshape(-1), vertices.shape[1])
    return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def sum_into(values: torch.Tensor, slots: torch.Tensor, count: int) -> torch.Tensor:
    """(B, count, 3): each batch element's ``values`` (B, N, 3) summed into their ``slots``
    (N,). One index_add over the flattened batch: along dimension 1 of a 3-D tensor torch
    takes a path 4-5x slower on a CPU."""
    batch = len(values)
    flat = (torch.arange(batch)[:, None] * count + slots).reshape(-1)
    return values.new_zeros(batch * count, 3).index_add_(
        0, flat, values.reshape(-1, 3)).view(batch, count, 3)


def picked(points: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """``points[:, ids]`` for ``points`` (B, V, 3), differentiable. For several bodies by
    index_select and :func:`sum_into`: torch's advanced index and its accumulating
    backward took 0.86 ms for the penetration term's 6,400 of 9,300 vertices on 8 bodies,
    these 0.61; on one body they are 10-30 % slower."""
    return points[:, ids] if len(points) == 1 else _Picked.apply(points, ids)


class _Picked(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
        ctx.ids, ctx.count = ids, points.shape[1]
        return points.index_select(1, ids)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        return sum_into(grad.contiguous(), ctx.ids, ctx.count), None


@wp.kernel
def _vertex_normals(vertices: wp.array2d(dtype=wp.vec3), faces: wp.array(dtype=wp.vec3i),
                    first: wp.array(dtype=wp.int32), around: wp.array(dtype=wp.int32),
                    slot: wp.array(dtype=wp.int32), normals: wp.array2d(dtype=wp.vec3)):
    b, i = wp.tid()
    v = slot[i]
    n = wp.vec3(0.0, 0.0, 0.0)
    for j in range(first[v], first[v + 1]):
        f = faces[around[j]]
        a = vertices[b, f[0]]
        n += wp.cross(vertices[b, f[1]] - a, vertices[b, f[2]] - a)
    normals[b, i] = n / wp.max(wp.length(n), 1e-12)


_VERTEX_NORMALS = CpuKernel(_vertex_normals, (wp.vec3, wp.vec3i, wp.int32, wp.int32, wp.int32,
                                              wp.vec3))


class VertexNormals:
    """Area-weighted unit normals of a fixed set of mesh vertices (the contact vertices),
    without gradient, from the faces around them only, in one warp kernel: 0.5 ms in torch
    for a body's contact set, a contact evaluation's largest part."""

    def __init__(self, faces: torch.Tensor, ids: torch.Tensor) -> None:
        self.ids = ids
        unique, order = torch.unique(ids, return_inverse=True)
        slot = torch.full((int(faces.max()) + 1,), -1, dtype=torch.long)
        slot[unique] = torch.arange(len(unique))
        corners = slot[faces]  # (F, 3): slot of each corner, -1 if not in ids
        face, corner = torch.nonzero(corners >= 0, as_tuple=True)
        owner = corners[face, corner]
        by_owner = torch.argsort(owner, stable=True)
        self._faces = faces.to(torch.int32).contiguous()
        self._first = torch.cat([torch.zeros(1, dtype=torch.long),
                                 torch.bincount(owner, minlength=len(unique)).cumsum(0)]
                                ).to(torch.int32)
        self._around = face[by_owner].to(torch.int32)  # each slot's faces, slot by slot
        self._slot = order.to(torch.int32)

    def __call__(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, len(ids), 3) normals of (B, V, 3) vertices."""
        normals = torch.empty(len(vertices), len(self._slot), 3)
        _VERTEX_NORMALS((len(vertices), len(self._slot)),
                        vertices.detach().float().contiguous(), self._faces, self._first,
                        self._around, self._slot, normals)
        return normals


def grid_subsample(points: torch.Tensor, spacing: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Ascending indices of one of ``points`` (N, 3), the first, in each occupied cell of
    a grid of ``spacing`` aligned with the origin, and how many points each cell holds."""
    _, cell, counts = torch.unique(torch.floor(points / spacing).long(), dim=0,
                                   return_inverse=True, return_counts=True)
    first = torch.full((len(counts),), len(points)).scatter_reduce(
        0, cell, torch.arange(len(points)), "amin")
    order = first.argsort()
    return first[order], counts[order]


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula for (..., 3) axis-angle vectors, smooth at zero: R = I + s K +
    c K^2 with K the cross-product matrix of the vector, s = sin(t) / t and c = (1 -
    cos(t)) / t^2 (t its angle). Differentiated in closed form (:class:`_Rodrigues`):
    autograd's trace of the formula's two dozen operations cost more than the arithmetic
    (SMPL-X turns 55 joints an evaluation; anny's bone chain has its own, in warp)."""
    return _Rodrigues.apply(aa)


def _rodrigues_terms(aa: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """K, s, c (see :func:`axis_angle_to_matrix`) and t^2 of axis-angles (..., 3), with
    Taylor expansions near zero."""
    theta2 = (aa * aa).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-16)
    small = theta2 < 1e-8
    s = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    c = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-16))
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(aa.shape + (3,))
    return k, s, c, theta2


def _vee(m: torch.Tensor) -> torch.Tensor:
    """(..., 3) the inner products of (..., 3, 3) with the cross-product matrices of the
    unit axes: m_zy - m_yz, m_xz - m_zx, m_yx - m_xy."""
    return torch.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                        m[..., 1, 0] - m[..., 0, 1]], -1)


class _Rodrigues(torch.autograd.Function):
    """R(a) = I + s K + c K^2; with G the gradient in R, the gradient in a is
    a (s'/t <G, K> + c'/t <G, K^2>) + s vee(G) + c vee(G K^T + K^T G), the derivatives'
    ratios to t by their series below 0.1 rad (where float32 would lose them)."""

    @staticmethod
    def forward(ctx, aa: torch.Tensor) -> torch.Tensor:
        k, s, c, theta2 = _rodrigues_terms(aa)
        kk = k @ k
        ctx.save_for_backward(aa, k, kk, s, c, theta2)
        eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand(k.shape)
        return eye + s[..., None] * k + c[..., None] * kk

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        aa, k, kk, s, c, t2 = ctx.saved_tensors
        series = t2 < 1e-2
        t = torch.where(series, torch.ones_like(t2), t2).sqrt()  # no 0 / 0 where unused
        cos, sin = torch.cos(t), torch.sin(t)
        ds = torch.where(series, -1 / 3 + t2 / 30 - t2 ** 2 / 840, (t * cos - sin) / t ** 3)
        dc = torch.where(series, -1 / 12 + t2 / 180 - t2 ** 2 / 6720,
                         (t * sin - 2 * (1 - cos)) / t ** 4)
        along = (ds * (grad * k).sum((-1, -2))[..., None]
                 + dc * (grad * kk).sum((-1, -2))[..., None])
        kt = k.transpose(-1, -2)
        return aa * along + s * _vee(grad) + c * _vee(grad @ kt + kt @ grad)


def turned_onto_ray(pivot: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``points`` (..., N, 3) in camera coordinates turned rigidly about ``pivot``
    (..., 3) until the first lies on the other point of its camera ray at its distance
    from the pivot: a limb seen from in front projects alike pointing toward the camera
    or away from it. A first point whose ray meets that sphere once stays put."""
    first = points[..., 0, :]
    ray = first / first.norm(dim=-1, keepdim=True)
    other = (2 * (ray * pivot).sum(-1, keepdim=True) - first.norm(dim=-1, keepdim=True)) * ray
    was, goes = first - pivot, other - pivot
    axis = torch.linalg.cross(was, goes, dim=-1)
    angle = torch.atan2(axis.norm(dim=-1), (was * goes).sum(-1))
    turn = axis_angle_to_matrix(axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
                                * angle[..., None])
    return pivot[..., None, :] + (points - pivot[..., None, :]) @ turn.transpose(-1, -2)


def ray_points_at(ray: torch.Tensor, centre: torch.Tensor, length: torch.Tensor,
                  slack: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The two points (..., 2, 3), nearer first, of the unit ``ray`` (..., 3) from the
    camera centre at ``length`` (...,) from ``centre`` (..., 3), and whether each is one
    ((..., 2) bool). A ray that passes the sphere within ``slack`` lengths of its centre
    gives its nearest point as the first (keypoints are not joints: a limb's length
    between two of them is a little off); the second is one only where the ray meets
    the sphere twice."""
    along = (ray * centre).sum(-1)
    square = along ** 2 - (centre ** 2).sum(-1) + length ** 2
    root = square.clamp_min(0).sqrt()
    points = torch.stack([along - root, along + root], -1)[..., None] * ray[..., None, :]
    return points, torch.stack([square >= (1 - slack ** 2) * length ** 2, square > 0], -1)


def matrix_to_axis_angle(r: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`axis_angle_to_matrix` (roma's, differentiable away from pi)."""
    import roma

    return roma.rotmat_to_rotvec(r)
