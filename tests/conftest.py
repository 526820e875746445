"""Shared fixtures: the real anny body (baked by `make setup`) and a small synthetic scene."""
from __future__ import annotations

import shutil
import subprocess
import sys
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


REC = "Synthetic_00000_01"


def coarse_config(tmp_path: Path, name: str, settings: str = "") -> Path:
    """The named configuration on a coarser SDF grid, to keep the tests quick, with
    ``settings`` (YAML lines) added."""
    from prox_engine.config import CONFIG_DIR

    path = tmp_path / f"{name}.yaml"
    path.write_text((CONFIG_DIR / f"{name}.yaml").read_text() + "sdf_dim: 128\n" + settings)
    return path


def cli_fit(base: Path, out: Path, config: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "prox_engine.cli", "fit", str(base), "--out",
                           str(out), "--config", str(config), *extra],
                          capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="session")
def cli_fits(sitting_data, tmp_path_factory) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    """``prox fit`` (with its reports) of the first two sitting frames with rgb and prox, on
    a copy of the data that has a colour image for the first frame only."""
    tmp = tmp_path_factory.mktemp("fits")
    base = tmp / "data"
    shutil.copytree(sitting_data, base, ignore=shutil.ignore_patterns("ground_truth"))
    photos = sorted((base / "recordings" / REC / "Color").iterdir())
    for photo in photos[1:]:  # the first frame is seen over its photograph, the rest not
        photo.unlink()
    runs = {}
    for name in ("rgb", "prox"):
        run = cli_fit(base, tmp / name, coarse_config(tmp, name), "--frames", "2")
        assert run.returncode == 0, run.stderr
        runs[name] = (tmp / name, run)
    return runs


def plane_mesh(size: float = 4.0, z: float = 0.0) -> trimesh.Trimesh:
    """An open, single-sided horizontal square (normal +z), like a scanned floor."""
    h = size / 2
    vertices = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return trimesh.Trimesh(vertices, faces, process=False).subdivide_to_size(0.25)


def closed_box(extents=(1.0, 1.0, 1.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents).subdivide_to_size(0.2)


@pytest.fixture
def unused_port() -> int:
    """A local TCP port nothing listens on (just released by the OS)."""
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]
