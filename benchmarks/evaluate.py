"""Accuracy of fitted recordings against the generator's ground truth (the paper's Table 1
metrics plus penetration and contact).

Joints are regressed from the fitted vertices with the body model's own keypoint
regressor, the one that made the ground-truth joints, so PJE compares like with like.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import trimesh

from prox_engine import metrics
from prox_engine.body.base import BodyModel
from prox_engine.dataset import Recording, load_scene_mesh
from prox_engine.scene import Scene


def procrustes(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``pred`` (N, 3) after the similarity transform that best aligns it with ``gt``."""
    mu_p, mu_g = pred.mean(0), gt.mean(0)
    p, g = pred - mu_p, gt - mu_g
    u, s, vt = np.linalg.svd(p.T @ g)
    d = np.sign(np.linalg.det(u @ vt))
    s[-1] *= d
    u[:, -1] *= d
    rotation = u @ vt
    scale = s.sum() / (p ** 2).sum()
    return scale * p @ rotation + mu_g


def _mean_error_mm(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b, axis=1).mean() * 1000)


def truth_meta(data: Path, recording: str) -> dict:
    """The generator's ``meta.json`` of a recording: its kind, person, true registration
    and what the detector did to each frame."""
    return json.loads((Path(data) / "ground_truth" / recording / "meta.json").read_text())


def truth_scene(data: Path, recording: str, sdf_dim: int = 256) -> Scene:
    """The recording's scan at its true registration to the camera (the generator writes
    a slightly wrong one for the fitter, as real registrations are)."""
    meta = truth_meta(data, recording)
    rec = Recording(Path(data), recording)
    return Scene.load(*load_scene_mesh(rec.scene_path), np.asarray(meta["cam2world"]),
                      rec.sdf_paths, dim=sdf_dim)


def frame_metrics(fit_vertices: np.ndarray, gt_vertices: np.ndarray, body: BodyModel,
                  fit_stats: dict, gt_contact: set[str]) -> dict:
    """PJE, V2V and their Procrustes-aligned versions (mm); the depth ratio (see
    :func:`depth_ratio`); the fit's penetration and which ground-truth contact parts it
    recovers, from its scene statistics ``fit_stats``
    (:func:`prox_engine.metrics.scene_stats` in the true scene). Vertices (V, 3) in the
    camera frame."""
    weights = body.keypoint_weights.numpy()
    fit_joints, gt_joints = weights @ fit_vertices, weights @ gt_vertices
    return {
        "pje": _mean_error_mm(fit_joints, gt_joints),
        "v2v": _mean_error_mm(fit_vertices, gt_vertices),
        "p_pje": _mean_error_mm(procrustes(fit_joints, gt_joints), gt_joints),
        "p_v2v": _mean_error_mm(procrustes(fit_vertices, gt_vertices), gt_vertices),
        "depth_ratio": depth_ratio(fit_vertices, gt_vertices),
        "penetrating_share": fit_stats["penetrating_share"],
        "penetration_mean_depth_m": fit_stats["mean_depth_m"],
        "gt_contacts": len(gt_contact),
        "contacts_recovered": len(gt_contact & set(fit_stats["contact_parts"])),
    }


def depth_ratio(fit_vertices: np.ndarray, gt_vertices: np.ndarray) -> float:
    """How far along the camera's rays a fit sits against the truth: its vertices'
    centroid's distance from the camera over the truth's (camera frame; 1.05: 5 % too far).
    Keypoints fix a body only up to a scale about the camera, so this is where the scale
    search and the size prior show: a fit of the right posture at the wrong depth."""
    return float(np.linalg.norm(fit_vertices.mean(0)) / np.linalg.norm(gt_vertices.mean(0)))


# The truth's vertices this near its lowest point carry it (soles, buttocks, a lying back)
SUPPORT_BAND_M = 0.02


def scene_height_error(gt_vertices: np.ndarray, registered: np.ndarray, true: np.ndarray
                       ) -> float:
    """How far above its true place (m) the scene sits, as the fitter registered it
    (``registered``, its cam2world), under the true body's lowest vertices (``gt_vertices``
    (V, 3) camera frame; ``true`` the true cam2world; world z up): +1.5 cm, a floor or seat
    read that much too high, on which the scale search rests the body nearer the camera.
    The colour-to-depth calibration's pitch goes into the registration unseen
    (``kinect.CALIBRATION_ERROR``); this shows it."""
    height = gt_vertices @ true[2, :3] + true[2, 3]
    read = gt_vertices @ registered[2, :3] + registered[2, 3]
    low = height <= height.min() + SUPPORT_BAND_M
    return float((height[low] - read[low]).mean())


