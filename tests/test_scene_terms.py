"""SDF sign and distances, penetration and contact terms, projection."""
from __future__ import annotations

import functools
import itertools
import math

import numpy as np
import pytest
import torch
import trimesh

from prox_engine.camera import Camera
from prox_engine.losses import contact_energy, penetration_energy
from prox_engine.scene import Scene
from prox_engine.scene_sdf import SignedDistanceField, cached_sdf, compute_sdf

from .conftest import closed_box, plane_mesh


@functools.cache
def _prox_size_weight() -> float:
    from prox_engine.config import load_config

    return load_config("prox").scale_size_weight


def best_scale(*args, **kwargs) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`scale_search.best_scale` with ``prox``'s size prior weight (read once)."""
    from prox_engine.scale_search import best_scale as search

    return search(*args, size_weight=_prox_size_weight(), **kwargs)


def _carrying(body) -> torch.Tensor:
    from prox_engine.scale_search import carrying_vertices

    return carrying_vertices(body.contact_parts, body.num_vertices)


def _seen_scene(mesh, cam2world: np.ndarray, dim: int, spacing: float = 0.05) -> Scene:
    """The scan ``mesh`` (world frame) as seen by the camera at ``cam2world``."""
    return Scene(mesh.vertices, mesh.faces, cam2world,
                 compute_sdf(mesh.vertices, mesh.faces, dim=dim, padding=0.5),
                 sample_spacing=spacing)


def _in_camera(points: torch.Tensor, cam2world: np.ndarray) -> torch.Tensor:
    """World points (..., 3) in the frame of the camera at ``cam2world``."""
    rotation = torch.tensor(cam2world[:3, :3], dtype=torch.float32)
    return (points - torch.tensor(cam2world[:3, 3], dtype=torch.float32)) @ rotation


def _scene(mesh, dim=64) -> Scene:
    """The scan ``mesh`` with the camera frame the world's."""
    return _seen_scene(mesh, np.eye(4), dim)


def test_sdf_sign_and_distance_on_closed_box():
    box = closed_box()
    sdf = compute_sdf(box.vertices, box.faces, dim=64, padding=0.5)
    points = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.1, -0.2], [0.9, 0.0, 0.0],
                           [0.0, 0.0, 0.7], [0.6, 0.6, 0.6]])
    values = sdf(points)
    expected = torch.tensor([-0.5, -0.2, 0.4, 0.2, math.sqrt(3 * 0.1 ** 2)])
    assert torch.all(values[:2] < 0) and torch.all(values[2:] > 0)
    assert torch.allclose(values, expected, atol=0.02)


def test_sdf_far_field_keeps_room_air_outside():
    """Far from every surface, an open furniture box on a floor in a non-cubic room must
    not flip the air above the floor to inside (the sign comes from the band around the
    surface, not from a far-away edge's normal) and distances must be metric."""

    floor = plane_mesh()  # 4 m x 4 m at z = 0, normal up
    box = trimesh.creation.box([0.5, 0.5, 0.5])
    box.vertices += [1.0, 1.0, 0.25]
    box.update_faces(box.face_normals[:, 2] > -0.5)  # scans never see under furniture
    mesh = trimesh.util.concatenate([floor, box])
    sdf = compute_sdf(mesh.vertices, mesh.faces, dim=48, padding=0.5)
    xs = torch.linspace(-1.9, 1.9, 12)
    pts = torch.stack(torch.meshgrid(xs, xs, torch.tensor([0.3, 0.8, 0.95]), indexing="ij"),
                      -1).reshape(-1, 3)
    in_box = ((pts[:, :2] - torch.tensor([1.0, 1.0])).abs() < 0.4).all(1) & (pts[:, 2] < 0.6)
    values = sdf(pts[~in_box])
    assert torch.all(values > 0)
    above_floor = pts[~in_box][:, 2]
    assert torch.all(values <= above_floor + 0.03)  # never farther than the floor


def test_sdf_sign_on_open_plane():
    """A single-sided plane: above is outside, below is inside (winding numbers fail here)."""
    plane = plane_mesh()
    sdf = compute_sdf(plane.vertices, plane.faces, dim=64, padding=0.5)
    xy = torch.tensor([[0.3, -0.7], [1.2, 0.4], [-1.5, 1.5]])
    for z in (0.05, 0.2, 0.4):
        above = sdf(torch.cat([xy, torch.full((3, 1), z)], 1))
        below = sdf(torch.cat([xy, torch.full((3, 1), -z)], 1))
        assert torch.allclose(above, torch.full((3,), z), atol=0.01)
        assert torch.allclose(below, torch.full((3,), -z), atol=0.01)


def test_sdf_save_load_round_trip_and_cache(tmp_path):
    box = closed_box()
    first = cached_sdf(box.vertices, box.faces, tmp_path, dim=32)
    files = sorted(p.name for p in tmp_path.iterdir())
    assert len(files) == 2 and files[0].endswith(".json") and files[1].endswith("_sdf.npy")
    again = cached_sdf(box.vertices, box.faces, tmp_path, dim=32)
    assert torch.equal(first.grid, again.grid)
    loaded = SignedDistanceField.load(tmp_path / files[0], tmp_path / files[1])
    assert loaded.dim == 32 and torch.equal(loaded.grid, first.grid)


def test_penetration_gradient_pushes_vertex_out():
    scene = _scene(plane_mesh())
    point = torch.tensor([[[0.2, 0.1, -0.05]]], requires_grad=True)
    energy = penetration_energy(point, scene)
    assert energy.item() > 0
    energy.sum().backward()
    step = -point.grad[0, 0]
    assert step[2] > 0 and step[2].abs() > 10 * step[:2].abs().max()
    outside = torch.tensor([[[0.2, 0.1, 0.05]]])
    assert penetration_energy(outside, scene).item() == 0


def test_exact_distance_gradient_is_the_direction_from_the_nearest_surface_point():
    """The exact distances are found without autograd and differentiated as |p - c|: the
    gradient must still be the true one, in a face's interior, by its edges and corners
    and inside, on a box turned off the axes (central differences)."""
    from prox_engine.scene_sdf import triangle_signed_distance

    box = trimesh.creation.box(extents=(0.6, 0.4, 0.3))
    box.apply_transform(trimesh.transformations.euler_matrix(0.3, -0.5, 0.8))
    scene = _scene(box, dim=32)
    torch.manual_seed(1)
    points = (torch.rand(200, 3, dtype=torch.float64) - 0.5) * 0.9
    points.requires_grad_(True)

    def distance(p):
        return triangle_signed_distance(p, scene._samples, scene._sample_face,
                                        scene._triangles64, scene._normals64)[0]

    d = distance(points)
    assert (d < 0).sum() > 10 and (d > 0).sum() > 10
    grad, = torch.autograd.grad(d.sum(), points)
    h = 1e-5
    numeric = torch.stack([(distance(points.detach() + h * e) - distance(points.detach() - h * e))
                           / (2 * h) for e in torch.eye(3, dtype=torch.float64)], 1)
    agree = (grad - numeric).norm(dim=1) < 1e-3
    assert agree.float().mean() > 0.97  # a few points sit where the nearest face changes
    assert torch.allclose(grad.norm(dim=1), torch.ones(200, dtype=torch.float64), atol=1e-6)


def test_penetration_tolerance_lets_a_body_sink_into_a_cushion():
    """Within the tolerance (a cushion's give, a scan's misregistration) penetration costs
    nothing and pushes nowhere; beyond it, the excess is pushed out as before."""
    scene = _scene(plane_mesh())
    shallow = torch.tensor([[[0.2, 0.1, -0.015]]], requires_grad=True)
    energy = penetration_energy(shallow, scene, tolerance=0.02)
    energy.sum().backward()
    assert energy.item() == 0 and shallow.grad.abs().max() == 0
    assert penetration_energy(shallow.detach(), scene).item() > 0  # no tolerance: pushed
    deep = torch.tensor([[[0.2, 0.1, -0.05]]])
    excess = penetration_energy(deep, scene, tolerance=0.02).item()
    assert abs(excess - (0.03 ** 2 + 0.03)) < 0.005


def test_the_flesh_a_body_rests_on_touches_and_penetrates_below_the_surface():
    """With a sink depth (flesh and cushions that give), a point 2 cm inside a floor
    touches it and penetrates nothing, where one on the surface is 2 cm from touching;
    the other points (sink 0) touch on the surface and penetrate below it, as before."""
    scene = _scene(plane_mesh())
    points = torch.tensor([[[0.2, 0.1, -0.02], [0.3, 0.1, 0.0]]])
    up = torch.tensor([0.0, 0.0, -1.0]).expand(1, 2, 3)  # facing the floor
    sink = torch.tensor([0.02, 0.02])
    touching = contact_energy(points[:, :1], up[:, :1], scene, 0.05, 45, 0.15, sink[:1])
    on_top = contact_energy(points[:, 1:], up[:, 1:], scene, 0.05, 45, 0.15, sink[1:])
    assert touching.item() < 1e-3 < on_top.item()
    assert contact_energy(points[:, :1], up[:, :1], scene, 0.05, 45, 0.15).item() > 1e-3
    assert contact_energy(points[:, 1:], up[:, 1:], scene, 0.05, 45, 0.15).item() < 1e-3
    inside = torch.tensor([[[0.2, 0.1, -0.015], [0.3, 0.1, -0.015]]])
    each = penetration_energy(inside, scene, tolerance=torch.tensor([0.02, 0.0]),
                              weights=torch.tensor([1.0, 0.0])).item()
    other = penetration_energy(inside, scene, tolerance=torch.tensor([0.02, 0.0]),
                               weights=torch.tensor([0.0, 1.0])).item()
    assert each == 0 and other > 0


