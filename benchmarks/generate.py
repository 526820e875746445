"""Reproducible benchmark data: one recording per interaction kind (sitting on a chair,
reclining on a sofa, lying on a bed on the back or a side, leaning on a table, reaching
from a stool, walking, standing before a wall), each in its own scan-like room, in the
PROX layout, with ground truth beside it.

    python -m benchmarks.generate --out DIR --seed 0 --frames 4

Everything follows from the seed (one sub-seed per kind). Furniture is built around the
ground-truth body so that it touches it, except that seats and mattresses are soft: the
body sinks 2-4 cm into the scanned surface. Scans are open surfaces with about 280k faces,
2 mm noise and a few holes away from the person, and are registered to the camera 1-3 cm
and 0.5-1.5 degrees off. Keypoints are what a detector reports (``benchmarks.detector``):
per-person offsets from the model's joints, left/right swaps and blur, on top of 2-4 px
noise; occluded joints are weakened or dropped, joints beyond the image's edge are not
reported (a tenth of the recordings are framed so that its bottom edge crosses the shins),
and some frames hold a spurious second person. Ground truth (never read by the fitter):
``ground_truth/<rec>/<frame>.npz`` with camera-frame ``vertices`` (V, 3) and BODY_25
``joints`` (25, 3), and ``meta.json``.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree
from trimesh.transformations import rotation_matrix

from prox_engine import metrics
from prox_engine.body.anny_body import AnnyBody
from prox_engine.dataset import Recording, load_scene_mesh
from prox_engine.keypoints import ANKLES, BODY, FEET, KNEES, LEFT_HAND, N_BODY, RIGHT_HAND
from prox_engine.output import atomic_write_text
from prox_engine.scene import Scene
from prox_engine.scene_sdf import compute_sdf
from prox_engine.synthetic import (HEIGHT, WIDTH, frame_name, look_at, open_box,
                                   openpose_person, paint, project, transform, write_frame,
                                   write_photos, write_scene)

from . import detector, kinect
from .poses import sample_phenotype, stature
from .staging import STAGES, Staging, table

KINDS = tuple(STAGES)  # in their order: a kind's index seeds its recording
FACES = 280_000  # target size of each scan


def make_benchmark(out: Path, seed: int, frames: int = 4, kinds: Sequence[str] = KINDS,
                   body: AnnyBody | None = None) -> list[str]:
    """Write one recording per kind under out (PROX layout) and return the recording names."""
    body = body or AnnyBody.load()
    kinect.write_calibration(Path(out), np.random.default_rng([seed, len(KINDS)]))
    # Height z-scores spread over the kinds, so that each seed has short and tall people.
    z_scores = np.random.default_rng(seed).permutation(np.linspace(-2.0, 2.0, len(KINDS)))
    return [make_recording(Path(out), kind, seed, frames, body, z_scores[KINDS.index(kind)])
            for kind in kinds]


def make_recording(out: Path, kind: str, seed: int, frames: int, body: AnnyBody,
                   height_z: float) -> str:
    """Write the scene, camera, keypoints and ground truth of one kind; return its name."""
    index = KINDS.index(kind)
    rng = np.random.default_rng([seed, index])
    scene = f"Bench{kind.capitalize()}{seed}"
    rec = f"{scene}_{100 * seed + index:05d}_01"
    phenotype = sample_phenotype(rng, body, height_z)
    staging = STAGES[kind](body, phenotype, frames, rng)
    cam_local, distance = place_camera(staging, body, kind, rng)
    cut_rng = np.random.default_rng([seed, index, 2])
    if cut_rng.random() < TRUNCATION_RATE:
        cam_local = cut_at_edge(cam_local, staging.keypoints, cut_rng)
    to_world = rotation_matrix(rng.uniform(-np.pi, np.pi), [0.0, 0.0, 1.0])
    cam2world = to_world @ cam_local
    vertices = transform(staging.vertices, to_world)
    furniture = [m.copy().apply_transform(to_world) for m in staging.furniture]
    bounds = room_bounds(vertices, furniture, cam2world[:3, 3], rng)
    furniture += distractors(bounds, vertices, furniture, cam2world[:3, 3], kind, rng)
    registration = misregistration(rng)
    mesh = paint(scan(bounds, furniture, vertices, rng))
    write_scene(out, scene, mesh, cam2world @ registration)

    to_cam = np.linalg.inv(cam_local)
    occluders = transform(trimesh.util.concatenate(furniture).triangles,
                          np.linalg.inv(cam2world))
    sigma = rng.uniform(2.0, 4.0)
    person = detector.subject(rng)
    names, occluded = [frame_name(t) for t in range(frames)], 0
    errors = {"legs swapped": 0, "arms swapped": 0, "blurred": 0, "truncated": 0}
    per_frame = {}
    for name, kp, verts in zip(names, staging.keypoints, staging.vertices):
        kp_cam, verts_cam = transform(kp, to_cam), transform(verts, to_cam)
        cond = detector.condition(rng, not _in_view(kp_cam[BODY], margin=0.0))
        for part in cond.swapped:
            errors[f"{part} swapped"] += 1
        errors["blurred"] += cond.blurred
        errors["truncated"] += cond.truncated
        per_frame[name] = asdict(cond)
        people, hidden = detections(detector.offset_keypoints(kp_cam, person), verts_cam,
                                    occluders, sigma, rng, cond)
        occluded += hidden
        write_frame(out, rec, name, people, verts_cam, kp_cam[:N_BODY])
    write_photos(out, rec, list(zip(names, vertices)), body.faces.numpy(), mesh, cam2world)
    kinect.write_depth(out, rec, list(zip(names, vertices)), body.faces.numpy(), mesh,
                       cam2world, np.random.default_rng([seed, index, 1]))
    meta = {"kind": kind, "scene": scene, "seed": seed, "phenotype": phenotype,
            "stature_m": stature(body, phenotype), "frames": names,
            "contact_parts": staging.contacts, "camera_distance_m": round(distance, 3),
            "occluded_share": round(occluded / (N_BODY * frames), 4),
            "detector_errors": errors, "frame_errors": per_frame,
            "cam2world": cam2world.tolist(),  # the true pose; the written one is off by:
            "misregistration": {"cm": round(100 * float(np.linalg.norm(registration[:3, 3])), 2),
                                "deg": round(float(np.degrees(np.arccos(np.clip(
                                    (np.trace(registration[:3, :3]) - 1) / 2, -1, 1)))), 2)}}
    atomic_write_text(out / "ground_truth" / rec / "meta.json", json.dumps(meta, indent=1))
    return rec


# --------------------------------------------------------------------------- camera, room
def misregistration(rng: np.random.Generator) -> np.ndarray:
    """A camera-frame rigid error of the scan's registration: 1-3 cm in a random direction
    and 0.5-1.5 degrees about a random axis (what the written cam2world is off by)."""
    return kinect.rigid_error(rng, (0.01, 0.03), (0.5, 1.5))


def place_camera(staging: Staging, body: AnnyBody, kind: str,
                 rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """A camera 2-3.5 m from the person's centre, aimed at it, seeing the whole body in
    every frame, 0.3 m clear of the furniture: 0.9-1.8 m high within 45 degrees of where
    the person faces, or for the bed 1.5-1.8 m high looking down from the foot end or side.
    Returns the camera-to-body-frame pose and the distance."""
    points = staging.vertices[:, body.scene_vertices.numpy()].reshape(-1, 3)
    centre = points.mean(0)
    heights, spread = ((1.5, 1.8), 80.0) if kind == "bed" else ((0.9, 1.8), 45.0)
    for _ in range(1000):
        distance, height = rng.uniform(2.0, 3.5), rng.uniform(*heights)
        azimuth = np.radians(rng.uniform(-spread, spread))
        ground = np.sqrt(distance ** 2 - (height - centre[2]) ** 2)
        position = np.array([centre[0] + ground * np.sin(azimuth),
                             centre[1] - ground * np.cos(azimuth), height])
        cam2body = look_at(position, centre)
        if (all(_box_distance(position[None], *m.bounds)[0] > 0.3 for m in staging.furniture)
                and _in_view(transform(points, np.linalg.inv(cam2body)))):
            return cam2body, float(distance)
    raise RuntimeError(f"{kind}: no camera position sees the whole person")


# A tenth of the recordings are framed as a person near a camera aimed at the upper body:
# the image's bottom edge crosses the shins, and whatever lies beyond it in a frame is not
# reported (truncation at the image edge, as in real recordings: where the motion takes it,
# a frame keeps a foot, or loses a knee too).
TRUNCATION_RATE = 0.1
MIN_SHINS_PX = 60.0  # shins shorter in the image (a lying or kneeling body) are not cut


def cut_at_edge(cam2body: np.ndarray, keypoints: np.ndarray, rng: np.random.Generator
                ) -> np.ndarray:
    """``cam2body`` pitched up until the image's bottom edge crosses the shins of the
    middle frame (``keypoints`` (F, 118, 3), body frame): the knees 20 px to 60 % of the
    shins' height in the image above it, the ankles beyond it. Unchanged where the shins
    are under MIN_SHINS_PX high in the image or the upper body (all but the knees and
    feet) would leave the image in some frame."""
    middle = keypoints[len(keypoints) // 2]

    def rows(pose: np.ndarray, joints: list[int]) -> float:
        return float(project(transform(middle[joints], np.linalg.inv(pose)))[:, 1].mean())

    shins = rows(cam2body, ANKLES) - rows(cam2body, KNEES)
    if shins < MIN_SHINS_PX:
        return cam2body
    target = HEIGHT - rng.uniform(20.0, 0.6 * shins)
    low, high = 0.0, 0.6  # radians of pitch: raising the view lowers the body in the image
    for _ in range(30):
        pitched = cam2body @ rotation_matrix((low + high) / 2, [1.0, 0.0, 0.0])
        low, high = ((low + high) / 2, high) if rows(pitched, KNEES) < target else (
            low, (low + high) / 2)
    upper = np.setdiff1d(np.arange(N_BODY), KNEES + FEET)
    if all(_in_view(transform(frame[upper], np.linalg.inv(pitched))) for frame in keypoints):
        return pitched
    return cam2body


def _in_view(points_cam: np.ndarray, margin: float = 20.0) -> bool:
    if (points_cam[:, 2] < 0.3).any():
        return False
    uv = project(points_cam)
    return bool((uv.min(0) > margin).all() and (uv.max(0) < [WIDTH - margin,
                                                             HEIGHT - margin]).all())


def _box_distance(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distances (N,) of points (N, D) to the axis-aligned box [lo, hi]."""
    return np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1)


