"""OpenPose keypoint layout (BODY_25 + two hands + face) and keypoint-file parsing."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError

if TYPE_CHECKING:  # the service parses keypoints without importing torch
    import torch

BODY_25 = [
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder",
    "left_elbow", "left_wrist", "mid_hip", "right_hip", "right_knee", "right_ankle",
    "left_hip", "left_knee", "left_ankle", "right_eye", "left_eye", "right_ear", "left_ear",
    "left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe",
    "right_heel",
]
HAND_21 = ["wrist"] + [f"{finger}_{k}" for finger in ("thumb", "index", "middle", "ring", "pinky")
                       for k in range(1, 5)]
# OpenPose's 70 face points; like PROX we fit 17..67 (brows, nose, eyes, mouth), not the
# jaw contour (0..16) and never the pupils (68, 69).
FACE_FIT = list(range(17, 68))

N_BODY, N_HAND, N_FACE = 25, 21, len(FACE_FIT)
BODY = slice(0, N_BODY)
LEFT_HAND = slice(N_BODY, N_BODY + N_HAND)
RIGHT_HAND = slice(N_BODY + N_HAND, N_BODY + 2 * N_HAND)
FACE = slice(N_BODY + 2 * N_HAND, N_BODY + 2 * N_HAND + N_FACE)
N_KEYPOINTS = FACE.stop  # 118, the SMPLify-X layout

# Left/right pairs a detector confuses (BODY_25 rows), by part; an arm swap takes the hand.
SIDE_PAIRS = {"legs": [(12, 9), (13, 10), (14, 11), (19, 22), (20, 23), (21, 24)],
              "arms": [(5, 2), (6, 3), (7, 4)]}

# Torso edges (shoulder-hip) for the similar-triangles depth initialisation.
TORSO_EDGES = [(2, 9), (5, 12)]  # right shoulder - right hip, left shoulder - left hip
MID_HIP, NECK = 8, 1  # the trunk, for the upright prior
ANKLES = [11, 14]  # right, left: a frame cut off at the knees has neither
# Per leg (right, left), the knee and what hangs from it: ankle, big toe, small toe, heel.
SHINS = [(10, [11, 22, 23, 24]), (13, [14, 19, 20, 21])]
HIPS = [9, 12]  # right, left: where each leg of SHINS hangs from
FOREARMS = [(3, 4), (6, 7)]  # (elbow, wrist), right then left
SHOULDERS = [2, 5]  # right, left: where each arm of FOREARMS hangs from
KNEES = [knee for knee, _ in SHINS]
FEET = [j for _, foot in SHINS for j in foot]  # ankles, toes and heels
TOES = [j for _, foot in SHINS for j in foot[1:3]]  # big and small toes
# The limbs whose keypoints sequence mode checks one by one: shoulder, elbow and wrist; hip,
# knee and ankle.
LIMBS = {"right arm": (2, 3, 4), "left arm": (5, 6, 7), "right leg": (9, 10, 11),
         "left leg": (12, 13, 14)}
# The arms' keypoints (118 layout): elbows, wrists (right, left) and both hands.
ARMS = [3, 4, 6, 7, *range(LEFT_HAND.start, RIGHT_HAND.stop)]
SEEN = 0.5  # detector confidence of a joint it clearly saw
# ... and below which a joint is a guess, hidden behind something: a blurred or
# self-occluded joint the detector sees is reported at 0.3-0.5, a joint behind furniture
# lower (or not at all)
HIDDEN = 0.3
MAX_PIXEL = 1e6  # no image is this large; squares of larger values overflow float32


def side_swap(parts: tuple[str, ...]) -> list[int]:
    """Row order (118) that exchanges the left and right keypoints of ``parts``."""
    order = list(range(N_KEYPOINTS))
    for part in parts:
        for left, right in SIDE_PAIRS[part]:
            order[left], order[right] = right, left
        if part == "arms":
            hands = list(range(LEFT_HAND.start, LEFT_HAND.stop))
            for i in hands:
                order[i], order[i + N_HAND] = i + N_HAND, i
    return order


LABELLINGS = ((), ("legs",), ("arms",), ("legs", "arms"))  # as detected, then swapped


@dataclass
class Keypoints:
    """One person's 2D keypoints, (118, 3) rows of (x, y, confidence) in the layout above."""

    data: np.ndarray
    has_hands: bool
    has_face: bool

    @property
    def xy(self) -> np.ndarray:
        return self.data[:, :2]

    @property
    def confidence(self) -> np.ndarray:
        return self.data[:, 2]


def _points(person: dict, key: str, count: int, path: Path) -> np.ndarray | None:
    values = person.get(key)
    if values is None or values == []:
        return None
    if not isinstance(values, list) or len(values) != 3 * count:
        got = len(values) if isinstance(values, list) else type(values).__name__
        raise InputError(path, f"'{key}' must hold {3 * count} numbers ({count} x, y, "
                               f"confidence), got {got}")
    try:
        array = np.asarray(values, dtype=np.float64).reshape(count, 3)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(path, f"'{key}' contains non-numeric values") from exc
    if not np.isfinite(array).all():
        raise InputError(path, f"'{key}' contains NaN or infinite values")
    if (array[:, 2] < 0).any():
        raise InputError(path, f"'{key}' has negative confidences")
    if (np.abs(array[:, :2]) > MAX_PIXEL).any() or (array[:, 2] > MAX_PIXEL).any():
        raise InputError(path, f"'{key}' has values beyond {MAX_PIXEL:.0e} (pixels of "
                               "an image, confidences in [0, 1])")
    return array