def test_penetration_inside_a_slab_thinner_than_a_voxel_pushes_out():
    """A 2 cm slab on a 10 cm grid: the grid misses it, the exact band finds the point
    inside and pushes it out through the nearer face; points outside cost nothing."""
    slab = trimesh.creation.box(extents=(1.0, 1.0, 0.02))
    scene = _scene(slab, dim=24)
    assert scene.sdf.voxel_size > 0.08
    inside = torch.tensor([[[0.1, -0.2, 0.004]]], requires_grad=True)
    assert scene.signed_distance(inside.detach()).item() > 0  # the grid alone misses it
    energy = penetration_energy(inside, scene)
    assert energy.item() > 0
    energy.sum().backward()
    step = -inside.grad[0, 0]
    assert step[2] > 0 and step[2].abs() > 10 * step[:2].abs().max()  # out through the top
    above = torch.tensor([[[0.1, -0.2, 0.02], [0.3, 0.3, -0.03]]], requires_grad=True)
    energy = penetration_energy(above, scene)
    energy.sum().backward()
    assert energy.item() == 0 and above.grad.abs().max() == 0


def _blend_reach(scene: Scene, points: torch.Tensor) -> torch.Tensor:
    """(N,) the weighted mean distance (m) from camera-frame points (N, 3) to the eight
    SDF grid corners their trilinear reads blend (trilinear.blend_reach)."""
    reader = scene._camera_sdf
    linear = torch.tensor(reader.linear, dtype=torch.float64).reshape(3, 3)
    u = points.double() @ linear.T + torch.tensor(reader.offset, dtype=torch.float64)
    spacing = 1 / linear.norm(dim=1)
    f = u - u.floor()
    reach = torch.zeros(len(points), dtype=torch.float64)
    for corner in itertools.product((0, 1), repeat=3):
        corner = torch.tensor(corner, dtype=torch.bool)
        weight = torch.where(corner, f, 1 - f).prod(1)
        reach += weight * (torch.where(corner, 1 - f, f) * spacing).norm(dim=1)
    return reach.float()


def _tilted_slab() -> trimesh.Trimesh:
    slab = trimesh.creation.box(extents=(1.2, 0.8, 0.02))
    slab.apply_transform(trimesh.transformations.rotation_matrix(0.4, [1.0, 0.3, 0.0]))
    return slab


def _depth_as_read(mesh, dim: int, spacing: float, count: int
                   ) -> tuple[Scene, torch.Tensor, dict[str, torch.Tensor]]:
    """``mesh`` seen by a tilted, off-centre camera, ``count`` points about its surface
    (camera frame), and the penetration depth there as the term reads it, written in torch:
    the triangles' distances (``exact``) where the grid reads less than two voxels inside or
    less than its blend reach outside (``read``), the grid's elsewhere (``depth``), and
    its gradient by autograd (``slope``)."""
    from prox_engine.synthetic import look_at

    cam2world = look_at(np.array([0.7, -2.5, 1.3]), np.array([0.1, 0.2, 0.0]))
    scene = _seen_scene(mesh, cam2world, dim=dim, spacing=spacing)
    voxel = scene.sdf.voxel_size
    world = torch.from_numpy(mesh.sample(count, seed=0)).float()
    world = world + torch.randn(len(world), 3, generator=torch.Generator().manual_seed(0)) * voxel
    points = _in_camera(world, cam2world).requires_grad_(True)
    values = scene.signed_distance(points)
    reach = _blend_reach(scene, points.detach()).clamp(max=voxel)
    read = (values > -2 * voxel) & ((values < 0) | (values < reach))
    exact, _ = scene._triangle_distance(scene.to_world(points))
    values = values.index_put((torch.nonzero(read).flatten(),), exact[read].float())
    (slope,) = torch.autograd.grad(torch.relu(-values).sum(), points)
    return scene, points.detach(), {"read": read, "exact": exact.detach(), "slope": slope,
                                    "depth": torch.relu(-values.detach())}


def test_penetration_depth_skips_the_exact_query_only_where_nothing_can_be_inside():
    """Around a tilted slab thinner than a voxel and a box: the exact distances are read
    where the grid reads less than the band inside or less than the blend of its corners'
    distances outside (never a voxel), and every point skipped outside is outside by the
    exact distances too, but one: 5 cm from the slab's edge, where the nearest samples'
    faces sign it 4.6 cm inside a 2 cm slab (the grid's reading, outside, is right). The
    voxel alone would skip under half as many."""
    box = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    box.apply_translation([0.3, 1.4, 0.1])
    scene, camera, expected = _depth_as_read(trimesh.util.concatenate([_tilted_slab(), box]),
                                             dim=40, spacing=0.02, count=4000)
    voxel = scene.sdf.voxel_size
    depth, slope = scene.penetration_depth(camera, exact_band=2 * voxel)
    assert torch.allclose(depth, expected["depth"], atol=1e-5)
    assert torch.allclose(slope, expected["slope"], atol=1e-4)
    grid, exact, read = scene.signed_distance(camera), expected["exact"], expected["read"]
    assert (exact[read & (grid < 0)] < 0).any()  # the slab is read inside where it is
    near = grid.abs() < 2 * voxel
    skipped, by_voxel = near & ~read, near & (grid >= voxel)
    assert (_blend_reach(scene, camera) < 0.87 * voxel).all()
    assert skipped.sum() > 2 * by_voxel.sum() > 0
    assert (exact[by_voxel] > 0).all() and (exact[skipped] <= 0).sum() == 1


def test_penetration_depth_of_points_the_sample_grid_leaves_to_the_tree():
    """On a grid of 10 cm voxels over a tilted slab sampled every 5 cm, some points read
    exactly have fewer than four samples within one ring of cells: the kernel leaves them
    to the k-d tree, and every depth and slope is the grid's or the nearest triangle's as
    the term reads them."""
    scene, camera, expected = _depth_as_read(_tilted_slab(), dim=24, spacing=0.05,
                                             count=2000)
    voxel = scene.sdf.voxel_size
    _, _, left = scene._inside_depth(camera, (-2 * voxel, voxel))
    assert 5 <= left.sum() < 0.5 * len(camera)
    depth, slope = scene.penetration_depth(camera, exact_band=2 * voxel)
    assert torch.allclose(depth, expected["depth"], atol=1e-6)
    assert torch.allclose(slope, expected["slope"], atol=1e-4)
    assert (depth[left] > 0).any() and (depth[~left] > 0).any()


def test_nearest_hit_is_the_first_hit_of_the_nearest_ray():
    """Rays straight down from points over a floor and a 3 cm tabletop, seen by a tilted,
    off-centre camera: stepping a few samples at a time and stopping at the first that
    meet gives the least of every ray's first hit, and inf where none meets."""
    from prox_engine.synthetic import look_at

    table = trimesh.creation.box(extents=(0.8, 0.6, 0.03))
    table.apply_translation([0.3, 0.2, 0.7])
    mesh = trimesh.util.concatenate([plane_mesh(size=4.0), table])
    cam2world = look_at(np.array([1.5, -2.5, 1.6]), np.array([0.2, 0.3, 0.5]))
    scene = Scene(mesh.vertices, mesh.faces, cam2world,
                  compute_sdf(mesh.vertices, mesh.faces, dim=64, padding=0.5),
                  sample_spacing=0.02)
    rotation = torch.tensor(cam2world[:3, :3], dtype=torch.float32)
    shift = torch.tensor(cam2world[:3, 3], dtype=torch.float32)
    down = -scene.up_in_camera()
    generator = torch.Generator().manual_seed(1)
    for low, high, expected in ((0.75, 0.78, 0.03), (0.25, 0.45, 0.25), (0.95, 1.2, None)):
        xy = torch.rand(40, 2, generator=generator) * 0.5 + torch.tensor([0.05, -0.05])
        z = low + torch.rand(40, 1, generator=generator) * (high - low)
        starts = (torch.cat([xy, z], 1) - shift) @ rotation
        if expected is None:  # only those beside the table, up to 0.9 m over the floor
            starts = (torch.cat([xy + 1.0, z], 1) - shift) @ rotation
        directions = down.expand_as(starts)
        first = scene.first_hits(starts, directions, torch.zeros(40), torch.full((40,), 0.5))
        nearest = scene.nearest_hit(starts, directions, 0.5)
        assert nearest == float(first.min()), (nearest, first.min())
        if expected is None:
            assert nearest == math.inf
        else:
            assert nearest <= expected + 0.011


