"""Depth input (SMPLify-D / PROX-D): back-projection of body-mask pixels and the depth term."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from prox_engine.camera import Camera
from prox_engine.depth import load_depth_points
from prox_engine.errors import InputError
from prox_engine.geometry import vertex_normals
from prox_engine.losses import depth_data


def _frames(tmp_path, width=64, height=36):
    depth = np.full((height, width), 2000 * 8, dtype=np.uint16)  # 2 m everywhere
    mask = np.full((height, width), 255, dtype=np.uint8)
    mask[10:20, 5:15] = 0  # body 0 on the left half of the image
    Image.fromarray(depth).save(tmp_path / "d.png")
    Image.fromarray(mask).save(tmp_path / "m.png")
    return tmp_path / "d.png", tmp_path / "m.png"


def test_depth_points_are_back_projected_mask_pixels(tmp_path):
    camera = Camera(fx=64.0, fy=64.0, cx=32.0, cy=18.0, width=64, height=36)
    points = load_depth_points(*_frames(tmp_path), camera, flip=False, max_points=1000)
    assert points.shape == (100, 3)
    assert torch.allclose(points[:, 2], torch.full((100,), 2.0))
    assert torch.all(points[:, 0] < 0)  # left of the optical centre
    flipped = load_depth_points(*_frames(tmp_path), camera, flip=True, max_points=1000)
    assert torch.all(flipped[:, 0] > 0)
    few = load_depth_points(*_frames(tmp_path), camera, flip=False, max_points=10)
    assert few.shape == (10, 3)


def test_depth_mask_size_mismatch(tmp_path):
    depth, _ = _frames(tmp_path)
    Image.fromarray(np.zeros((5, 5), dtype=np.uint8)).save(tmp_path / "small.png")
    with pytest.raises(InputError, match="does not match"):
        load_depth_points(depth, tmp_path / "small.png", Camera(1, 1, 0, 0), False, 10)


def test_depth_term_is_zero_on_the_surface_and_grows_off_it(body):
    params = body.init_params(1)
    params["transl"][0, 2] = 3.0
    params["global_orient"][0] = torch.tensor([torch.pi / 2, 0.0, 0.0])  # upright, facing us
    out = body(params)
    visible = ((vertex_normals(out.vertices, body.faces)[0] * out.vertices[0]).sum(-1) < 0)
    cloud = out.vertices[0, visible & body.scene_vertices][::50]
    on = depth_data(out, body, [cloud], rho=0.05)
    off = depth_data(out, body, [cloud + torch.tensor([0.0, 0.0, 0.05])], rho=0.05)
    assert on.item() < 1e-6 and off.item() > 100 * on.item()