def room_bounds(vertices: np.ndarray, furniture: list[trimesh.Trimesh], camera: np.ndarray,
                rng: np.random.Generator) -> np.ndarray:
    """Floor rectangle [[x0, y0], [x1, y1]] around the person, furniture and camera with
    0.5-1.5 m to spare on each side, at least 4.5 m square."""
    xy = np.concatenate([vertices.reshape(-1, 3)[:, :2], camera[None, :2],
                         *[m.vertices[:, :2] for m in furniture]])
    lo = xy.min(0) - rng.uniform(0.5, 1.5, 2)
    hi = xy.max(0) + rng.uniform(0.5, 1.5, 2)
    grow = np.maximum(4.5 - (hi - lo), 0.0) / 2
    return np.stack([lo - grow, hi + grow])


def distractors(bounds: np.ndarray, vertices: np.ndarray, furniture: list[trimesh.Trimesh],
                camera: np.ndarray, kind: str, rng: np.random.Generator
                ) -> list[trimesh.Trimesh]:
    """Two or three pieces of furniture 0.7 m from the person, clear of the staged
    furniture, the camera and its line of sight (the sitter always gets a dining table);
    a piece that finds no room is left out."""
    body_xy = vertices.reshape(-1, 3)[::11, :2]
    sight = np.linspace(camera[:2], body_xy.mean(0), 20)
    names = list(rng.choice(list(PIECES), rng.integers(2, 4), replace=False))
    if kind == "sit" and "dining table" not in names:
        names[0] = "dining table"
    placed: list[trimesh.Trimesh] = []
    for name in names:
        meshes = piece(name, rng)
        half = trimesh.util.concatenate(meshes).extents[:2] / 2
        for _ in range(50):
            centre = rng.uniform(bounds[0] + 0.05 + half, bounds[1] - 0.05 - half)
            lo, hi = centre - half, centre + half
            if (_box_distance(body_xy, lo, hi).min() > 0.7
                    and _box_distance(sight, lo, hi).min() > 0.3
                    and _box_distance(camera[None, :2], lo, hi)[0] > 0.6
                    and not any(((lo - 0.2 < m.bounds[1, :2])
                                 & (hi + 0.2 > m.bounds[0, :2])).all()
                                for m in furniture + placed)):
                placed += [m.apply_translation([*centre, 0.0]) for m in meshes]
                break
    return placed