def test_contact_normals_of_a_vertex_set_are_the_mesh_normals(body):
    """The contact term's normals, from the faces around the contact vertices only, are
    the whole mesh's area-weighted vertex normals at those vertices (repeated vertices
    included), each body of a batch its own."""
    from prox_engine.geometry import VertexNormals, vertex_normals

    params = body.init_params(2, "sitting")
    params["global_orient"][1] = torch.tensor([0.3, -1.2, 0.5])
    vertices = body(params).vertices
    ids = torch.cat([body.contact_parts["gluteus"], body.contact_parts["left_hand"],
                     body.contact_parts["gluteus"][:5]])
    normals = vertex_normals(vertices, body.faces)
    faces = body.faces.numpy()
    for b in range(2):  # each body's own area-weighted normals, summed face by face
        corners = vertices[b].numpy()[faces]
        areas = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        summed = np.zeros((len(vertices[b]), 3))
        for k in range(3):
            np.add.at(summed, faces[:, k], areas)
        summed /= np.linalg.norm(summed, axis=1, keepdims=True)
        assert np.allclose(normals[b].numpy(), summed, atol=1e-5)
    expected = normals[:, ids]
    assert torch.allclose(VertexNormals(body.faces, ids)(vertices), expected, atol=1e-5)


def test_contact_pulls_near_vertex_and_ignores_far_one():
    scene = _scene(plane_mesh())
    down = torch.tensor([[[0.0, 0.0, -1.0]]])  # body surface facing the floor
    near = torch.tensor([[[0.3, 0.2, 0.03]]], requires_grad=True)
    contact_energy(near, down, scene, rho=0.05, max_angle_deg=45,
                   max_distance=0.15).sum().backward()
    assert near.grad[0, 0, 2] > 0  # descending the energy moves the point down to the floor
    far = torch.tensor([[[0.3, 0.2, 0.5]]], requires_grad=True)
    energy = contact_energy(far, down, scene, rho=0.05, max_angle_deg=45, max_distance=0.15)
    energy.sum().backward()
    assert energy.item() == 0 and far.grad.abs().max() == 0
    up = torch.tensor([[[0.0, 0.0, 1.0]]])  # facing away: orientation test rejects it
    assert contact_energy(near.detach(), up, scene, 0.05, 45, 0.15).item() == 0


def _tilted_box() -> tuple[trimesh.Trimesh, np.ndarray, Scene]:
    """A tilted box, a tilted, off-centre camera looking at it, and the scene it makes."""
    from prox_engine.synthetic import look_at

    box = trimesh.creation.box(extents=(0.9, 0.6, 0.5))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.5, [0.2, 1.0, 0.4]))
    cam2world = look_at(np.array([0.8, -2.4, 1.4]), np.array([0.1, 0.1, 0.0]))
    return box, cam2world, _seen_scene(box, cam2world, dim=48)


def test_contact_energy_is_the_torch_form_seen_by_a_tilted_camera():
    """Points near a tilted box seen by a tilted, off-centre camera, two bodies of normals
    turned every way, a sink on some points: the kernel's energy and gradient are those of
    the term written in torch (the camera-frame SDF read with autograd, the facing test
    against the world SDF's central differences), and a good share of points qualify."""
    box, cam2world, scene = _tilted_box()
    g = torch.Generator().manual_seed(0)
    world = torch.from_numpy(box.sample(600, seed=1)).float()
    world = world + 0.05 * torch.randn(len(world), 3, generator=g)
    points = _in_camera(world, cam2world).expand(2, -1, -1).contiguous()
    normals = torch.nn.functional.normalize(torch.randn(2, len(world), 3, generator=g), dim=-1)
    sink = torch.where(torch.rand(len(world), generator=g) < 0.3, 0.02, 0.0)
    rho, angle, reach = 0.05, 45.0, 0.15

    def torch_form(x: torch.Tensor) -> torch.Tensor:
        dist = (scene.signed_distance(x) + sink).abs()
        with torch.no_grad():
            outward = scene.sdf.normals(scene.to_world(x))
            facing = -(scene.world_normals(normals) * outward).sum(-1)
            valid = (dist < reach) & (facing > math.cos(math.radians(angle)))
        robust = dist ** 2 / (dist ** 2 + rho ** 2)
        return (robust * valid).sum(1) / valid.sum(1).clamp_min(1)

    ours = points.clone().requires_grad_(True)
    energy = contact_energy(ours, normals, scene, rho, angle, reach, sink)
    theirs = points.clone().requires_grad_(True)
    expected = torch_form(theirs)
    assert torch.allclose(energy, expected, rtol=1e-5)
    (gradient,) = torch.autograd.grad(energy.sum(), ours)
    (expected_gradient,) = torch.autograd.grad(expected.sum(), theirs)
    assert torch.allclose(gradient, expected_gradient, atol=1e-5 * float(
        expected_gradient.abs().max()))
    _, valid, _ = scene.contact_distance(points, normals, reach, math.cos(math.radians(angle)),
                                         sink)
    assert 0.1 < float(valid.float().mean()) < 0.9


def test_nearest_contacts_and_upward_gaps_are_the_minima_over_every_point():
    """The scale search's per-part nearest qualifying contact and per-body nearest gap over
    an upward-facing surface, which read a point's SDF normal only when it could be the
    nearest yet, are the minima of the all-points queries: near a tilted box seen by a
    tilted, off-centre camera, points in uneven parts (an empty one among them), normals
    turned every way."""
    box, cam2world, scene = _tilted_box()
    g = torch.Generator().manual_seed(2)
    world = torch.from_numpy(box.sample(900, seed=3)).float()
    world = world + 0.06 * torch.randn(len(world), 3, generator=g)
    points = _in_camera(world, cam2world).reshape(3, 300, 3)
    normals = torch.nn.functional.normalize(torch.randn(3, 300, 3, generator=g), dim=-1)
    sizes, reach, facing = [40, 0, 7, 153, 100], 0.15, math.cos(math.radians(45))

    nearest = scene.contact_distance.nearest(points, normals, sizes, reach, facing)
    dist, valid, _ = scene.contact_distance(points, normals, reach, facing)
    expected = torch.stack([torch.where(v, d, math.inf).min(1).values if len(d[0]) else
                            torch.full((3,), math.inf) for d, v in zip(
                                dist.split(sizes, 1), valid.split(sizes, 1))], 1)
    assert torch.equal(nearest, expected)
    assert nearest.isfinite().sum() >= 6 and not nearest[:, 1].isfinite().any()

    flat, gaps = world[:600], scene.sdf(world[:600]).abs()
    low = torch.rand(600, generator=g) < 0.3
    upward = scene.sdf.normals(flat)[:, 2] > 0.7
    sizes = [250, 0, 350]
    found = scene.contact_distance.nearest_upward(flat, gaps, low, sizes, 0.7)
    expected = torch.stack([torch.stack([torch.where(u & lo, d, math.inf).min(),
                                         torch.where(u, d, math.inf).min()])
                            if len(d) else torch.full((2,), math.inf) for d, u, lo in zip(
                                gaps.split(sizes), upward.split(sizes), low.split(sizes))])
    assert torch.equal(found, expected)
    assert found.isfinite().sum() == 4


def test_exact_distance_uses_surface_not_vertices():
    """Point-to-surface distance: a point over the middle of a large triangle is close,
    on the side its normal points to positive, below it negative."""
    vertices = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [0.0, 2.0, 0.0]])
    faces = np.array([[0, 1, 2]])
    sdf = compute_sdf(vertices, faces, dim=32, padding=0.5)
    scene = Scene(vertices, faces, np.eye(4), sdf, sample_spacing=0.5)
    d = scene.exact_signed_distance(torch.tensor([[0.1, 0.0, 0.02], [0.1, 0.0, -0.02]]))
    assert torch.allclose(d, torch.tensor([0.02, -0.02]), atol=1e-5)


def _thighs_through_a_tabletop(body) -> tuple[torch.Tensor, Scene, trimesh.Trimesh]:
    """A body whose thighs pass through a 3 cm tabletop in a 6 m room (5 cm voxels): its
    vertices, the scene and the tabletop."""
    room = trimesh.creation.box([6.0, 6.0, 3.0])
    room.vertices += [0.0, 0.0, 1.5]
    room.invert()
    top = trimesh.creation.box([1.2, 0.7, 0.03])
    with torch.no_grad():
        verts = body(body.init_params(1)).vertices[0]
    verts = verts - torch.tensor([0.0, 0.0, float(verts[:, 2].min())])
    thighs = verts[body.contact_parts["thighs"]]
    top.vertices += [0.0, float(thighs[:, 1].mean()), float(thighs[:, 2].mean())]
    scene_mesh = trimesh.util.concatenate([room.subdivide_to_size(0.5), top])
    sdf = compute_sdf(scene_mesh.vertices, scene_mesh.faces, dim=128, padding=0.2)
    scene = Scene(scene_mesh.vertices, scene_mesh.faces, np.eye(4), sdf, sample_spacing=0.02)
    return verts, scene, top