def parse_person(person: dict, path: Path) -> Keypoints:
    """Convert one OpenPose ``people`` entry to the fitting layout."""
    if not isinstance(person, dict):
        raise InputError(path, "each entry of 'people' must be an object")
    body = _points(person, "pose_keypoints_2d", N_BODY, path)
    if body is None:
        raise InputError(path, "person without 'pose_keypoints_2d'")
    left = _points(person, "hand_left_keypoints_2d", N_HAND, path)
    right = _points(person, "hand_right_keypoints_2d", N_HAND, path)
    face = _points(person, "face_keypoints_2d", 70, path)
    data = np.zeros((N_KEYPOINTS, 3))
    data[BODY] = body
    if left is not None:
        data[LEFT_HAND] = left
    if right is not None:
        data[RIGHT_HAND] = right
    if face is not None:
        data[FACE] = face[FACE_FIT]
    return Keypoints(data, has_hands=left is not None or right is not None,
                     has_face=face is not None)


def parse_people(content: bytes | str, path: Path | str) -> list[Keypoints]:
    """Every person of an OpenPose JSON document (possibly none); ``path`` names it in errors."""
    try:
        data = json.loads(content.decode("utf-8") if isinstance(content, bytes) else content)
    except (ValueError, RecursionError) as exc:  # bad UTF-8 or JSON, absurd numbers or nesting
        raise InputError(path, f"not valid JSON ({exc})") from exc
    people = data.get("people") if isinstance(data, dict) else None
    if not isinstance(people, list):
        raise InputError(path, "no 'people' list")
    return [parse_person(p, path) for p in people]


def load_keypoints(path: Path) -> Keypoints:
    """Read an OpenPose JSON file and return its main person (largest total confidence)."""
    path = Path(path)
    try:
        content = path.read_bytes()
    except FileNotFoundError as exc:
        raise InputError(path, "file not found") from exc
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc})") from exc
    persons = parse_people(content, path)
    if not persons:
        raise InputError(path, "'people' is empty: nobody detected in this frame")
    best = max(persons, key=lambda k: float(k.confidence[BODY].sum()))
    if best.confidence[BODY].sum() <= 0:
        raise InputError(path, "all body keypoints have zero confidence")
    return best


def ankle_seen(conf: torch.Tensor) -> torch.Tensor:
    """(...,) whether the detector reported either ankle, from confidences (..., K) (a
    tensor or an array): a frame cut off at the knees has neither, and its legs' posture
    is a guess."""
    return (conf[..., ANKLES] > 0).any(-1)


# A thigh hangs in the image (thighs_hanging) within HANG_ANGLE degrees of world down and
# at least HANG_LENGTH times as long as the trunk: a standing thigh is about as long as
# the trunk; a seated one points toward the camera (short) or sideways.
HANG_ANGLE, HANG_LENGTH = 30.0, 0.5


def thighs_hanging(target: torch.Tensor, conf: torch.Tensor, down: torch.Tensor
                   ) -> torch.Tensor:
    """(B,) whether every thigh seen (mid-hip to a knee above HIDDEN: the hips' own
    points may be left out of the data term) hangs along ``down`` (B, 2), world down in
    the image at the mid-hip, and at least one is seen, from keypoints ``target``
    (B, K, 2) and confidences ``conf`` (B, K); the trunk is mid-hip to mid-shoulder. A
    frame cut off at the knees whose thighs hang is standing or kneeling upright."""
    shoulders = list(SHOULDERS)
    hip = target[:, MID_HIP]
    thighs = target[:, KNEES] - hip[:, None]  # (B, 2, 2)
    trunk = (target[:, shoulders].mean(1) - hip).norm(dim=-1)
    length = thighs.norm(dim=-1)
    along = (thighs * down[:, None]).sum(-1) / length.clamp_min(1e-9)
    hangs = (along > math.cos(math.radians(HANG_ANGLE))) & (length > HANG_LENGTH * trunk[:, None])
    seen = ((conf[:, KNEES] > HIDDEN) & (conf[:, [MID_HIP]] > 0)
            & (conf[:, shoulders] > 0).all(-1, keepdim=True))
    return seen.any(-1) & (hangs | ~seen).all(-1)


def toes_unseen(seen: torch.Tensor) -> torch.Tensor:
    """(..., 2) per foot of SHINS, whether neither of its toes is ``seen`` ((..., 25)
    bool, e.g. confidences over SEEN); a seen heel does not count."""
    return ~seen[..., TOES].unflatten(-1, (2, 2)).any(-1)


def cut_legs(conf: torch.Tensor) -> torch.Tensor:
    """(..., 2) per leg of SHINS, whether the detector reported its knee and nothing below
    it (ankle, toes, heel), from confidences (..., K): a leg cut off by the image's edge
    or wholly hidden below the knee, whose shin the fit has to guess."""
    return (conf[..., KNEES] > 0) & _nothing_below(conf)


def nothing_below_knees(conf: torch.Tensor) -> torch.Tensor:
    """(...,) whether the detector reports no point below either knee (ankles, toes,
    heels), from confidences (..., K): a frame cut off under the knees, as opposed to one
    leg's lower part hidden while the other's is reported."""
    return _nothing_below(conf).all(-1)


def _nothing_below(conf: torch.Tensor) -> torch.Tensor:
    """(..., 2) per leg of SHINS, whether no point below its knee is reported."""
    return (conf[..., [foot for _, foot in SHINS]] == 0).all(-1)  # feet (..., 2, 4)


def thighs_hidden(conf: torch.Tensor) -> torch.Tensor:
    """(...,) whether the detector reports neither hip nor knee above HIDDEN, from
    confidences (..., K): the thighs are behind something (a seated person's, behind a
    table, the feet seen under it), and where they point is a guess."""
    return ~(conf[..., [*HIPS, *KNEES]] > HIDDEN).any(-1)