PIECES = {"dining table": ((1.2, 1.6), (0.7, 0.9), (0.72, 0.78)),  # width, depth, height
          "side table": ((0.45, 0.7), (0.45, 0.7), (0.45, 0.65)),
          "cabinet": ((0.6, 1.2), (0.35, 0.5), (0.8, 1.9)),
          "ottoman": ((0.4, 0.7), (0.4, 0.7), (0.35, 0.45))}


def piece(name: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """A distractor of ``PIECES`` centred on x = y = 0, standing on the floor."""
    width, depth, height = (rng.uniform(*r) for r in PIECES[name])
    if name.endswith("table"):
        return table(-width / 2, width / 2, -depth / 2, depth / 2, height, 0.04)
    return [open_box([width, depth, height], [0.0, 0.0, height / 2])]


# --------------------------------------------------------------------------- scan
def scan(bounds: np.ndarray, furniture: list[trimesh.Trimesh], vertices: np.ndarray,
         rng: np.random.Generator) -> trimesh.Trimesh:
    """Floor, walls (no ceiling) and furniture as a scanner fuses them: open surfaces of
    about ``FACES`` near-isotropic faces, 2 mm vertex noise and 3-6 holes 5-15 cm across,
    0.4 m or more from the body."""
    area = (np.prod(bounds[1] - bounds[0]) + 2 * WALL * (bounds[1] - bounds[0]).sum()
            + sum(m.area for m in furniture))
    spacing = np.sqrt(2 * area / FACES)  # a grid has two faces per spacing squared
    mesh = trimesh.util.concatenate(room(bounds, spacing)
                                    + [g for m in furniture for g in gridded(m, spacing)])
    mesh.merge_vertices()
    centres = mesh.triangles_center
    clear = np.isinf(cKDTree(vertices.reshape(-1, 3)[::7]).query(
        centres, distance_upper_bound=0.4)[0])
    count = rng.integers(3, 7)
    keep = np.ones(len(centres), dtype=bool)
    for face, radius in zip(rng.choice(np.flatnonzero(clear), count, replace=False),
                            rng.uniform(0.025, 0.075, count)):
        keep &= np.linalg.norm(centres - centres[face], axis=1) > radius
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    mesh.vertices += rng.normal(0.0, 0.002, mesh.vertices.shape)
    return mesh


def gridded(boxes: trimesh.Trimesh, spacing: float) -> list[trimesh.Trimesh]:
    """Each rectangular side of a union of boxes as a regular grid of about ``spacing``
    (subdividing would keep the slivers of thin sides, whose normals noise scrambles)."""
    grids = []
    for box in boxes.split(only_watertight=False):
        normals = box.face_normals
        side = (normals @ normals.T > 0.999).argmax(1)  # first face of the same side
        for first in np.unique(side):
            corners = box.vertices[np.unique(box.faces[side == first])]
            edges = corners[1:] - corners[0]
            u, v = edges[np.argsort(np.linalg.norm(edges, axis=1))[:2]]
            if np.dot(np.cross(u, v), normals[first]) < 0:
                u, v = v, u
            grids.append(grid(corners[0], u, v, spacing))
    return grids


WALL = 2.8  # wall height, metres


def room(bounds: np.ndarray, spacing: float) -> list[trimesh.Trimesh]:
    """Floor and four walls over ``bounds`` as regular grids, normals pointing inside."""
    (x0, y0), (x1, y1) = bounds
    dx, dy, up = [x1 - x0, 0.0, 0.0], [0.0, y1 - y0, 0.0], [0.0, 0.0, WALL]
    return [grid([x0, y0, 0.0], dx, dy, spacing), grid([x0, y0, 0.0], up, dx, spacing),
            grid([x0, y1, 0.0], dx, up, spacing), grid([x0, y0, 0.0], dy, up, spacing),
            grid([x1, y0, 0.0], up, dy, spacing)]


def grid(origin: list[float], u: list[float], v: list[float],
         spacing: float) -> trimesh.Trimesh:
    """The rectangle origin + [0, 1] u + [0, 1] v as a regular triangle grid, normal u x v."""
    nu, nv = (max(1, int(np.ceil(np.linalg.norm(w) / spacing))) for w in (u, v))
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    points = np.asarray(origin) + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    index = np.arange(len(points)).reshape(nu + 1, nv + 1)
    c00, c10 = index[:-1, :-1].ravel(), index[1:, :-1].ravel()
    c11, c01 = index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([c00, c10, c11], 1), np.stack([c00, c11, c01], 1)])
    return trimesh.Trimesh(points, faces, process=False)


