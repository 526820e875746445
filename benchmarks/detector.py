"""How OpenPose's detections differ from a body model's joints, applied to the generated
ground truth so that the benchmark stops agreeing with the engine by construction:

- per-subject joint offsets: OpenPose's hips sit 3-7 cm higher and up to 3 cm wider than a
  model's hip joints, its shoulders a little higher, the other joints 1-2 cm off in a
  direction that stays the same for a person;
- left/right swaps of the legs in about 10 % of the frames and of the arms in about 5 %;
- motion blur in about 15 % of the frames: 10 px of noise and lower confidences;
- truncation at the image edge (``benchmarks.generate.cut_at_edge`` frames a tenth of the
  recordings so that the bottom edge crosses the shins): what lies beyond it is not
  reported.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prox_engine.keypoints import SIDE_PAIRS, side_swap

LEFT_RIGHT = {**SIDE_PAIRS, "head": [(16, 15), (18, 17)]}
SWAP_RATES = {"legs": 0.10, "arms": 0.05}
BLUR_RATE, BLUR_PX = 0.15, 10.0


@dataclass
class Subject:
    """One person's fixed offsets of the BODY_25 keypoints, (25, 3) metres along the
    body's (outward, up, forward) axes."""

    offsets: np.ndarray


def subject(rng: np.random.Generator) -> Subject:
    """Offsets drawn for one person, the same for a joint and its mirror image."""
    offsets = np.zeros((25, 3))
    for left, right in LEFT_RIGHT["arms"] + LEFT_RIGHT["legs"] + LEFT_RIGHT["head"]:
        offsets[left] = offsets[right] = rng.normal(0.0, 0.012, 3)
    for left, right in [(12, 9)]:  # hips
        offsets[left] = offsets[right] = [rng.uniform(0.0, 0.03), rng.uniform(0.03, 0.07),
                                          rng.uniform(-0.02, 0.02)]
    for left, right in [(5, 2)]:  # shoulders
        offsets[left] = offsets[right] = [rng.uniform(-0.01, 0.02), rng.uniform(0.0, 0.03),
                                          rng.uniform(-0.01, 0.01)]
    offsets[0] = rng.normal(0.0, 0.01, 3)
    return Subject(offsets)


def offset_keypoints(kp: np.ndarray, person: Subject) -> np.ndarray:
    """The 118 keypoints (camera frame) with the person's body offsets applied along the
    body's own axes in this frame, so that they follow the body as it turns or lies."""
    up = kp[1] - kp[8]
    up /= np.linalg.norm(up)
    lateral = kp[12] - kp[9]  # toward the person's left
    lateral -= (lateral @ up) * up
    lateral /= np.linalg.norm(lateral)
    forward = np.cross(lateral, up)
    out = kp.copy()
    left = {left for left, _ in sum(LEFT_RIGHT.values(), [])}
    right = {right for _, right in sum(LEFT_RIGHT.values(), [])}
    for j in range(25):
        outward = lateral if j in left else -lateral if j in right else lateral
        o = person.offsets[j]
        out[j] = kp[j] + o[0] * outward + o[1] * up + o[2] * forward
    out[1] = (out[2] + out[5]) / 2  # OpenPose's neck: between its shoulders
    out[8] = (out[9] + out[12]) / 2
    return out


@dataclass
class Condition:
    """What goes wrong in one frame."""

    swapped: list[str]  # "legs", "arms"
    blurred: bool
    truncated: bool


def condition(rng: np.random.Generator, truncated: bool) -> Condition:
    """Swaps and blur drawn for one frame; ``truncated``: the image's edge cuts the body."""
    return Condition([part for part, rate in SWAP_RATES.items() if rng.random() < rate],
                     bool(rng.random() < BLUR_RATE), truncated)


def apply(uv: np.ndarray, conf: np.ndarray, cond: Condition,
          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Pixel keypoints and confidences (118 rows) as the detector reports them in a
    frame with ``cond``: swapped sides, blur."""
    order = side_swap(tuple(cond.swapped))
    uv, conf = uv[order].copy(), conf[order].copy()
    if cond.blurred:
        seen = conf > 0
        uv[seen] += rng.normal(0.0, BLUR_PX, (int(seen.sum()), 2))
        conf[seen] *= rng.uniform(0.5, 0.8, int(seen.sum()))
    return uv, conf