def test_statistics_see_a_thin_tabletop(body):
    """The SDF grid barely sees a 3 cm tabletop through the thighs, the statistics do."""
    from prox_engine import metrics

    verts, scene, top = _thighs_through_a_tabletop(body)
    inside = (torch.tensor(np.abs(top.vertices - top.centroid).max(0)) + 1e-3
              >= (verts - torch.tensor(top.centroid, dtype=torch.float32)).abs()).all(1)
    inside &= body.scene_vertices
    grid = scene.signed_distance(verts[inside])
    exact = scene.exact_signed_distance(verts[inside])
    assert inside.sum() > 20
    assert float((exact < -metrics.PENETRATION_THRESHOLD).float().mean()) > 0.3
    assert float((grid < -metrics.PENETRATION_THRESHOLD).float().mean()) < 0.1
    stats = metrics.penetration_stats(verts, body, scene)
    assert stats["penetrating_share"] * int(body.scene_vertices.sum()) >= 0.3 * int(inside.sum())


def test_frame_statistics_are_those_of_exact_distances(body):
    """A frame's statistics read the SDF grid where it puts a vertex far outside (most of a
    body in a room): the same penetration, depth and touching vertices as exact distances
    everywhere give, the thighs in a tabletop the grid barely sees included."""
    from prox_engine import metrics

    verts, scene, _ = _thighs_through_a_tabletop(body)
    stats, flagged = metrics.scene_stats(verts, body, scene)
    ids = torch.nonzero(body.scene_vertices).flatten()
    exact = scene.exact_signed_distance(verts[ids])
    assert stats == {**metrics._penetration(exact), "contact_parts": stats["contact_parts"]}
    assert stats["penetrating_share"] > 0
    assert flagged["penetrating"] == ids[exact < -metrics.PENETRATION_THRESHOLD].tolist()
    contact = torch.cat(list(body.contact_parts.values())).unique()
    touching = contact[scene.exact_signed_distance(verts[contact]) < metrics.CONTACT_THRESHOLD]
    assert flagged["contact"] == sorted(touching.tolist()) and len(touching)
    far = scene.signed_distance(verts[ids]) > (metrics.CONTACT_THRESHOLD + 2 * 3 ** 0.5
                                               * scene.sdf.voxel_size)
    assert far.float().mean() > 0.3  # the grid's reading was used


def test_frame_statistics_read_exact_distances_where_the_grid_is_coarse():
    """Beside a 1 cm rod on a grid of 20 cm voxels the grid's trilinear reading is several
    times the true distance: points 15 mm away read as exact, touching."""
    from prox_engine import metrics

    rod = trimesh.creation.box([0.01, 0.01, 2.0])
    sdf = compute_sdf(rod.vertices, rod.faces, dim=16, padding=0.5)
    scene = Scene(rod.vertices, rod.faces, np.eye(4), sdf, sample_spacing=0.005)
    beside = torch.tensor([[0.02, 0.0, z] for z in np.linspace(-0.9, 0.9, 19)],
                          dtype=torch.float32)
    assert sdf.voxel_size > 0.15
    assert (scene.signed_distance(beside) > metrics.CONTACT_THRESHOLD).all()
    read = metrics._distances(beside, scene, torch.arange(len(beside)))
    assert torch.equal(read, scene.exact_signed_distance(beside))
    assert (read < metrics.CONTACT_THRESHOLD).all()


def test_exact_sign_holds_in_the_air_above_a_noisy_chair(sitting_data):
    """The demo scene's chair back has a noisy top edge; the plane of a sliver there can
    pass through a point far above it, and the nearest face's sign read the air 30 cm up
    as 30 cm inside. The area-weighted vote of the nearest faces says outside."""
    from prox_engine.dataset import Recording
    from prox_engine.pipeline import load_scene
    from prox_engine.scene_sdf import triangle_signed_distance

    scene = load_scene(Recording(sitting_data, "Synthetic_00000_01"), 128)
    v = scene.vertices
    furniture = (np.abs(v[:, :2]) < 2.5).all(1) & (v[:, 2] > 0.05) & (v[:, 2] < 2.0)
    top = v[furniture, 2].max()
    axes = [np.linspace(-2.5, 2.5, 60)] * 2 + [np.linspace(top + 0.1, top + 0.6, 6)]
    air = torch.from_numpy(np.stack(np.meshgrid(*axes), -1).reshape(-1, 3))
    nearest_face, _ = triangle_signed_distance(air, scene._samples, scene._sample_face,
                                               scene._triangles64, scene._normals64)
    assert (nearest_face < 0).sum() > 0  # the scene has the noisy edge this is about
    camera = (air.float() - scene.cam2world[:3, 3]) @ scene.cam2world[:3, :3]
    assert (scene.exact_signed_distance(camera) > 0).all()


def test_projection_matches_hand_computed_point():
    camera = Camera(fx=1000.0, fy=900.0, cx=960.0, cy=540.0)
    uv = camera.project(torch.tensor([[0.5, -0.25, 2.0]]))
    assert torch.allclose(uv, torch.tensor([[960 + 1000 * 0.25, 540 - 900 * 0.125]]))
    distorted = Camera(1000.0, 1000.0, 0.0, 0.0, k=[0.1])
    x = 0.5 / 2.0
    r2 = x * x
    assert torch.allclose(distorted.project(torch.tensor([[0.5, 0.0, 2.0]])),
                          torch.tensor([[1000 * x * (1 + 0.1 * r2), 0.0]]))


def test_scene_frame_transform():
    """Scene terms read the SDF in world coordinates through cam2world."""
    plane = plane_mesh()
    cam2world = np.eye(4)
    cam2world[:3, 3] = [0.0, 0.0, 1.0]  # camera 1 m above the floor, axes aligned
    sdf = compute_sdf(plane.vertices, plane.faces, dim=64, padding=0.5)
    scene = Scene(plane.vertices, plane.faces, cam2world, sdf, sample_spacing=0.05)
    assert abs(scene.signed_distance(torch.tensor([[0.0, 0.0, -0.8]])).item() - 0.2) < 0.01


def test_scale_search_puts_feet_back_on_the_floor(body):
    """A standing body scaled 1.2x about the camera (same pixels, 20 % too far and too big)
    has its feet through the floor; the search finds the scale that undoes it."""
    from prox_engine.geometry import vertex_normals

    floor = plane_mesh(size=10.0)
    cam2world = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 1.0], [0, 0, 0, 1]])
    scene = _seen_scene(floor, cam2world, dim=96)
    with torch.no_grad():
        world = body(body.init_params(1)).vertices[0]
    world = world + torch.tensor([0.0, 3.0, 0.0]) - torch.tensor([0, 0, world[:, 2].min()])
    camera = _in_camera(world, cam2world)
    far = 1.2 * camera[None]
    parts = [body.contact_parts[p] for p in ("left_foot", "right_foot", "left_hand")]
    scale, cost_far = best_scale(far, vertex_normals(far, body.faces), body.scene_vertices,
                                 _carrying(body), parts, scene, True,
                                 True, rho=0.05, max_angle_deg=45, max_distance=0.15)
    assert abs(float(scale) * 1.2 - 1.0) < 0.03
    # It reads the normals only at normal_vertices (the fitter computes no others)
    from prox_engine.scale_search import normal_vertices
    read = normal_vertices(body.scene_vertices, parts)
    assert len(read) < 0.5 * body.num_vertices
    normals = torch.full_like(far, float("nan"))
    normals[:, read] = vertex_normals(far, body.faces)[:, read]
    again = best_scale(far, normals, body.scene_vertices, _carrying(body), parts, scene, True,
                       True, rho=0.05, max_angle_deg=45, max_distance=0.15)
    assert torch.equal(again[0], scale) and torch.equal(again[1], cost_far)
    # Its cost is that of the body fitted at the right size: the size prior (0.46 at
    # 1 / 1.2) only picks a scale, it does not make one start worse than another.
    _, cost = best_scale(camera[None], vertex_normals(camera[None], body.faces),
                         body.scene_vertices, _carrying(body), parts,
                         scene, True, True, rho=0.05, max_angle_deg=45, max_distance=0.15)
    assert abs(float(cost_far) - float(cost)) < 0.1


def test_scale_search_keeps_a_body_standing_before_a_wall(body):
    """A correctly placed standing body with a wall 20 cm behind it keeps its scale within
    2 %: moving it back would touch the wall with the back but sink the feet."""
    from prox_engine.geometry import vertex_normals

    with torch.no_grad():
        world = body(body.init_params(1)).vertices[0]  # faces -y, back toward +y
    world = world - torch.tensor([0.0, 0.0, float(world[:, 2].min())])
    back = float(world[body.scene_vertices, 1].max())
    floor = plane_mesh(size=10.0)
    wall = trimesh.Trimesh([[-5, back + 0.2, 0], [5, back + 0.2, 0], [5, back + 0.2, 3],
                            [-5, back + 0.2, 3]], [[0, 1, 2], [0, 2, 3]],
                           process=False).subdivide_to_size(0.25)  # normal toward -y
    room = trimesh.util.concatenate([floor, wall])
    # A tilted camera 3 m in front of the person, 1.5 m high, looking at the chest.
    from prox_engine.synthetic import look_at
    cam2world = look_at(np.array([0.8, -3.0, 1.5]), np.array([0.0, 0.0, 1.0]))
    scene = _seen_scene(room, cam2world, dim=128)
    camera = _in_camera(world, cam2world)[None]
    parts = [body.contact_parts[p] for p in body.contact_parts]
    scale, _ = best_scale(camera, vertex_normals(camera, body.faces), body.scene_vertices,
                          _carrying(body), parts, scene, True, True,
                          rho=0.05, max_angle_deg=45, max_distance=0.15)
    assert abs(float(scale) - 1.0) < 0.02