# --------------------------------------------------------------------------- keypoints
def detections(kp_cam: np.ndarray, verts_cam: np.ndarray, occluders: np.ndarray,
               sigma: float, rng: np.random.Generator,
               cond: detector.Condition | None = None) -> tuple[list[dict], int]:
    """OpenPose-like people for one frame (118-point camera-frame keypoints in, no face
    out) and the number of body joints that furniture hides.

    Visible joints get ``sigma`` px of noise and confidence 0.6-0.95 (hands 0.3-0.7),
    halved behind the body's own surface; joints behind furniture are dropped or kept with
    0.05-0.3 and 20-60 px of error, half each; joints outside the image are dropped. A
    quarter of the frames add a faint partial second person."""
    n = len(kp_cam)
    depth = np.linalg.norm(kp_cam, axis=1)
    rays = kp_cam / depth[:, None]
    hidden = first_hits(rays, occluders) < depth - 0.02
    along = verts_cam @ rays.T  # (V, n)
    across = (verts_cam ** 2).sum(1)[:, None] - along ** 2
    behind_self = ((across < 0.015 ** 2) & (along < depth - 0.1)).any(0)
    conf = rng.uniform(0.6, 0.95, n)
    for hand in (LEFT_HAND, RIGHT_HAND):
        conf[hand] = rng.uniform(0.3, 0.7, hand.stop - hand.start)
    uv = project(kp_cam) + rng.normal(0.0, sigma, (n, 2))
    conf[behind_self] *= 0.5
    drop = hidden & (rng.random(n) < 0.5)
    weak = hidden & ~drop
    conf[weak] = rng.uniform(0.05, 0.3, weak.sum())
    angle = rng.uniform(0.0, 2 * np.pi, weak.sum())
    uv[weak] += rng.uniform(20.0, 60.0, weak.sum())[:, None] * np.stack(
        [np.cos(angle), np.sin(angle)], 1)
    drop |= (kp_cam[:, 2] <= 0) | (uv < 0).any(1) | (uv[:, 0] >= WIDTH) | (uv[:, 1] >= HEIGHT)
    conf[drop], uv[drop] = 0.0, 0.0
    if cond is not None:  # swaps, blur, truncation (benchmarks.detector)
        uv, conf = detector.apply(uv, conf, cond, rng)
    people = [openpose_person(uv, conf)]
    if rng.random() < 0.25:
        ghost = spurious_person(uv[BODY], conf[BODY], rng)
        if ghost is not None:
            people.insert(int(rng.integers(0, 2)), ghost)
    return people, int(hidden[BODY].sum())