# What the generator's detector did to a frame (benchmarks.detector), worst first: a frame
# cut off below the knees by the image's edge (benchmarks.generate.cut_at_edge) counts as
# cut off whatever else happened to it, a blurred one as blurred, and so on.
CONDITIONS = ("cut off below the knees", "blurred", "sides swapped", "clean")


def condition(errors: dict) -> str:
    """The frame's entry of CONDITIONS, from its ``frame_errors`` in the truth's meta.json
    (``{}``: clean)."""
    if errors.get("truncated"):
        return CONDITIONS[0]
    if errors.get("blurred"):
        return CONDITIONS[1]
    return CONDITIONS[2] if errors.get("swapped") else CONDITIONS[3]


def evaluate_recording(data: Path, recording: str, fitted: Path, body: BodyModel,
                       scene: Scene) -> list[dict]:
    """Metrics of every fitted frame of ``recording`` (``fitted`` = the ``--out`` folder)
    against the ground truth, ``scene`` being its :func:`truth_scene` (penetration and
    contacts of the fit and the truth are measured in the real scene)."""
    summary = json.loads((Path(fitted) / recording / "summary.json").read_text())
    truth = truth_meta(data, recording)
    registered = summary.get("registration", {}).get("cam2world")  # not in older fits
    registered = None if registered is None else np.asarray(registered)
    true_cam2world = np.asarray(truth["cam2world"])
    rows = []
    for frame in summary["frames"]:
        name = frame["frame"]
        gt = np.load(Path(data) / "ground_truth" / recording / f"{name}.npz")["vertices"]
        gt_contact = set(metrics.contact_parts(torch.as_tensor(gt), body, scene))
        mesh = trimesh.load(Path(fitted) / recording / "meshes" / name / "000.ply",
                            process=False)
        fit = np.asarray(mesh.vertices, dtype=np.float64)
        stats, _ = metrics.scene_stats(torch.as_tensor(fit, dtype=torch.float32), body, scene)
        errors = truth.get("frame_errors", {}).get(name, {})
        swapped = errors.get("swapped", [])
        rows.append({"frame": name, "seconds": frame["seconds"],
                     "condition": condition(errors),
                     **({"size_ratio": frame["stature_m"] / truth["stature_m"]}
                        if "stature_m" in frame else {}),  # not in fits made before it was
                     **({"scene_height_error_m": scene_height_error(gt, registered,
                                                                    true_cam2world)}
                        if registered is not None else {}),
                     # the fit's own statistic: inside the scan as the fitter read it
                     "penetrating_share_as_given": frame["penetrating_share"],
                     "sides_right": set(frame.get("sides_swapped", [])) == set(swapped),
                     **frame_metrics(fit, gt.astype(np.float64), body, stats, gt_contact)})
    return rows


def aggregate(rows: list[dict]) -> dict:
    """Means over frames; contact = share of ground-truth contact parts recovered; sides =
    share of frames fitted with the left/right labelling the detector's truth had; depth off
    and bias = the mean of |depth ratio - 1| and of depth ratio - 1, size off and bias the
    same of the size ratio (the fit's stature over the truth's), scene height off and bias
    the same of :func:`scene_height_error` (m; each None for rows written before it was)."""
    if not rows:
        return {}
    mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
    gt = sum(r["gt_contacts"] for r in rows)
    return {
        "frames": len(rows),
        **{k: mean(k) for k in ("pje", "v2v", "p_pje", "p_v2v", "penetrating_share",
                                "penetration_mean_depth_m", "penetrating_share_as_given",
                                "seconds")},
        "contact_recovered": sum(r["contacts_recovered"] for r in rows) / gt if gt else None,
        "sides_right": mean("sides_right"),  # frames whose left/right labelling the fit got
        **_off_and_bias(rows, "depth"),
        **_off_and_bias(rows, "size"),
        **_off_and_bias(rows, "scene_height", "error_m", 0.0),
    }


def _off_and_bias(rows: list[dict], what: str, read: str = "ratio", right: float = 1.0
                  ) -> dict:
    """``{what}_off`` and ``{what}_bias``: the mean of |x - right| and of x - right over the
    rows' ``{what}_{read}`` (a ratio, right at 1, by default; None where a row has none)."""
    errors = np.array([r.get(f"{what}_{read}", np.nan) for r in rows]) - right
    known = not np.isnan(errors).any()
    return {f"{what}_off": float(np.abs(errors).mean()) if known else None,
            f"{what}_bias": float(errors.mean()) if known else None}