def test_scale_search_counts_only_the_feet_of_a_standing_body(body):
    """A correctly placed standing body with a wall 8 cm behind its back: counting every
    contact part, the search moves it 1-2 % farther, toward the wall (the back and hands
    reach for it); counting only the feet of a standing body (the other parts as
    missing), it stays where it stood without the wall."""
    from prox_engine.geometry import vertex_normals
    from prox_engine.keypoints import BODY
    from prox_engine.scale_search import (STANDING_PARTS, standing_counts,
                                          standing_legs)
    from prox_engine.synthetic import look_at

    with torch.no_grad():
        out = body(body.init_params(1))  # faces -y, back toward +y
    lift = torch.tensor([0.0, 0.0, float(out.vertices[0, :, 2].min())])
    world, joints = out.vertices[0] - lift, out.keypoints[0, BODY] - lift
    back = float(world[body.scene_vertices, 1].max()) + 0.08
    floor = plane_mesh(size=10.0)
    wall = trimesh.Trimesh([[-5, back, 0], [5, back, 0], [5, back, 3], [-5, back, 3]],
                           [[0, 1, 2], [0, 2, 3]], process=False).subdivide_to_size(0.25)
    cam2world = look_at(np.array([0.8, -3.0, 1.5]), np.array([0.0, 0.0, 1.0]))
    names = list(body.contact_parts)
    parts = [body.contact_parts[p] for p in names]
    feet = torch.tensor([p in STANDING_PARTS for p in names])
    scales = {}
    for room, mesh in (("bare", floor), ("wall", trimesh.util.concatenate([floor, wall]))):
        scene = _seen_scene(mesh, cam2world, dim=128)
        camera = _in_camera(world, cam2world)[None]
        standing = standing_legs(_in_camera(joints, cam2world)[None], torch.ones(1, 25),
                                 scene.up_in_camera())
        assert standing.tolist() == [True]
        for counted, who in enumerate(("all", "feet")):
            scales[room, who], _ = best_scale(
                camera, vertex_normals(camera, body.faces), body.scene_vertices,
                _carrying(body), parts, scene, True, True, rho=0.05, max_angle_deg=45,
                max_distance=0.15,
                counted_parts=standing_counts(standing, feet) if counted else None)
    assert abs(float(scales["wall", "feet"] - scales["bare", "feet"])) < 1e-6
    assert abs(float(scales["wall", "feet"]) - 1.0) < 0.01
    assert float(scales["wall", "all"] - scales["wall", "feet"]) > 0.01


def test_standing_legs_hang_plumb_in_any_camera_frame():
    """Standing: every thigh and shin within 30 degrees of world down, read in a camera
    frame whose axes are not the world's (up along its -y turned 40 degrees about x), on
    legs the detector did not report hidden; a seated body's horizontal thighs, a lying
    body's legs and plumb legs with a knee it reports hidden are not standing."""
    from prox_engine.keypoints import HIPS, KNEES, SHINS
    from prox_engine.scale_search import standing_legs

    turn = torch.tensor(trimesh.transformations.rotation_matrix(
        np.radians(40), [1, 0, 0])[:3, :3], dtype=torch.float32)
    up = turn @ torch.tensor([0.0, -1.0, 0.0])
    forward = turn @ torch.tensor([0.0, 0.0, 1.0])

    def legs(thigh: torch.Tensor, shin: torch.Tensor, knee_seen: float = 0.9
             ) -> torch.Tensor:
        keypoints = torch.zeros(1, 25, 3)
        for side, (hip, (knee, foot)) in enumerate(zip(HIPS, SHINS)):
            keypoints[0, hip] = torch.tensor([0.2 * side, 0.0, 3.0])
            keypoints[0, knee] = keypoints[0, hip] + 0.45 * thigh
            keypoints[0, foot[0]] = keypoints[0, knee] + 0.45 * shin
        detected = torch.full((1, 25), 0.9)
        detected[0, KNEES[1]] = knee_seen
        return standing_legs(keypoints, detected, up)

    tilted = (-up + 0.4 * forward) / (-up + 0.4 * forward).norm()  # 22 degrees off plumb
    assert legs(-up, -up).tolist() == [True]
    assert legs(tilted, -up).tolist() == [True]
    assert legs(forward, -up).tolist() == [False]  # seated
    assert legs(forward, forward).tolist() == [False]  # lying
    assert legs(up, up).tolist() == [False]  # upside down
    assert legs(-up, -up, knee_seen=0.2).tolist() == [False]  # a guessed leg


def test_scale_search_keeps_a_seated_body_before_a_sofa_back(body):
    """A correctly placed seated body (buttocks on the seat, feet on the floor) with the
    sofa's back 20 cm behind its own keeps its scale within 2 %: moving it back would
    touch the sofa back but lift it off the seat and sink its feet."""
    from prox_engine.geometry import vertex_normals

    from .test_fitting import tilted_camera

    with torch.no_grad():
        world = body(body.init_params(1, "sitting")).vertices[0]  # faces -y
    world = world - torch.tensor([0.0, 0.0, float(world[:, 2].min())])  # feet on the floor
    gluteus = world[body.contact_parts["gluteus"]]
    thighs = world[body.contact_parts["thighs"]]
    seat_top = float(gluteus[:, 2].min())
    back = float(world[body.scene_vertices, 1].max())
    front = float(thighs[:, 1].min()) + 0.1  # the seat ends under the thighs
    seat = trimesh.creation.box([1.2, back + 0.2 - front, seat_top])
    seat.apply_translation([0.0, (back + 0.2 + front) / 2, seat_top / 2])
    sofa_back = trimesh.creation.box([1.2, 0.2, 0.6])
    sofa_back.apply_translation([0.0, back + 0.3, seat_top + 0.3])
    room = trimesh.util.concatenate([plane_mesh(size=6.0), seat, sofa_back])
    room = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(room.vertices, room.faces, 0.1))
    cam2world = tilted_camera(position=(1.2, -2.8, 1.4), target=(0.0, 0.0, 0.6))
    scene = _seen_scene(room, cam2world, dim=128)
    camera = _in_camera(world, cam2world)[None]
    scale, _ = best_scale(camera, vertex_normals(camera, body.faces), body.scene_vertices,
                          _carrying(body), list(body.contact_parts.values()), scene, True,
                          True, rho=0.05, max_angle_deg=45, max_distance=0.15)
    assert abs(float(scale) - 1.0) < 0.02


def test_scale_search_lets_a_lying_body_sink_into_its_mattress(body):
    """A body lying on its back, sunk 3 cm into a mattress (seen by a tilted, rolled,
    off-centre camera): counted as penetrating from PENETRATION_MARGIN on, the search
    lifts it toward the camera onto the mattress; with a sink of 2 cm for lying bodies
    (FitConfig.lying_sink), it stays where it lies. The trunk reads as lying, a standing
    one's does not."""
    from prox_engine.geometry import vertex_normals
    from prox_engine.keypoints import BODY
    from prox_engine.scale_search import lying

    from .test_fitting import tilted_camera

    on_back = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # y -> -z
    with torch.no_grad():
        out = body(body.init_params(1))  # standing, back toward +y
    standing_joints = out.keypoints[:, BODY]
    world, joints = out.vertices[0] @ on_back.T, out.keypoints[0, BODY] @ on_back.T
    top, sink = 0.5, 0.03
    centre = (world.max(0).values + world.min(0).values) / 2
    shift = torch.tensor([-float(centre[0]), -float(centre[1]),
                          top - sink - float(world[:, 2].min())])
    world, joints = world + shift, joints + shift
    mattress = trimesh.creation.box([1.0, 2.4, top])
    mattress.apply_translation([0.0, 0.0, top / 2])
    room = trimesh.util.concatenate([plane_mesh(size=6.0), mattress])
    room = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(room.vertices, room.faces, 0.1))
    cam2world = tilted_camera(position=(1.4, -2.2, 2.0), target=(0.1, 0.2, 0.5))
    scene = _seen_scene(room, cam2world, dim=128)
    camera = _in_camera(world, cam2world)[None]
    up = scene.up_in_camera()
    assert lying(_in_camera(joints, cam2world)[None], up, 0.4).tolist() == [True]
    assert lying(_in_camera(standing_joints[0], cam2world)[None], up, 0.4).tolist() == [False]

    def search(sinks):
        return float(best_scale(camera, vertex_normals(camera, body.faces),
                                body.scene_vertices, _carrying(body),
                                [body.contact_parts[p] for p in ("back", "gluteus")], scene,
                                True, True, rho=0.05, max_angle_deg=45, max_distance=0.15,
                                sinks=sinks)[0][0])

    assert search(None) < 0.992  # lifted onto the mattress, two steps of the grid near
    assert abs(search(torch.tensor([0.02])) - 1.0) < 0.008  # within a step


