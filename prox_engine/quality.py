"""Quality flags: frames whose fit is probably wrong, from what the fit itself knows. A flag
is ``{"kind": ..., "detail": ...}``; frames carry theirs in ``summary.json``.

Per frame (:func:`frame_flags`): the body hidden behind the scan where the detector saw it,
its underside clear of every surface (floating), or deep inside the scan. Over the recording
(:func:`recording_flags`): a reprojection error or a distance from the camera far from the
recording's median, and a jump from the previous frame faster than a person moves.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .keypoints import BODY, SEEN
from .scene import Scene

HIDDEN_SHARE = 0.5  # flag when at least this share of the clearly seen joints is hidden
UNDERSIDE = 0.10  # m: a body's underside, what rests on something, is its lowest 10 cm
FLOATING = 0.05  # m: the underside this far above the surface below it
REACH = 0.5  # m: how far below the underside a surface is looked for
SUNK = 0.10  # m: a vertex this deep inside the scan
MIN_FRAMES = 3  # recording-level outliers need a median to stand out from
ERROR_RATIO, ERROR_MIN = 3.0, 10.0  # reprojection error > 3 x median and > 10 px
DEPTH_RATIO = 0.25  # distance from the camera off the median by more than 25 %
SPEED = 3.0  # m/s: faster than anyone walks around a room


def _flag(kind: str, detail: str) -> dict:
    return {"kind": kind, "detail": detail}


@torch.no_grad()
def hidden_joints(joints: torch.Tensor, confidence: np.ndarray, scene: Scene
                  ) -> tuple[int, int]:
    """Of the body joints (camera frame, (25, 3)) the detector clearly saw, how many lie
    behind a scan surface from the camera; returns (hidden, seen)."""
    seen = joints[torch.from_numpy(confidence[BODY] > SEEN)]
    return int((scene.visible_scale(seen, 1.0) <= 1.0).sum()), len(seen)


@torch.no_grad()
def underside_gap(vertices: torch.Tensor, scene: Scene) -> float:
    """How far (m) the body's underside (its lowest 10 cm: a standing body's soles, a lying
    body's back) is above the first surface straight below it; inf beyond 50 cm."""
    height = scene.to_world(vertices)[:, 2]
    under = vertices[height < height.min() + UNDERSIDE][::4]
    return scene.nearest_hit(under, -scene.up_in_camera().expand_as(under), REACH)


def gap_text(gap: float) -> str:
    """An :func:`underside_gap` in words: '12 cm', or 'more than 50 cm' beyond REACH."""
    return f"{gap * 100:.0f} cm" if math.isfinite(gap) else f"more than {REACH * 100:.0f} cm"


def frame_flags(stats: dict, vertices: torch.Tensor, joints: torch.Tensor,
                confidence: np.ndarray, scene: Scene, gap: float | None = None
                ) -> list[dict]:
    """Flags of one fitted frame: ``stats`` as :func:`metrics.scene_stats` wrote them,
    the fitted ``vertices`` (V, 3) and body ``joints`` (25, 3) in camera coordinates,
    ``confidence`` the detector's (118,), and the :func:`underside_gap` if already
    measured."""
    flags = []
    hidden, seen = hidden_joints(joints, confidence, scene)
    if seen and hidden >= HIDDEN_SHARE * seen:
        flags.append(_flag("hidden", f"{hidden} of the {seen} joints the detector saw are "
                                     "behind the scan from the camera"))
    gap = underside_gap(vertices, scene) if gap is None else gap
    if gap > FLOATING:
        flags.append(_flag("floating", f"nothing under the body: its underside is "
                                       f"{gap_text(gap)} above any surface"))
    if stats["max_depth_m"] > SUNK:
        flags.append(_flag("sunk", f"part of the body is {stats['max_depth_m'] * 100:.0f} cm "
                                   "inside the scan"))
    return flags


def recording_flags(frames: list[dict], times: list[float]) -> None:
    """Add to each frame's ``flags`` (in place) the outliers of the recording: reprojection
    error, distance from the camera, and speed since the previous frame. ``frames`` are the
    summary's, in order; ``times`` their time in the recording (s)."""
    if len(frames) >= MIN_FRAMES:
        error = np.median([f["reprojection_error_px"] for f in frames])
        distance = np.median([np.linalg.norm(f["root_m"]) for f in frames])
        for f in frames:
            if f["reprojection_error_px"] > max(ERROR_RATIO * error, ERROR_MIN):
                f["flags"].append(_flag("reprojection", f"data error "
                                        f"{f['reprojection_error_px']:.0f} px against "
                                        f"{error:.0f} px for the recording's median"))
            off = np.linalg.norm(f["root_m"]) / distance - 1
            if abs(off) > DEPTH_RATIO:
                f["flags"].append(_flag("distance", f"{abs(off) * 100:.0f} % "
                                        f"{'farther from' if off > 0 else 'closer to'} the "
                                        "camera than the recording's median"))
    for i in range(1, len(frames)):
        before, f = frames[i - 1], frames[i]
        seconds = times[i] - times[i - 1]
        moved = float(np.linalg.norm(np.subtract(f["root_m"], before["root_m"])))
        if seconds > 0 and moved / seconds > SPEED:
            f["flags"].append(_flag("jump", f"moved {moved:.2f} m in {seconds:.2f} s since "
                                            f"{before['frame']}"))
