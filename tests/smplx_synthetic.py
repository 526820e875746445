"""A synthetic SMPL-X model file for tests: a random capsule humanoid in the exact ``.npz`` layout.

No SMPL-X data is used: the body is built from closed capsule meshes, one per bone, in the
SMPL-X rest frame (metres, y up, z forward, x to the body's left, T-pose). The pelvis is at
(0, -0.35, 0), the soles at y = -1.23 and the top of the head at y = 0.45 (1.68 m).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

NUM_VERTICES = 10475
NUM_JOINTS = 55
FINGERS = ("index", "middle", "pinky", "ring", "thumb")

JOINT_NAMES: list[str] = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "jaw", "left_eye_smplhf", "right_eye_smplhf",
    *[f"{side}_{finger}{k}" for side in ("left", "right") for finger in FINGERS for k in (1, 2, 3)],
]
SMPLX_PARENTS: list[int] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    *[p for wrist, first in ((20, 25), (21, 40)) for f in range(5)
      for p in (wrist, first + 3 * f, first + 3 * f + 1)],
]
EXTRA_VERTICES: dict[str, int] = {
    "nose": 9120, "reye": 9929, "leye": 9448, "rear": 616, "lear": 6,
    "LBigToe": 5770, "LSmallToe": 5780, "LHeel": 8846,
    "RBigToe": 8463, "RSmallToe": 8474, "RHeel": 8635,
    "lthumb": 5361, "lindex": 4933, "lmiddle": 5058, "lring": 5169, "lpinky": 5286,
    "rthumb": 8079, "rindex": 7669, "rmiddle": 7794, "rring": 7905, "rpinky": 8022,
}

_CENTRE = {"pelvis": (0.0, -0.35, 0.0), "spine1": (0.0, -0.25, 0.0), "spine2": (0.0, -0.1, 0.0),
           "spine3": (0.0, 0.0, 0.0), "neck": (0.0, 0.15, 0.0), "head": (0.0, 0.25, 0.0),
           "jaw": (0.0, 0.27, 0.03)}
_LEFT = {"hip": (0.06, -0.44, 0.0), "knee": (0.09, -0.75, 0.0), "ankle": (0.09, -1.15, 0.0),
         "foot": (0.09, -1.2, 0.1), "collar": (0.07, 0.1, 0.0), "shoulder": (0.18, 0.1, 0.0),
         "elbow": (0.45, 0.1, 0.0), "wrist": (0.7, 0.1, 0.0), "eye_smplhf": (0.03, 0.34, 0.06)}
# Left hand, from the wrist: the three joints of each finger, then its tip.
_FINGER_POINTS = {
    "index": [(0.085, 0.0, 0.025), (0.12, 0.0, 0.025), (0.145, 0.0, 0.025), (0.165, 0.0, 0.025)],
    "middle": [(0.09, 0.0, 0.007), (0.13, 0.0, 0.007), (0.157, 0.0, 0.007), (0.18, 0.0, 0.007)],
    "pinky": [(0.075, 0.0, -0.03), (0.103, 0.0, -0.03), (0.122, 0.0, -0.03), (0.14, 0.0, -0.03)],
    "ring": [(0.085, 0.0, -0.012), (0.122, 0.0, -0.012), (0.147, 0.0, -0.012),
             (0.168, 0.0, -0.012)],
    "thumb": [(0.025, -0.012, 0.03), (0.05, -0.015, 0.055), (0.075, -0.015, 0.07),
              (0.095, -0.015, 0.08)],
}


@dataclass(frozen=True)
class _Part:
    """One closed capsule from a to b, skinned to `joint` (blended into `blend` near b)."""

    joint: int
    a: np.ndarray
    b: np.ndarray
    radii: tuple[float, float]  # cross-section semi-axes
    caps: tuple[float, float]  # how far the surface reaches beyond a and beyond b
    res: tuple[int, int, int]  # rings per cap, inner cylinder rings, vertices per ring
    blend: int | None = None


def _mirror(p: tuple[float, float, float], side: str) -> np.ndarray:
    return np.array(p) * (1.0 if side == "left" else -1.0, 1.0, 1.0)


def joint_positions() -> np.ndarray:
    """The (55, 3) rest joints of the synthetic model (what J_regressor @ v_template gives)."""
    pos = {name: np.array(p) for name, p in _CENTRE.items()}
    for side in ("left", "right"):
        pos.update({f"{side}_{k}": _mirror(p, side) for k, p in _LEFT.items()})
        wrist = pos[f"{side}_wrist"]
        for finger, points in _FINGER_POINTS.items():
            pos.update({f"{side}_{finger}{k + 1}": wrist + _mirror(points[k], side)
                        for k in range(3)})
    return np.stack([pos[name] for name in JOINT_NAMES])


def _parts(joints: np.ndarray) -> dict[str, _Part]:
    """The body's capsules, named after the joint that each one starts at (and is skinned to)."""
    ix = {name: i for i, name in enumerate(JOINT_NAMES)}

    def bone(name: str, child: str, radii: tuple[float, float], caps: tuple[float, float],
             res: tuple[int, int, int]) -> _Part:
        return _Part(ix[name], joints[ix[name]], joints[ix[child]], radii, caps, res, ix[child])

    def leaf(name: str, b: np.ndarray, radii: tuple[float, float], caps: tuple[float, float],
             res: tuple[int, int, int], a: np.ndarray | None = None) -> _Part:
        return _Part(ix[name], joints[ix[name]] if a is None else a, b, radii, caps, res)

    head = joints[ix["head"]]
    parts = {
        "pelvis": bone("pelvis", "spine1", (0.15, 0.11), (0.1, 0.03), (5, 6, 40)),
        "spine1": bone("spine1", "spine2", (0.14, 0.1), (0.03, 0.03), (4, 6, 40)),
        "spine2": bone("spine2", "spine3", (0.145, 0.1), (0.03, 0.03), (4, 6, 40)),
        "spine3": bone("spine3", "neck", (0.17, 0.11), (0.03, 0.04), (5, 8, 40)),
        "neck": bone("neck", "head", (0.055, 0.055), (0.02, 0.02), (3, 6, 24)),
        "head": leaf("head", head + (0.0, 0.13, 0.0), (0.075, 0.09), (0.05, 0.07), (8, 8, 36)),
        "jaw": leaf("jaw", np.array([0.0, 0.235, 0.075]), (0.035, 0.02), (0.01, 0.02), (3, 2, 20)),
    }
    for side in ("left", "right"):
        s = side + "_"
        x = joints[ix[s + "ankle"], 0]
        eye = joints[ix[s + "eye_smplhf"]]
        parts |= {
            s + "eye_smplhf": leaf(s + "eye_smplhf", eye + (0.0, 0.0, 0.002), (0.012, 0.012),
                                   (0.012, 0.012), (3, 0, 12)),
            s + "hip": bone(s + "hip", s + "knee", (0.07, 0.075), (0.06, 0.03), (4, 10, 28)),
            s + "knee": bone(s + "knee", s + "ankle", (0.05, 0.055), (0.03, 0.05), (4, 10, 24)),
            # the ankle's part is the foot's body, from behind the heel to the ball of the foot
            s + "ankle": _Part(ix[s + "ankle"], np.array([x, -1.19, -0.02]),
                               joints[ix[s + "foot"]], (0.045, 0.03), (0.045, 0.02), (4, 4, 24),
                               ix[s + "foot"]),
            s + "foot": leaf(s + "foot", np.array([x, -1.21, 0.15]), (0.045, 0.022), (0.01, 0.03),
                             (3, 2, 20)),
            s + "collar": bone(s + "collar", s + "shoulder", (0.05, 0.05), (0.02, 0.03),
                               (3, 3, 20)),
            s + "shoulder": bone(s + "shoulder", s + "elbow", (0.05, 0.05), (0.04, 0.03),
                                 (4, 8, 24)),
            s + "elbow": bone(s + "elbow", s + "wrist", (0.04, 0.04), (0.02, 0.02), (4, 8, 20)),
            s + "wrist": bone(s + "wrist", s + "middle1", (0.016, 0.042), (0.02, 0.01), (3, 3, 20)),
        }
        wrist = joints[ix[s + "wrist"]]
        for finger, points in _FINGER_POINTS.items():
            for k in (1, 2):
                r = 0.01 - 0.001 * k
                parts[f"{s}{finger}{k}"] = bone(f"{s}{finger}{k}", f"{s}{finger}{k + 1}", (r, r),
                                                (r, r), (2, 1, 8))
            parts[f"{s}{finger}3"] = leaf(f"{s}{finger}3", wrist + _mirror(points[3], side),
                                          (0.007, 0.007), (0.007, 0.007), (2, 1, 8))
    return parts