def test_scale_search_keeps_a_body_whose_toes_point_into_the_floor(body):
    """A correctly placed standing body whose feet are fitted pointing down (as a
    kneeler's often are), the toes 10 cm into the floor: the scene stages bend a foot
    out, but do not move the body along its rays, so the search keeps the scale within
    2 % instead of shrinking the body toward the camera until the toes leave the floor."""
    from prox_engine.body.anny_body import BODY_BONES
    from prox_engine.geometry import vertex_normals
    from prox_engine.keypoints import ANKLES
    from prox_engine.scale_search import toe_vertices
    from prox_engine.synthetic import look_at

    params = body.init_params(1)
    with torch.no_grad():
        rest = body(params)
        for side in ("L", "R"):
            params["body_pose"][0, BODY_BONES.index(f"foot.{side}"), 0] = 0.7
        pointed = body(params).vertices[0]
    lift = torch.tensor([0.0, 0.0, -float(rest.vertices[0, :, 2].min())])
    assert float((pointed + lift)[:, 2].min()) < -0.08  # the toes are through the floor
    floor = plane_mesh(size=10.0)
    cam2world = look_at(np.array([0.6, -3.0, 1.4]), np.array([0.1, 0.0, 0.8]))
    scene = _seen_scene(floor, cam2world, dim=96)
    camera = _in_camera(pointed + lift, cam2world)[None]
    toes = toe_vertices(body.vertex_parts, rest.vertices[0],
                        rest.keypoints[0, ANKLES]).any(0)
    parts = [body.contact_parts[p] for p in ("left_foot", "right_foot")]
    scale, _ = best_scale(camera, vertex_normals(camera, body.faces), body.scene_vertices,
                          _carrying(body), parts, scene, True, True, rho=0.05,
                          max_angle_deg=45, max_distance=0.15, toes=toes)
    assert abs(float(scale) - 1.0) < 0.02


def test_scale_search_keeps_the_joints_the_detector_saw_in_view(body):
    """A standing body fitted 25 cm behind a wall (seen by a tilted, rolled, off-centre
    camera): the joints the detector saw cannot be behind it, so the search brings the body
    forward until each is at most RAY_MARGIN (its own flesh) behind the wall along its ray
    and the chest is out of the wall; without them, it stays behind the wall."""
    from prox_engine.geometry import vertex_normals
    from prox_engine.scene import RAY_MARGIN

    from .test_fitting import tilted_camera

    cam2world = tilted_camera()  # at (1.7, -2.4, 1.6), looking at (0.2, 0.3, 0.9)
    with torch.no_grad():
        out = body(body.init_params(1))
    lift = torch.tensor([0.2, 0.3, -float(out.vertices[0, :, 2].min())])
    wall = trimesh.creation.box([8.0, 0.1, 4.0])  # front face at y = -0.2
    wall.apply_translation([0.0, -0.15, 1.0])
    wall = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(wall.vertices, wall.faces, 0.3))
    scene = _seen_scene(wall, cam2world, dim=128)
    centre = torch.tensor(cam2world[:3, 3], dtype=torch.float32)
    rotation = torch.tensor(cam2world[:3, :3], dtype=torch.float32)
    vertices = _in_camera(out.vertices[0] + lift, cam2world)[None]
    joints = _in_camera(out.keypoints[0, :25] + lift, cam2world)
    seen = joints[[1, 2, 5, 8, 9, 12]]  # neck, shoulders, hips
    # Where each seen joint's ray meets the wall's front face, as a scale of the joint.
    world_rays = seen @ rotation.T
    limit = ((-0.2 - float(centre[1])) / world_rays[:, 1] + RAY_MARGIN / seen.norm(dim=1))
    assert float(limit.max()) < 0.9  # the body is well behind the wall

    def search(seen_joints):
        return float(best_scale(vertices, vertex_normals(vertices, body.faces),
                                body.scene_vertices, _carrying(body),
                                list(body.contact_parts.values()), scene, True, True,
                                rho=0.05, max_angle_deg=45, max_distance=0.15,
                                seen_joints=seen_joints)[0][0])

    assert search(None) > float(limit.max())
    scale = search([seen])
    # In view, and no nearer than it takes to bring the chest out of the wall too.
    assert float(limit.min()) - 0.06 < scale <= float(limit.min()) + 0.01, (scale, limit)


def test_scale_search_charges_faint_legs_in_view(body):
    """A kneeler on the floor behind a low table, seen by a tilted, rolled, off-centre
    camera, whose knees and ankles the detector reports faintly: the table hides them,
    so they cost nothing where the body is; without the table they are in view at every
    scale and cost FAINT_WEIGHT on top, and the scale does not move."""
    from prox_engine.geometry import vertex_normals
    from prox_engine.keypoints import ANKLES, KNEES
    from prox_engine.scale_search import FAINT_WEIGHT

    from .test_fitting import tilted_camera

    cam2world = tilted_camera()  # at (1.7, -2.4, 1.6), looking at (0.2, 0.3, 0.9)
    with torch.no_grad():
        out = body(body.init_params(1, "kneeling"))
    lift = torch.tensor([0.2, 0.3, -float(out.vertices[0, :, 2].min())])
    camera_xy = torch.tensor(cam2world[:2, 3], dtype=torch.float32)
    toward = (camera_xy - lift[:2]) / (camera_xy - lift[:2]).norm()
    table = trimesh.creation.box([0.6, 0.6, 0.45])  # between the camera and the knees
    table.apply_translation([*(lift[:2] + 0.6 * toward).tolist(), 0.225])
    vertices = _in_camera(out.vertices[0] + lift, cam2world)[None]
    normals = vertex_normals(vertices, body.faces)
    legs = _in_camera(out.keypoints[0, [*KNEES, *ANKLES]] + lift, cam2world)

    def search(room, faint):
        scene = _seen_scene(room, cam2world, dim=128, spacing=0.02)
        scale, cost = best_scale(vertices, normals, body.scene_vertices, _carrying(body),
                                 list(body.contact_parts.values()), scene, True, True,
                                 rho=0.05, max_angle_deg=45, max_distance=0.15,
                                 faint_joints=faint)
        return float(scale[0]), float(cost[0]), scene

    floor = plane_mesh(size=8.0)
    scale, cost, scene = search(trimesh.util.concatenate([floor, table]), None)
    assert abs(scale - 1.0) < 0.03  # kneeling on the floor where it is
    assert float(scene.visible_scale(legs, 1.4).max()) < scale  # the table hides them
    assert search(trimesh.util.concatenate([floor, table]), [legs])[:2] == (scale, cost)
    bare_scale, bare_cost, _ = search(floor, None)
    in_view = search(floor, [legs])
    assert in_view[0] == bare_scale
    assert in_view[1] == pytest.approx(bare_cost + FAINT_WEIGHT, abs=1e-5)


def test_scale_search_does_not_keep_a_body_through_a_board(body):
    """A 12 cm board through a standing body's chest, narrower than the chest and thinner
    than it is deep (as a partition goes through the arm or trunk of a person fitted too
    far before it): no surface vertex is counted inside it, but the body's axis (its
    collision spheres' centres) is. Without the axis the search keeps the body there;
    with it, the search moves the body off the board (in either direction)."""
    from prox_engine.geometry import vertex_normals
    from prox_engine.scale_search import PENETRATION_MARGIN

    from .test_fitting import tilted_camera

    cam2world = tilted_camera()  # at (1.7, -2.4, 1.6), looking at (0.2, 0.3, 0.9)
    with torch.no_grad():
        out = body(body.init_params(1))
    lift = torch.tensor([0.2, 0.3, -float(out.vertices[0, :, 2].min())])
    chest = (out.keypoints[0, 1] + out.keypoints[0, 8]) / 2 + lift  # neck, mid-hip
    trunk = out.spheres[0, :, :3] + lift
    trunk = trunk[((trunk - chest)[:, [0, 2]].abs() < torch.tensor([0.1, 0.15])).all(1)]
    chest[1] = trunk[:, 1].mean()  # the trunk's axis, whose depth the joints may not share
    board = trimesh.creation.box([0.2, 0.12, 0.3])
    board.apply_translation(chest.numpy())
    board = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(board.vertices, board.faces,
                                                              0.05))
    scene = _seen_scene(board, cam2world, dim=96, spacing=0.02)
    vertices = _in_camera(out.vertices[0] + lift, cam2world)[None]
    axes = _in_camera(out.spheres[0, :, :3] + lift, cam2world)[None]
    inside = -scene.signed_distance(vertices[:, body.scene_vertices])
    assert float(inside.max()) < PENETRATION_MARGIN  # none counted as penetrating
    assert float(scene.signed_distance(axes).min()) < -0.05

    def search(axes):
        return float(best_scale(vertices, vertex_normals(vertices, body.faces),
                                body.scene_vertices, _carrying(body), [], scene, False,
                                True, rho=0.05, max_angle_deg=45, max_distance=0.15,
                                use_support=False, axes=axes)[0][0])

    assert abs(search(None) - 1.0) < 0.01
    scale = search(axes)
    assert abs(scale - 1.0) > 0.01
    assert float(scene.signed_distance(scale * axes).min()) >= -PENETRATION_MARGIN