def spurious_person(uv: np.ndarray, conf: np.ndarray, rng: np.random.Generator
                    ) -> dict | None:
    """A false detection: a smaller copy of some of the body joints elsewhere in the
    image, with confidences 0.1-0.35 summing to under a third of the real ones."""
    seen = conf > 0
    centre = uv[seen].mean(0)
    shape = (uv - centre) * rng.uniform(0.4, 0.7) + rng.normal(0.0, 5.0, uv.shape)
    keep = seen & (rng.random(len(uv)) < rng.uniform(0.3, 0.7))
    span = np.ptp(uv[seen], axis=0)
    for _ in range(20):
        target = rng.uniform([0.0, 0.0], [WIDTH, HEIGHT])
        fake = shape + target
        inside = (fake[keep] > 0).all() and (fake[keep] < [WIDTH, HEIGHT]).all()
        if inside and (np.abs(target - centre) > span * 0.8).any():
            ghost_conf = np.where(keep, rng.uniform(0.1, 0.35, len(uv)), 0.0)
            ghost_conf *= min(1.0, conf.sum() / 3 / max(ghost_conf.sum(), 1e-9))
            full_uv, full_conf = np.zeros((N_POINTS, 2)), np.zeros(N_POINTS)
            full_uv[BODY] = np.where(keep[:, None], fake, 0.0)
            full_conf[BODY] = ghost_conf
            return openpose_person(full_uv, full_conf)
    return None


