"""Writing results in the PROX layout, atomically (temporary file + rename).

``OUT/<rec>/results/<frame>/000.json`` (and ``000.pkl`` as PROX writes it, for SMPL-X),
``OUT/<rec>/meshes/<frame>/000.ply`` (camera frame), ``OUT/<rec>/summary.json``.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


UMASK = _umask()


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all (a temporary file beside it, then renamed), with
    the permissions a plain ``open()`` would give it (not mkstemp's owner-only 0600, which
    hid reports from the web server that publishes them)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.chmod(tmp, 0o666 & ~UMASK)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json(path: Path, content: object) -> None:
    atomic_write_text(path, json.dumps(content, indent=1))


def write_pickle(path: Path, content: object) -> None:
    """A pickle, as PROX and SMPLify-X write their ``000.pkl`` results."""
    import pickle

    atomic_write_bytes(path, pickle.dumps(content, protocol=2))


def ply_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A binary little-endian PLY of a triangle mesh."""
    vertices = np.ascontiguousarray(vertices, dtype="<f4")
    faces = np.asarray(faces, dtype="<i4")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
              "end_header\n").encode()
    face_records = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face_records["n"] = 3
    face_records["idx"] = faces
    return header + vertices.tobytes() + face_records.tobytes()


def frame_paths(out: Path, recording: str, frame: str) -> tuple[Path, Path]:
    """(results JSON, mesh PLY) of one frame."""
    base = Path(out) / recording
    return (base / "results" / frame / "000.json", base / "meshes" / frame / "000.ply")
