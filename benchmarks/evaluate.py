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
from prox_engine.dataset import Recording, load_cam2world, load_scene_mesh
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


def frame_metrics(fit_vertices: np.ndarray, gt_vertices: np.ndarray, body: BodyModel,
                  scene: Scene) -> dict:
    """PJE, V2V and their Procrustes-aligned versions (mm), penetration of the fit, and
    which ground-truth contact parts the fit recovers."""
    weights = body.keypoint_weights.numpy()
    fit_joints, gt_joints = weights @ fit_vertices, weights @ gt_vertices
    fit_t = torch.as_tensor(fit_vertices, dtype=torch.float32)
    gt_t = torch.as_tensor(gt_vertices, dtype=torch.float32)
    pen = metrics.penetration_stats(fit_t, body, scene)
    gt_contact = set(metrics.contact_parts(gt_t, body, scene))
    fit_contact = set(metrics.contact_parts(fit_t, body, scene))
    return {
        "pje": _mean_error_mm(fit_joints, gt_joints),
        "v2v": _mean_error_mm(fit_vertices, gt_vertices),
        "p_pje": _mean_error_mm(procrustes(fit_joints, gt_joints), gt_joints),
        "p_v2v": _mean_error_mm(procrustes(fit_vertices, gt_vertices), gt_vertices),
        "penetrating_share": pen["penetrating_share"],
        "penetration_mean_depth_m": pen["mean_depth_m"],
        "gt_contacts": len(gt_contact),
        "contacts_recovered": len(gt_contact & fit_contact),
    }


def evaluate_recording(data: Path, recording: str, fitted: Path, body: BodyModel,
                       sdf_dim: int = 256) -> list[dict]:
    """Metrics of every fitted frame of ``recording`` (``fitted`` = the ``--out`` folder)."""
    rec = Recording(Path(data), recording)
    scene = Scene.load(*load_scene_mesh(rec.scene_path), load_cam2world(rec.cam2world_path),
                       rec.sdf_paths, dim=sdf_dim)
    summary = json.loads((Path(fitted) / recording / "summary.json").read_text())
    rows = []
    for frame in summary["frames"]:
        name = frame["frame"]
        gt = np.load(Path(data) / "ground_truth" / recording / f"{name}.npz")["vertices"]
        mesh = trimesh.load(Path(fitted) / recording / "meshes" / name / "000.ply",
                            process=False)
        rows.append({"frame": name, "seconds": frame["seconds"],
                     **frame_metrics(np.asarray(mesh.vertices, dtype=np.float64),
                                     gt.astype(np.float64), body, scene)})
    return rows


def aggregate(rows: list[dict]) -> dict:
    """Means over frames; contact = share of ground-truth contact parts recovered."""
    if not rows:
        return {}
    mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
    gt = sum(r["gt_contacts"] for r in rows)
    return {
        "frames": len(rows),
        **{k: mean(k) for k in ("pje", "v2v", "p_pje", "p_v2v", "penetrating_share",
                                "penetration_mean_depth_m", "seconds")},
        "contact_recovered": sum(r["contacts_recovered"] for r in rows) / gt if gt else None,
    }
