"""GLB files for the report's 3D viewer: the scan, simplified to a size a browser loads
quickly, and each fitted body, both in the scene's world frame (z up, metres, as the scan:
not glTF's y up, so that the files line up with the scan and the PLY meshes)."""
from __future__ import annotations

import json
import struct

import numpy as np

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
    """A binary glTF 2.0 of one triangle mesh: float32 positions, per-vertex RGBA colours
    (from RGB or RGBA in [0, 1]) as normalised bytes, and 16-bit indices where they fit
    (a body's 13718 vertices do: a third smaller than trimesh's 32-bit export)."""
    positions = np.ascontiguousarray(vertices, dtype="<f4")
    index_type = "<u2" if len(positions) < 2 ** 16 else "<u4"
    chunks = [(np.ascontiguousarray(faces, dtype=index_type).ravel(), 34963),
              (positions, 34962)]
    accessors = [{"componentType": 5123 if index_type == "<u2" else 5125,
                  "type": "SCALAR", "count": int(np.size(faces))},
                 {"componentType": 5126, "type": "VEC3", "count": len(positions),
                  "min": positions.min(0).tolist(), "max": positions.max(0).tolist()}]
    attributes = {"POSITION": 1}
    if colours is not None:
        colours = np.asarray(colours, dtype=np.float64)
        if colours.shape[1] == 3:
            colours = np.column_stack([colours, np.ones(len(colours))])
        chunks.append((np.round(np.clip(colours, 0, 1) * 255).astype(np.uint8), 34962))
        accessors.append({"componentType": 5121, "normalized": True, "type": "VEC4",
                          "count": len(colours)})
        attributes["COLOR_0"] = 2
    blob, views = b"", []
    for (array, target), accessor in zip(chunks, accessors):
        data = array.tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data),
                      "target": target})
        accessor["bufferView"] = len(views) - 1
        blob += data + b"\0" * (-len(data) % 4)  # views start on 4-byte boundaries
    document = json.dumps({
        "asset": {"version": "2.0", "generator": "prox"}, "scene": 0,
        "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": 0, "mode": 4}]}],
        "accessors": accessors, "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}]}, separators=(",", ":")).encode()
    document += b" " * (-len(document) % 4)
    return b"".join([struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(document) + 8 + len(blob)),
                     struct.pack("<I4s", len(document), b"JSON"), document,
                     struct.pack("<I4s", len(blob), b"BIN\0"), blob])
