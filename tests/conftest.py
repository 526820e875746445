"""Shared fixtures: the real anny body (baked by `make setup`) and a small synthetic scene."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def body():
    from prox_engine.body.anny_body import AnnyBody

    return AnnyBody.load()


@pytest.fixture(scope="session")
def sitting_data(tmp_path_factory, body) -> Path:
    """The synthetic sitting scene in the PROX layout (coarse, for speed)."""
    from prox_engine.synthetic import make_sitting_dataset

    return make_sitting_dataset(tmp_path_factory.mktemp("sitting"), frames=2, body=body,
                                face_size=0.12)


def plane_mesh(size: float = 4.0, z: float = 0.0) -> trimesh.Trimesh:
    """An open, single-sided horizontal square (normal +z), like a scanned floor."""
    h = size / 2
    vertices = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return trimesh.Trimesh(vertices, faces, process=False).subdivide_to_size(0.25)


def closed_box(extents=(1.0, 1.0, 1.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents).subdivide_to_size(0.2)