def test_scale_search_rests_a_tall_leaner_on_the_floor(tmp_path, body):
    """A tall person leaning on a table, fitted at the mean adult size (17 % too small, so
    too close and floating): a sole against a table leg or the thighs against the table's
    edge must not hold the body there; the search finds the scale at which the feet rest
    on the floor and the hands on the table."""
    import json

    from benchmarks.generate import make_benchmark
    from prox_engine.dataset import Recording, load_cam2world, load_scene_mesh
    from prox_engine.geometry import vertex_normals

    rec = make_benchmark(tmp_path, seed=0, frames=1, kinds=["table"], body=body)[0]
    recording = Recording(tmp_path, rec)
    vertices, faces = load_scene_mesh(recording.scene_path)
    # As the fitter sees it: the scan at its written (1-3 cm misregistered) pose.
    scene = Scene(vertices, faces, load_cam2world(recording.cam2world_path),
                  compute_sdf(vertices, faces, dim=128, padding=0.5))
    meta = json.loads((tmp_path / "ground_truth" / rec / "meta.json").read_text())
    truth = np.load(tmp_path / "ground_truth" / rec / f"{meta['frames'][0]}.npz")["vertices"]
    too_close = torch.tensor(truth, dtype=torch.float32)[None] / 1.17
    scale, _ = best_scale(too_close, vertex_normals(too_close, body.faces),
                          body.scene_vertices, _carrying(body),
                          list(body.contact_parts.values()), scene, True, True, rho=0.05,
                          max_angle_deg=45, max_distance=0.15)
    assert abs(float(scale) / 1.17 - 1.0) < 0.03


def test_scale_search_does_not_stand_a_body_on_its_hands(body):
    """A standing body fitted 15 % too small (too close, floating) whose fingertips happen
    to rest on two small shelves at that size: hands cannot carry a body, so the search
    still scales it up until its feet rest on the floor."""
    from prox_engine.geometry import vertex_normals
    from prox_engine.synthetic import look_at

    with torch.no_grad():
        world = body(body.init_params(1)).vertices[0]
    world = world - torch.tensor([0.0, 0.0, float(world[:, 2].min())])  # on the floor
    cam2world = look_at(np.array([0.7, -3.0, 1.6]), np.array([0.0, 0.0, 0.9]))
    centre = torch.tensor(cam2world[:3, 3], dtype=torch.float32)
    near = centre + (world - centre) / 1.15  # the same pixels, 15 % too small
    shelves = []
    for side in ("left_hand", "right_hand"):
        hand = near[body.contact_parts[side]]
        tip = hand[hand[:, 2].argmin()].numpy()
        shelf = trimesh.creation.box([0.2, 0.2, 0.03])
        shelf.apply_translation([tip[0], tip[1], tip[2] - 0.015 - 0.003])
        shelves.append(shelf)
    room = trimesh.util.concatenate([plane_mesh(size=10.0), *shelves])
    scene = _seen_scene(room, cam2world, dim=128, spacing=0.02)
    camera = _in_camera(near, cam2world)[None]
    parts = [body.contact_parts[p] for p in ("left_foot", "right_foot", "left_hand",
                                             "right_hand")]
    scale, _ = best_scale(camera, vertex_normals(camera, body.faces), body.scene_vertices,
                          _carrying(body), parts, scene, True, True,
                          rho=0.05, max_angle_deg=45, max_distance=0.15)
    assert abs(float(scale) / 1.15 - 1.0) < 0.03


def test_scale_search_rests_a_body_on_its_feet_not_on_a_shelf(body):
    """A standing body fitted a fifth too small (too close, floating 38 cm over the floor)
    whose buttocks happen to rest on a thin shelf at that size, seen from its side by a
    tilted, rolled camera, its knees hidden. Buttocks can carry a body, and the size prior
    favours the fitted size: under ``prox-no-feet-carry`` the search keeps it on the shelf.
    Under ``prox``, a body on its feet with a foot clearly seen rests on its lowest
    vertices alone, and the search scales it until its feet reach the floor; with the
    feet not clearly seen it is kept on the shelf as before."""
    from prox_engine.config import load_config
    from prox_engine.fitting import Fitter
    from prox_engine.geometry import axis_angle_to_matrix, matrix_to_axis_angle, vertex_normals
    from prox_engine.keypoints import ANKLES, KNEES, SEEN, TOES
    from prox_engine.scale_search import feet_carried
    from prox_engine.synthetic import body_params, sitting_pose

    from .test_fitting import tilted_camera

    standing = body.init_params(1)
    with torch.no_grad():
        world = body(standing).vertices[0]
    standing["transl"] = standing["transl"] - torch.tensor([0.0, 0.0, float(world[:, 2].min())])
    world = world - torch.tensor([0.0, 0.0, float(world[:, 2].min())])  # soles at z = 0
    cam2world = tilted_camera(position=(2.6, -0.9, 1.5), target=(0.0, 0.0, 0.8))
    eye = torch.tensor(cam2world[:3, 3], dtype=torch.float32)
    floor_z = float(eye[2] + 1.25 * (0.0 - eye[2]))  # the soles' height at 1.25 times
    normals = vertex_normals(world[None], body.faces)[0]
    seat = torch.isin(torch.arange(body.num_vertices), body.contact_parts["gluteus"])
    seat &= normals[:, 2] < -0.5
    assert int(seat.sum()) > 10
    under = world[seat][world[seat][:, 2].argmin()].numpy()
    shelf = trimesh.creation.box([0.25, 0.25, 0.03])
    shelf.apply_translation([under[0], under[1], under[2] - 0.015 - 0.003])
    room = trimesh.util.concatenate([plane_mesh(size=10.0, z=floor_z), shelf])
    scene = _seen_scene(room, cam2world, dim=128, spacing=0.02)
    world2cam = np.linalg.inv(cam2world)
    rotation = torch.tensor(world2cam[:3, :3], dtype=torch.float32)
    params = {**standing, "global_orient": matrix_to_axis_angle(
        rotation @ axis_angle_to_matrix(standing["global_orient"])),
        "transl": standing["transl"] @ rotation.T
        + torch.tensor(world2cam[:3, 3], dtype=torch.float32)}
    camera = Camera(fx=1000.0, fy=1000.0, cx=960.0, cy=540.0, width=1920, height=1080)
    seen = torch.full((1, 25), 0.9)
    seen[:, KNEES] = 0.1  # hidden, as by a table: the search counts every contact part
    unseen_feet = seen.clone()
    unseen_feet[:, [*ANKLES, *TOES]] = SEEN / 2

    def scale(config: str, detected: torch.Tensor) -> float:
        fitter = Fitter(body, camera, load_config(config), scene)
        return float(fitter._scale_search(params, detected)[0][0])

    assert abs(scale("prox-no-feet-carry", seen) - 1.0) < 0.03
    assert abs(scale("prox", seen) / 1.25 - 1.0) < 0.03
    assert abs(scale("prox", unseen_feet) - 1.0) < 0.03
    sitting = body_params(body, sitting_pose(), 0.0, {})  # thighs level: not on its feet
    with torch.no_grad():
        joints = body(sitting, vertices=False).keypoints[:, :25]
    assert not bool(feet_carried(joints, torch.full((1, 25), 0.9), torch.tensor([0., 0., 1.])))