def _frame(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors u, v with (u, v, d) right-handed: u follows x, or y for bones along x."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ref - (ref @ d) * d
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def _capsule(part: _Part) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, outward triangles, axial fraction (0 at a, 1 at b), and the rings at a and at b."""
    n_cap, n_cyl, n_seg = part.res
    axis = part.b - part.a
    length = float(np.linalg.norm(axis))
    d = axis / length
    u, v = _frame(d)
    cap_a, cap_b = part.caps
    t = 0.5 * np.pi * np.arange(n_cap + 1) / n_cap
    axial = np.concatenate([-cap_a * np.cos(t[1:]), length * np.arange(1, n_cyl + 1) / (n_cyl + 1),
                            length + cap_b * np.sin(t[:-1])])
    radial = np.concatenate([np.sin(t[1:]), np.ones(n_cyl), np.cos(t[:-1])])
    phi = 2.0 * np.pi * np.arange(n_seg) / n_seg
    section = part.radii[0] * np.cos(phi)[:, None] * u + part.radii[1] * np.sin(phi)[:, None] * v
    rings = (part.a + axial[:, None, None] * d + radial[:, None, None] * section).reshape(-1, 3)
    verts = np.concatenate([[part.a - cap_a * d], rings, [part.b + cap_b * d]])
    along = np.concatenate([[-cap_a], np.repeat(axial, n_seg), [length + cap_b]]) / length

    n_rings = len(axial)
    i = np.arange(n_seg)
    j = (i + 1) % n_seg
    quads = [np.stack([1 + r * n_seg + i, 1 + r * n_seg + j, 1 + (r + 1) * n_seg + i,
                       1 + (r + 1) * n_seg + j], axis=1) for r in range(n_rings - 1)]
    q = np.concatenate(quads)
    last = len(verts) - 1
    faces = np.concatenate([
        np.stack([np.zeros(n_seg, int), 1 + j, 1 + i], axis=1),
        q[:, [0, 1, 2]], q[:, [1, 3, 2]],
        np.stack([np.full(n_seg, last), 1 + (n_rings - 1) * n_seg + i,
                  1 + (n_rings - 1) * n_seg + j], axis=1),
    ])
    ring_a = 1 + (n_cap - 1) * n_seg + i
    ring_b = 1 + (n_cap + n_cyl) * n_seg + i
    return verts, faces, along, ring_a, ring_b


def _special_targets(joints: np.ndarray,
                     parts: dict[str, _Part]) -> dict[str, tuple[str, np.ndarray]]:
    """For each extra vertex: the part it lies on and the spot it should be nearest to."""
    head = joints[JOINT_NAMES.index("head")]
    out = {
        "nose": ("head", head + (0.0, 0.07, 0.095)),
        "reye": ("head", head + (-0.03, 0.09, 0.085)),
        "leye": ("head", head + (0.03, 0.09, 0.085)),
        "rear": ("head", head + (-0.075, 0.07, 0.0)),
        "lear": ("head", head + (0.075, 0.07, 0.0)),
    }
    for side, tag in (("left", "L"), ("right", "R")):
        x = joints[JOINT_NAMES.index(f"{side}_ankle"), 0]
        inward = -np.sign(x)
        out[tag + "BigToe"] = (f"{side}_foot", np.array([x + 0.025 * inward, -1.21, 0.165]))
        out[tag + "SmallToe"] = (f"{side}_foot", np.array([x - 0.035 * inward, -1.21, 0.13]))
        out[tag + "Heel"] = (f"{side}_ankle", np.array([x, -1.205, -0.065]))
        for finger in FINGERS:
            part = parts[f"{side}_{finger}3"]
            tip = part.b + part.caps[1] * (part.b - part.a) / np.linalg.norm(part.b - part.a)
            out[f"{tag.lower()}{finger}"] = (f"{side}_{finger}3", tip)
    return out


def write_smplx_model(folder: Path, gender: str = "NEUTRAL", num_betas: int = 10,
                      num_expression: int = 10, seed: int = 0) -> Path:
    """Write folder/SMPLX_{GENDER}.npz (a synthetic humanoid in the SMPL-X format); return its path.

    The geometry is the same for every gender and seed; the seed draws the blend shapes, the
    pose correctives, the hand PCA bases, the landmarks and which torso faces get split.
    """
    rng = np.random.default_rng(seed)
    joints = joint_positions()
    parts = _parts(joints)

    verts, faces, weights, span, rings = [], [], [], {}, {}
    count = 0
    for name, part in parts.items():
        pv, pf, along, ring_a, ring_b = _capsule(part)
        w = np.zeros((len(pv), NUM_JOINTS))
        if part.blend is None:
            w[:, part.joint] = 1.0
        else:
            mix = 0.5 * np.clip((along - 0.75) / 0.25, 0.0, 1.0)
            w[:, part.joint], w[:, part.blend] = 1.0 - mix, mix
        verts.append(pv)
        faces.append(pf + count)
        weights.append(w)
        span[name] = (count, count + len(pv))
        rings[name] = (ring_a + count, ring_b + count)
        count += len(pv)
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    w = np.concatenate(weights)

    # Pad to V vertices by splitting torso triangles at their centroids (the surface stays closed).
    pad = NUM_VERTICES - len(v)
    torso = np.flatnonzero(np.all((f >= span["spine2"][0]) & (f < span["spine3"][1]), axis=1))
    assert 0 <= pad <= len(torso), pad
    split = np.sort(rng.choice(torso, pad, replace=False))
    tri = f[split]
    centre = len(v) + np.arange(pad)
    v = np.concatenate([v, v[tri].mean(axis=1)])
    w = np.concatenate([w, w[tri].mean(axis=1)])
    f[split] = np.stack([tri[:, 0], tri[:, 1], centre], axis=1)
    f = np.concatenate([f, np.stack([tri[:, 1], tri[:, 2], centre], axis=1),
                        np.stack([tri[:, 2], tri[:, 0], centre], axis=1)])

    # Renumber so that each extra vertex id is the vertex nearest its spot on its part.
    targets = _special_targets(joints, parts)
    chosen: list[int] = []
    for part_name, target in (targets[name] for name in EXTRA_VERTICES):
        lo, hi = span[part_name]
        dist = np.linalg.norm(v[lo:hi] - target, axis=1)
        dist[[k - lo for k in chosen if lo <= k < hi]] = np.inf
        chosen.append(lo + int(np.argmin(dist)))
    ids = np.array(list(EXTRA_VERTICES.values()))
    perm = np.empty(NUM_VERTICES, dtype=np.int64)  # new index -> old index
    perm[ids] = chosen
    perm[np.setdiff1d(np.arange(NUM_VERTICES), ids)] = np.setdiff1d(np.arange(NUM_VERTICES), chosen)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(NUM_VERTICES)

    j_regressor = np.zeros((NUM_JOINTS, NUM_VERTICES))
    for j, name in enumerate(JOINT_NAMES):
        # each joint is the centre of the ring at the start of its part (the ankles: at the
        # end of the shin, since their part is the foot)
        ring = rings[JOINT_NAMES[SMPLX_PARENTS[j]]][1] if name.endswith("ankle") else rings[name][0]
        j_regressor[j, inv[ring]] = 1.0 / len(ring)

    template = v[perm]
    skin = w[perm]
    tris = inv[f]

    # Landmarks on the face: head triangles in front of the head.
    lo, hi = span["head"]
    head_tris = np.all((f >= lo) & (f < hi), axis=1)
    front = np.flatnonzero(head_tris & (v[f].mean(axis=1)[:, 2] > joints[15, 2] + 0.045))
    bary_static = rng.dirichlet(np.ones(3), 51)
    bary_dynamic = rng.dirichlet(np.ones(3), (79, 17))

    # Blend shapes: beta 0 scales about the pelvis (3 % per unit); the others are random linear
    # fields with 1 mm noise; expressions are random fields on the head's vertices only.
    rel = template - joints[0]
    shapedirs = np.empty((NUM_VERTICES, 3, num_betas + num_expression))
    for k in range(num_betas):
        shapedirs[:, :, k] = 0.03 * rel if k == 0 else (
            rel @ rng.normal(0.0, 0.01 / np.sqrt(k), (3, 3)).T + rng.normal(0.0, 1e-3, rel.shape))
    on_head = np.isin(skin.argmax(axis=1), [15, 22, 23, 24])[:, None]
    rel_head = template - joints[15]
    for k in range(num_expression):
        field = rel_head @ rng.normal(0.0, 0.03, (3, 3)).T + rng.normal(0.0, 5e-4, rel.shape)
        shapedirs[:, :, num_betas + k] = on_head * field

    parents = np.array(SMPLX_PARENTS)
    hands = {}
    for side in "lr":
        hands[f"hands_components{side}"] = np.linalg.qr(rng.standard_normal((45, 45)))[0]
        hands[f"hands_mean{side}"] = 0.1 * rng.standard_normal(45)

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"SMPLX_{gender.upper()}.npz"
    np.savez(
        path,
        v_template=template,
        f=tris.astype(np.uint32),
        shapedirs=shapedirs,
        posedirs=1e-3 * rng.standard_normal((NUM_VERTICES, 3, 9 * (NUM_JOINTS - 1))),
        J_regressor=j_regressor,
        weights=skin,
        kintree_table=np.stack([np.where(parents < 0, 2**32 - 1, parents),
                                np.arange(NUM_JOINTS)]).astype(np.uint32),
        **hands,
        lmk_faces_idx=rng.choice(front, 51, replace=False).astype(np.int64),
        lmk_bary_coords=bary_static,
        dynamic_lmk_faces_idx=rng.choice(front, (79, 17)).astype(np.int64),
        dynamic_lmk_bary_coords=bary_dynamic,
    )
    return path
