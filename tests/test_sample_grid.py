"""The grid of surface samples answers as scipy's k-d tree does."""
from __future__ import annotations

import numpy as np
import pytest

from prox_engine import sample_grid
from prox_engine.sample_grid import SampleGrid
from prox_engine.scene_sdf import surface_samples, surface_tree


def _room() -> np.ndarray:
    """Samples 2 cm apart on a noisy box room with a thin tilted table top inside."""
    import trimesh

    room = trimesh.creation.box(extents=(4.0, 3.0, 2.6))
    room.apply_translation((0.3, -0.2, 1.3))
    table = trimesh.creation.box(extents=(1.2, 0.8, 0.03))
    table.apply_transform(trimesh.transformations.rotation_matrix(0.2, (1, 1, 0)))
    table.apply_translation((0.5, 0.4, 0.75))
    mesh = trimesh.util.concatenate([room.subdivide().subdivide(), table.subdivide()])
    vertices = mesh.vertices + np.random.default_rng(0).normal(0, 0.002, mesh.vertices.shape)
    return surface_samples(vertices, mesh.faces, 0.02)[0]


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, SampleGrid]:
    samples = _room()
    return samples, SampleGrid.build(samples, surface_tree(samples))


@pytest.mark.parametrize("k", [1, 4, 6, 8])
def test_nearest_samples_are_the_trees(room, k):
    """Points near the walls, floor and table (what the penetration term asks about), in
    the open room, and outside the room and its grid: the same samples, nearest first."""
    samples, grid = room
    rng = np.random.default_rng(k)
    near = samples[rng.integers(0, len(samples), 3000)] + rng.normal(0, 0.03, (3000, 3))
    anywhere = rng.uniform((-2.5, -2.5, -0.5), (3.0, 2.5, 3.5), (2000, 3))
    far = rng.uniform(-50, 50, (200, 3))
    points = np.concatenate([near, anywhere, far])
    distance, index = grid.query(points, k)
    expected_distance, expected_index = grid.tree.query(points, k=k)
    assert np.array_equal(index, np.reshape(expected_index, (-1, k)))
    assert np.allclose(distance, np.reshape(expected_distance, (-1, k)), rtol=1e-12)


def test_a_large_room_gets_larger_cells(room, monkeypatch):
    """With a cap on the number of cells, the cells grow and the answers stay the tree's."""
    samples, _ = room
    monkeypatch.setattr(sample_grid, "MAX_CELLS", 2000)
    grid = SampleGrid.build(samples, surface_tree(samples))
    assert grid.cell > sample_grid.CELL and int(np.prod(grid.dims)) <= 2 * 2000
    points = samples[::50] + 0.01
    assert np.array_equal(grid.query(points, 4)[1], grid.tree.query(points, k=4)[1])


def test_more_neighbours_than_the_kernel_holds_are_refused(room):
    _, grid = room
    with pytest.raises(ValueError, match="1 to 8"):
        grid.query(np.zeros((1, 3)), sample_grid.MAX_K + 1)


def test_a_scenes_samples_and_grid_come_back_from_the_cache_as_made(tmp_path):
    """The cache gives the grid that making it gives (same answers, its k-d tree's too),
    one file per mesh and spacing; a damaged entry is made again."""
    import trimesh

    from prox_engine.scene_sdf import cached_surface

    room = trimesh.creation.box(extents=(4.0, 3.0, 2.6)).subdivide()
    vertices, faces = np.asarray(room.vertices), np.asarray(room.faces)
    made_face, made = cached_surface(vertices, faces, 0.05, None)
    assert not list(tmp_path.iterdir())
    cached_surface(vertices, faces, 0.05, tmp_path)
    (entry,) = tmp_path.iterdir()
    face, grid = cached_surface(vertices, faces, 0.05, tmp_path)
    assert np.array_equal(face, made_face) and np.array_equal(grid.order, made.order)
    points = np.random.default_rng(3).uniform(-2.5, 2.5, (500, 3))
    for answer, expected in zip(grid.query(points, 4), made.query(points, 4)):
        assert np.array_equal(answer, expected)
    assert grid.tree.n == made.tree.n == len(made_face)
    for answer, expected in zip(grid.tree.query(points, 6), made.tree.query(points, 6)):
        assert np.array_equal(answer, expected)  # the tree restored, not rebuilt, answers alike
    entry.write_bytes(b"not a zip")
    face, grid = cached_surface(vertices, faces, 0.05, tmp_path)
    assert np.array_equal(face, made_face) and entry.stat().st_size > 1000
    assert len(list(tmp_path.iterdir())) == 1
