"""GLB files for the report's 3D viewer: the scan, simplified to a size a browser loads
quickly, and each fitted body, both in the scene's world frame (z up, metres, as the scan:
not glTF's y up, so that the files line up with the scan and the PLY meshes)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from .output import atomic_write_bytes

MAX_SCENE_FACES = 100_000
SCENE_CELL = 0.01  # first vertex-clustering cell (m); doubled until the scan is small enough


def simplify(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None,
             max_faces: int = MAX_SCENE_FACES) -> tuple[np.ndarray, np.ndarray,
                                                        np.ndarray | None]:
    """Vertex clustering: vertices merged per cubic cell (position and colour averaged),
    faces that collapse or repeat dropped, the cell doubled from 1 cm until at most
    ``max_faces`` remain. Returns vertices, faces and colours (or None)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    cell = SCENE_CELL
    while len(faces) > max_faces:
        keys = np.floor(vertices / cell).astype(np.int64)
        _, cluster, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        cluster = cluster.ravel()
        merged = np.zeros((len(counts), 3))
        np.add.at(merged, cluster, vertices)
        merged /= counts[:, None]
        if colours is not None:
            paint = np.zeros((len(counts), colours.shape[1]))
            np.add.at(paint, cluster, colours)
            colours = paint / counts[:, None]
        mapped = cluster[faces]
        keep = ((mapped[:, 0] != mapped[:, 1]) & (mapped[:, 1] != mapped[:, 2])
                & (mapped[:, 0] != mapped[:, 2]))
        mapped = mapped[keep]
        _, first = np.unique(np.sort(mapped, axis=1), axis=0, return_index=True)
        vertices, faces = merged, mapped[np.sort(first)]
        cell *= 2
    used, faces = np.unique(faces, return_inverse=True)
    return (vertices[used], faces.reshape(-1, 3),
            None if colours is None else colours[used])


def mesh_glb(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None) -> bytes:
    """A binary glTF of one mesh with per-vertex colours (RGB or RGBA in [0, 1])."""
    rgba = None
    if colours is not None:
        colours = np.asarray(colours, dtype=np.float64)
        if colours.shape[1] == 3:
            colours = np.column_stack([colours, np.ones(len(colours))])
        rgba = np.round(np.clip(colours, 0, 1) * 255).astype(np.uint8)
    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float32), faces, vertex_colors=rgba,
                           process=False)
    return mesh.export(file_type="glb")


def write_glb(path: Path, vertices: np.ndarray, faces: np.ndarray,
              colours: np.ndarray | None) -> None:
    atomic_write_bytes(Path(path), mesh_glb(vertices, faces, colours))