def test_start_choice_asks_which_start_can_sit_on_the_chair(tmp_path, body):
    """Two starts of one frame in front of a chair: the person sitting on it, and the same
    trunk with its legs hanging straight (through the seat and the floor at the fitted size,
    floating above the seat when shrunk onto the floor). The hanging start explains the
    keypoints a little better (its objective is lower); the scene decides for the sitting
    one, unless ``start_scene_weight`` is 0. The camera is tilted, turned and off-centre."""
    from prox_engine.body.anny_body import BODY_BONES
    from prox_engine.config import load_config
    from prox_engine.fitting import Fitter
    from prox_engine.geometry import axis_angle_to_matrix, matrix_to_axis_angle
    from prox_engine.synthetic import body_params, chair, look_at, sitting_pose

    sitting = body_params(body, sitting_pose(), 0.0, {})
    with torch.no_grad():
        world = body(sitting).vertices[0].numpy()
    main = body.scene_vertices.numpy()
    seat = chair(world[main], np.asarray(body.vertex_parts)[main])
    floor = plane_mesh(size=3.0, z=float(world[:, 2].min()))
    room = trimesh.util.concatenate([floor, seat])
    centre = world[main].mean(0)
    cam2world = look_at(centre + np.array([0.9, -2.6, 0.8]), centre)
    scene = Scene(room.vertices, room.faces, cam2world,
                  compute_sdf(room.vertices, room.faces, dim=128, padding=0.5))
    hanging = {k: v.clone() for k, v in sitting.items()}
    for bone in ("upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R"):
        hanging["body_pose"][0, BODY_BONES.index(bone)] = 0.0
    # Into the camera frame (the root pivot is anny's origin).
    rotation = torch.tensor(np.linalg.inv(cam2world)[:3, :3], dtype=torch.float32)
    offset = torch.tensor(np.linalg.inv(cam2world)[:3, 3], dtype=torch.float32)
    starts = {}
    for key in sitting:
        starts[key] = torch.cat([hanging[key], sitting[key]])
    starts["global_orient"] = matrix_to_axis_angle(
        rotation @ axis_angle_to_matrix(starts["global_orient"]))
    starts["transl"] = starts["transl"] @ rotation.T + offset
    terms = {"data": torch.tensor([100.0, 200.0])}  # the hanging legs fit the pixels better

    camera = Camera(fx=1000.0, fy=1000.0, cx=960.0, cy=540.0)
    config = load_config("prox")
    seen = torch.ones(2, 25, dtype=torch.bool)  # every joint seen clearly

    def choice() -> list[int]:
        return Fitter(body, camera, config, scene)._best_rows(starts, seen, terms, [2],
                                                               by_scene=True)

    assert choice() == [1]
    config.start_scene_weight = 0.0
    assert choice() == [0]


def test_grid_subsample_keeps_the_first_point_of_each_cell():
    from prox_engine.geometry import grid_subsample

    points = torch.tensor([[0.031, 0.0, 0.0], [0.001, 0.002, 0.0], [0.009, 0.004, 0.001],
                           [0.0, 0.0, -0.001], [0.035, 0.001, 0.0], [0.012, 0.0, 0.0]])
    # cells of 1 cm: (3,0,0), (0,0,0), (0,0,0), (0,0,-1), (3,0,0), (1,0,0)
    kept, counts = grid_subsample(points, 0.01)
    assert kept.tolist() == [0, 1, 3, 5] and counts.tolist() == [2, 2, 1, 1]
    kept, counts = grid_subsample(points, 0.1)
    assert kept.tolist() == [0, 3] and counts.tolist() == [5, 1]


def test_penetration_reads_one_scene_vertex_per_centimetre(body):
    """The penetration term's vertices: at 0 every scene vertex once; at 1 cm one per
    cell over the standing body, counted for the cell's vertices, so that every scene
    vertex has a kept one within a cell's diagonal, the sparse thighs are kept whole and
    the dense hands and face thinned; and the counted subset's energy is the whole
    body's within 6 % for a body standing 2, 5 or 30 cm deep in a floor (scaled by one
    factor for all instead, the thinned feet would weigh up to a third less)."""
    from prox_engine.losses import penetration_vertices

    every, once = penetration_vertices(body, 0.0)
    assert torch.equal(every, torch.nonzero(body.scene_vertices).flatten())
    assert torch.equal(once, torch.ones(len(every)))
    kept, counts = penetration_vertices(body, 0.01)
    assert set(kept.tolist()) <= set(every.tolist()) and len(kept) < 0.55 * len(every)
    assert int(counts.sum()) == len(every)
    with torch.no_grad():
        rest = body(body.init_params(1)).vertices
    gap = torch.cdist(rest[0, every], rest[0, kept]).min(1).values
    assert float(gap.max()) <= 0.01 * math.sqrt(3) + 1e-6
    parts = np.array(body.vertex_parts)

    def share(part: str) -> float:
        return float(np.isin(kept.numpy(), np.flatnonzero(parts == part)).sum()
                     / np.isin(every.numpy(), np.flatnonzero(parts == part)).sum())

    assert share("left_thigh") > 0.95 and share("right_thigh") > 0.95
    assert share("left_hand") < 0.5 and share("head") < 0.5
    for depth in (0.02, 0.05, 0.3):
        scene = _scene(plane_mesh(z=float(rest[0, :, 2].min()) + depth))
        whole = penetration_energy(rest[:, every], scene)
        assert abs(float(penetration_energy(rest[:, kept], scene, weights=counts) / whole)
                   - 1) < 0.06, depth


def test_scale_search_skips_only_scales_that_cannot_win():
    """The search skips scales whose size prior and hidden joints alone exceed the best
    total found: on jagged costs (a one-scale valley, as contact parts switching on make)
    it picks what the whole grid picks, and evaluates fewer scales the better the best;
    under a ceiling on the total, the same where the least total is under it, and no
    total under it where it is not. Fifty bodies searched together are searched as each
    alone, every round of the search in one call. A scale's cost may be left unfinished
    (inf) where it is over the limit the search passes: the same pick."""
    from prox_engine.scale_search import CHUNK, FIRST_CHUNK, SCALES, bounded_search

    count, bodies = len(SCALES), 50
    prior = 0.1 * (torch.log(SCALES) / 0.06) ** 2 / 2
    generator = torch.Generator().manual_seed(0)
    costs = torch.rand(bodies, count, generator=generator)
    for trial in range(bodies):
        costs[trial, int(torch.randint(count, (1,), generator=generator))] = 0.01 * trial
    hidden = (torch.arange(count) > 70 + torch.arange(bodies)[:, None] % 20).float()
    whole = costs + hidden + prior
    least = whole.min(1).values
    evaluated: list[list[int]] = [[] for _ in range(bodies)]
    calls, over = [], []  # scales a call was asked for; scales over their limits

    def search(ceilings: torch.Tensor, first: int = 0) -> list:
        """The bodies from ``first`` on, one per ceiling, searched together."""
        def cost_at(which: torch.Tensor, picked: torch.Tensor, limits: torch.Tensor
                    ) -> torch.Tensor:
            if not calls:  # nothing evaluated yet: no limit
                assert limits.isinf().all()
            calls.append(len(picked))
            for b, i in zip(which.tolist(), picked.tolist()):
                evaluated[first + b].append(i)
            cost = costs[first + which, picked]
            over.append(int((cost > limits).sum()))
            return torch.where(cost > limits, math.inf, cost)  # as cost_at may

        evaluated[:] = [[] for _ in range(bodies)]
        calls.clear()
        return bounded_search(cost_at, hidden[first:first + len(ceilings)], prior, ceilings)

    found = search(torch.full((bodies,), math.inf))
    assert len(calls) <= 1 + math.ceil((count - FIRST_CHUNK) / CHUNK)
    everywhere = [len(e) for e in evaluated]
    assert sum(over) > bodies  # later rounds' limits leave scales unfinished
    for b, (picked, cost) in enumerate(found):
        assert picked.tolist() == sorted(set(evaluated[b]))
        exact = costs[b, picked] + hidden[b, picked]
        assert torch.equal(cost[cost.isfinite()], exact[cost.isfinite()])
        assert (exact[cost.isinf()] + prior[picked][cost.isinf()] > least[b]).all()
        assert int(picked[(cost + prior[picked]).argmin()]) == int(whole[b].argmin())
    alone = search(torch.full((1,), math.inf), 7)[0]
    assert torch.equal(alone[0], found[7][0]) and torch.equal(alone[1], found[7][1])
    # under a ceiling above the least total: the same pick from fewer scales; below it:
    # no total under the ceiling (the caller's other candidate wins), and no scale at all
    # where every bound is over it
    for b, (picked, cost) in enumerate(search(least + 0.05)):
        assert int(picked[(cost + prior[picked]).argmin()]) == int(whole[b].argmin())
        assert len(evaluated[b]) <= everywhere[b]
    for b, (picked, cost) in enumerate(search(least - 1e-3)):
        assert len(picked) == 0 or float((cost + prior[picked]).min()) > least[b] - 1e-3
    below = (hidden + prior).min(1).values - 1e-3
    assert all(len(picked) == 0 for picked, _ in search(below))
    # a size prior per body: where the scene tells no scale apart, each body's pick is
    # the scale that takes its size to the prior's centre
    from prox_engine.scale_search import size_prior
    sizes = torch.tensor([1.0, 1.1, 0.9])
    found = bounded_search(lambda b, i, _: torch.ones(len(i)), torch.zeros(3, count),
                           size_prior(SCALES, 0.1, sizes[:, None]), torch.full((3,), math.inf))
    for (picked, cost), size in zip(found, sizes):
        scale = float(SCALES[picked[(cost + size_prior(SCALES[picked], 0.1, size)).argmin()]])
        assert abs(scale * float(size) - 1) < 0.004, (scale, size)
    flat = torch.ones(1, count)
    flat[0, 48] = 0.0  # a body that meets the scene at its fitted size
    (picked, _), = bounded_search(lambda b, i, _: flat[b, i], torch.zeros(1, count), prior,
                                  torch.full((1,), math.inf))
    assert 48 in picked.tolist() and len(picked) < count / 2