N_POINTS = RIGHT_HAND.stop  # body and hands: the face is left out


def first_hits(rays: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Distance from the origin along each unit ray (R, 3) to the first of the triangles
    (T, 3, 3) it crosses, inf where none (Moller-Trumbore)."""
    if len(triangles) == 0:
        return np.full(len(rays), np.inf)
    a = triangles[:, 0]
    e1, e2 = triangles[:, 1] - a, triangles[:, 2] - a
    p = np.cross(rays[:, None], e2[None])  # (R, T, 3)
    det = (p * e1).sum(-1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = -a  # the rays start at the origin
    u = (p * s).sum(-1) * inv
    q = np.cross(s, e1)  # (T, 3)
    v = (rays @ q.T) * inv
    t = (e2 * q).sum(-1) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
    return np.where(hit, t, np.inf).min(1)


# --------------------------------------------------------------------------- checks
def ground_truth_check(out: Path, rec: str, body: AnnyBody | None = None) -> dict:
    """How the ground truth sits in its scan (at the true registration): ``penetration``,
    the mean share of ``body.scene_vertices`` more than 1 cm inside it; ``contact``, the
    share of the vertices of the recording's contact parts within 2 cm of it;
    ``touching``, per contact part the number of frames in which one of its vertices is
    that close. Uses exact distances (a 64^3 SDF of the scan within 0.3 m of the body,
    exact closest points)."""
    body = body or AnnyBody.load()
    recording = Recording(Path(out), rec)
    truth = Path(out) / "ground_truth" / rec
    meta = json.loads((truth / "meta.json").read_text())
    cam2world = np.asarray(meta["cam2world"])  # the true registration, not the written one
    frames = [torch.from_numpy(np.load(truth / f"{name}.npz")["vertices"])
              for name in meta["frames"]]
    world = transform(torch.cat(frames).numpy(), cam2world)
    vertices, faces = load_scene_mesh(recording.scene_path)
    lo, hi = world.min(0) - 0.3, world.max(0) + 0.3
    centres = vertices[faces].mean(1)
    crop = trimesh.Trimesh(vertices, faces[((centres > lo) & (centres < hi)).all(1)],
                           process=False)
    crop.remove_unreferenced_vertices()
    padding = max(0.1, *(crop.bounds[0] - lo), *(hi - crop.bounds[1]))  # box holds body
    # Exact values at every voxel, so the check does not rest on the far-field
    # approximation of the SDF the fitter uses.
    sdf = compute_sdf(crop.vertices, crop.faces, dim=64, padding=padding, band_voxels=64)
    scene = Scene(crop.vertices, crop.faces, cam2world, sdf)
    penetration, close = [], []
    touching = dict.fromkeys(meta["contact_parts"], 0)
    for verts in frames:
        penetration.append(metrics.penetration_stats(verts, body, scene)["penetrating_share"])
        for part in touching:
            points = verts[body.contact_parts[part]]
            with torch.no_grad():
                near = (scene.exact_signed_distance(points) < metrics.CONTACT_THRESHOLD).numpy()
            close.append(near)
            touching[part] += int(near.any())
    return {"penetration": float(np.mean(penetration)),
            "contact": float(np.concatenate(close).mean()), "touching": touching}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
    args = parser.parse_args()
    torch.set_num_threads(1)
    body = AnnyBody.load()
    names = make_benchmark(args.out, args.seed, args.frames, args.kinds, body)
    print(f"{'recording':<22} {'faces':>7} {'pen %':>6} {'contact %':>9} {'camera m':>8} "
          f"{'occluded %':>10}  touching (frames)")
    for rec in names:
        meta = json.loads((args.out / "ground_truth" / rec / "meta.json").read_text())
        faces = len(load_scene_mesh(Recording(args.out, rec).scene_path)[1])
        check = ground_truth_check(args.out, rec, body)
        touching = " ".join(part if n == args.frames else f"{part}({n}/{args.frames})"
                            for part, n in check["touching"].items())
        print(f"{rec:<22} {faces:>7} {100 * check['penetration']:6.2f} "
              f"{100 * check['contact']:9.1f} {meta['camera_distance_m']:8.2f} "
              f"{100 * meta['occluded_share']:10.1f}  {touching}")


if __name__ == "__main__":
    main()
