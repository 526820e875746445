"""SMPL-X from the user's licensed model files (``SMPLX_{NEUTRAL,MALE,FEMALE}.npz``).

Our own loader and linear blend skinning (a few dozen lines): the ``smplx`` package's code is
under the Max Planck licence, so the default install and the images stay free of it; the
model files are read from the user's folder, never fetched.

Parameters (batch first; axis-angle rotations about the rest pose's axes, parent-relative,
as in SMPL-X: x to the body's left, y up, z forward):
- ``global_orient`` (B, 3), ``transl`` (B, 3): the root (pelvis) in the fitting frame;
- ``body_pose`` (B, 21, 3): joints 1-21 (hips to wrists);
- ``hand_pose``: (B, 2 * P) PCA coefficients of the left then the right hand (P = 12 as in
  the paper), or (B, 30, 3) finger rotations when ``hand_pca`` is 0; in both cases relative
  to the model's mean hand, as SMPLify-X's ``flat_hand_mean: False`` (zero: the mean hand);
- ``betas`` (B, 10), ``expression`` (B, 10), ``jaw_pose`` (B, 3); the eyes stay at rest.
With VPoser (the user's snapshot), ``pose_embedding`` (B, 32) replaces ``body_pose``.
"""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import torch

from ..config import GENDERS
from ..errors import InputError
from ..geometry import axis_angle_to_matrix, matrix_to_axis_angle
from ..keypoints import BODY, FACE, LEFT_HAND, N_KEYPOINTS, RIGHT_HAND
from .base import BodyModel, BodyOutput, Params, VertexSubset, limit_excess
from .vposer import LATENT, VPoser

JOINTS = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "jaw", "left_eye_smplhf", "right_eye_smplhf",
    *[f"{side}_{finger}{k}" for side in ("left", "right")
      for finger in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3)],
]
BODY_JOINTS = JOINTS[1:22]
# Surface points that SMPL-X adds to its joints (the smplx package's vertex_ids), in order:
# they are joints 55-75 below.
EXTRA_VERTICES = {
    "nose": 9120, "reye": 9929, "leye": 9448, "rear": 616, "lear": 6,
    "LBigToe": 5770, "LSmallToe": 5780, "LHeel": 8846,
    "RBigToe": 8463, "RSmallToe": 8474, "RHeel": 8635,
    "lthumb": 5361, "lindex": 4933, "lmiddle": 5058, "lring": 5169, "lpinky": 5286,
    "rthumb": 8079, "rindex": 7669, "rmiddle": 7794, "rring": 7905, "rpinky": 8022,
}
# OpenPose BODY_25 and hands from SMPL-X joints (0-54) and the points above (55-75), as in
# SMPLify-X; the face keypoints are the model's 51 static landmarks.
BODY_25 = [55, 12, 17, 19, 21, 16, 18, 20, 0, 2, 5, 8, 1, 4, 7, 56, 57, 58, 59, 60, 61, 62, 63,
           64, 65]
LEFT_HAND_21 = [20, 37, 38, 39, 66, 25, 26, 27, 67, 28, 29, 30, 68, 34, 35, 36, 69, 31, 32, 33,
                70]
RIGHT_HAND_21 = [21, 52, 53, 54, 71, 40, 41, 42, 72, 43, 44, 45, 73, 49, 50, 51, 74, 46, 47, 48,
                 75]
# PROX's body_segments/*.json names for our contact parts.
SEGMENT_FILES = {"left_hand": "L_Hand", "right_hand": "R_Hand", "left_foot": "L_Leg",
                 "right_foot": "R_Leg", "back": "back", "gluteus": "gluteus",
                 "thighs": "thighs"}
def _legs(hip: float, knee: float) -> dict[str, list[float]]:
    return {"left_hip": [hip, 0.0, 0.0], "right_hip": [hip, 0.0, 0.0],
            "left_knee": [knee, 0.0, 0.0], "right_knee": [knee, 0.0, 0.0]}


# Hip flexion is -x, knee and trunk flexion +x, as for anny.
_POSTURES = {
    "standing": {},
    "sitting": _legs(-1.4, 1.4),
    "leaning": {"spine1": [0.25, 0.0, 0.0], "spine2": [0.25, 0.0, 0.0],
                "spine3": [0.25, 0.0, 0.0]},
    "kneeling": _legs(-0.2, 2.0),
    "crouching": {**_legs(-2.0, 2.3), "spine2": [0.3, 0.0, 0.0]},
    "lying": _legs(-0.2, 0.4),
}
# Limits (radians) of the joints that bend one way only; the others are free. Knees flex
# about +x; the left elbow flexes about -y, the right about +y (SMPLify's bending prior).
_LIMITS = {
    "left_knee": ((-0.1, -0.3, -0.3), (2.6, 0.3, 0.3)),
    "right_knee": ((-0.1, -0.3, -0.3), (2.6, 0.3, 0.3)),
    "left_elbow": ((-0.6, -2.6, -0.6), (0.6, 0.1, 0.6)),
    "right_elbow": ((-0.6, -0.1, -0.6), (0.6, 2.6, 0.6)),
}


# The arrays the loader uses and their shapes (None: any size).
ARRAYS = {
    "v_template": (None, 3), "f": (None, 3), "shapedirs": (None, 3, None),
    "posedirs": (None, 3, 486), "J_regressor": (55, None), "weights": (None, 55),
    "kintree_table": (2, 55), "hands_componentsl": (45, 45), "hands_componentsr": (45, 45),
    "hands_meanl": (45,), "hands_meanr": (45,), "lmk_faces_idx": (51,),
    "lmk_bary_coords": (51, 3),
}


def _shapes(data: dict[str, np.ndarray], path: Path) -> tuple[int, int]:
    """Check the arrays the loader uses; returns (vertices, shape columns)."""
    for key, shape in ARRAYS.items():
        if key not in data:
            raise InputError(path, f"'{key}' missing: not an SMPL-X model file")
        got = data[key].shape
        if len(got) != len(shape) or any(e is not None and e != g for e, g in zip(shape, got)):
            wanted = "x".join("N" if e is None else str(e) for e in shape)
            raise InputError(path, f"'{key}' has shape {got}, expected {wanted}")
    count = len(data["v_template"])
    for key, axis in (("shapedirs", 0), ("posedirs", 0), ("weights", 0), ("J_regressor", 1)):
        if data[key].shape[axis] != count:
            raise InputError(path, f"'{key}' is for {data[key].shape[axis]} vertices, the "
                                   f"template has {count}")
    if count <= max(EXTRA_VERTICES.values()) or data["f"].max() >= count:
        raise InputError(path, f"{count} vertices: too few for SMPL-X")
    parents = data["kintree_table"][0].astype(np.int64)[1:]
    if not (parents < np.arange(1, 55)).all():
        raise InputError(path, "'kintree_table' does not list parents before children")
    return count, data["shapedirs"].shape[2]


def model_file(folder: Path | str, gender: str = "neutral") -> Path:
    """``FOLDER/SMPLX_<GENDER>.npz``, with a clear error when it is not there."""
    folder = Path(folder)
    if gender not in GENDERS:
        raise InputError(folder, f"unknown gender '{gender}' (choose {', '.join(GENDERS)})")
    if not folder.is_dir():
        raise InputError(folder, "SMPL-X model folder not found (it should hold the licensed "
                                 "SMPLX_NEUTRAL.npz, SMPLX_MALE.npz, SMPLX_FEMALE.npz)")
    path = folder / f"SMPLX_{gender.upper()}.npz"
    if not path.is_file():
        raise InputError(path, "SMPL-X model file not found")
    return path


def load_model_data(path: Path) -> dict[str, np.ndarray]:
    """The arrays the loader uses (never unpickling: the files also hold pickled dicts,
    which are skipped)."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {key: npz[key] for key in ARRAYS if key in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(path, f"not a readable .npz model file ({exc})") from exc


def load_segments(folder: Path) -> dict[str, np.ndarray]:
    """PROX's ``body_segments/*.json`` ({"verts_ind": [...]}) as contact parts."""
    parts = {}
    for part, name in SEGMENT_FILES.items():
        path = Path(folder) / f"{name}.json"
        try:
            parts[part] = np.asarray(json.loads(path.read_text())["verts_ind"], dtype=np.int64)
        except FileNotFoundError as exc:
            raise InputError(path, "body segment file not found") from exc
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError(path, f"not a body segment file ({exc})") from exc
    return parts


class SMPLXBody(BodyModel):
    """SMPL-X with linear blend skinning; see the module docstring for the parameters."""

    name = "smplx"
    postures = tuple(_POSTURES)
    lying_postures = ("lying",)

    def __init__(self, data: dict[str, np.ndarray], path: Path, gender: str = "neutral",
                 hand_pca: int = 12, segments: dict[str, np.ndarray] | None = None,
                 vposer: VPoser | None = None, num_betas: int = 10,
                 num_expression: int = 10) -> None:
        super().__init__()
        count, columns = _shapes(data, path)
        if not 0 <= hand_pca <= 45:
            raise InputError(path, f"hand_pca must be 0 (full finger rotations) to 45, "
                                   f"got {hand_pca}")
        # Files with 400 columns hold 300 shape then 100 expression components; older
        # ones 10 + 10.
        expression_at = 300 if columns >= 400 else 10
        if columns < expression_at + num_expression:
            raise InputError(path, f"'shapedirs' has {columns} components, too few for "
                                   f"{num_betas} betas and {num_expression} expressions")
        f32 = lambda a: torch.tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
        self.gender, self.hand_pca, self.source = gender, hand_pca, str(path)
        self.vposer = vposer
        self.register_buffer("v_template", f32(data["v_template"]))
        dirs = data["shapedirs"]
        self.register_buffer("shapedirs", f32(np.concatenate(
            [dirs[..., :num_betas], dirs[..., expression_at:expression_at + num_expression]],
            -1)))
        self.register_buffer("posedirs", f32(data["posedirs"].reshape(count * 3, 486).T))
        self.register_buffer("J_regressor", f32(data["J_regressor"]))
        self.register_buffer("skin_weights", f32(data["weights"]))
        parents = data["kintree_table"][0].astype(np.int64)
        parents[0] = -1
        self.parents = parents.tolist()
        self.faces = torch.tensor(data["f"].astype(np.int64))
        self.register_buffer("hand_basis", torch.stack(
            [f32(data[f"hands_components{s}"])[:hand_pca] for s in "lr"]))
        self.register_buffer("hand_mean", torch.stack([f32(data["hands_meanl"]),
                                                       f32(data["hands_meanr"])]))
        self.register_buffer("landmark_faces", self.faces[torch.tensor(
            data["lmk_faces_idx"].astype(np.int64))])
        self.register_buffer("landmark_bary", f32(data["lmk_bary_coords"]))
        self.register_buffer("extra_vertices", torch.tensor(list(EXTRA_VERTICES.values())))
        self.num_betas, self.num_expression = num_betas, num_expression
        lo, hi = np.full((21, 3), -np.pi), np.full((21, 3), np.pi)
        for joint, (low, high) in _LIMITS.items():
            lo[BODY_JOINTS.index(joint)], hi[BODY_JOINTS.index(joint)] = low, high
        self.register_buffer("limit_lo", f32(lo))
        self.register_buffer("limit_hi", f32(hi))
        self._setup_static_geometry(segments)

    @classmethod
    def load(cls, folder: Path | str, gender: str = "neutral", hand_pca: int = 12,
             segments: Path | str | None = None, vposer: Path | str | None = None
             ) -> SMPLXBody:
        """Load ``FOLDER/SMPLX_<GENDER>.npz``; ``segments`` is PROX's body_segments folder,
        ``vposer`` a VPoser v1.0 snapshot (or its folder)."""
        path = model_file(folder, gender)
        return cls(load_model_data(path), path, gender, hand_pca,
                   load_segments(Path(segments)) if segments else None,
                   VPoser.load(vposer) if vposer else None)

    # ----------------------------------------------------------------- static geometry
    def _setup_static_geometry(self, segments: dict[str, np.ndarray] | None) -> None:
        """Keypoint regressor, parts, contact sets and collision spheres at the mean shape."""
        count = len(self.v_template)
        rest_joints = self.J_regressor @ self.v_template
        weights = torch.zeros(N_KEYPOINTS, count)
        for k, joint in enumerate(BODY_25):
            if joint < 55:
                weights[k] = self.J_regressor[joint]
            else:
                weights[k, self.extra_vertices[joint - 55]] = 1.0
        self.register_buffer("keypoint_weights", weights[BODY])

        dominant = self.skin_weights.argmax(1).numpy()
        names = np.asarray(JOINTS)[dominant]
        parts = np.array(["torso"] * count, dtype=object)
        for side in ("left", "right"):
            for joints, part in (((f"{side}_hip",), "thigh"), ((f"{side}_knee",), "shin"),
                                 ((f"{side}_ankle", f"{side}_foot"), "foot"),
                                 ((f"{side}_shoulder",), "upper_arm"),
                                 ((f"{side}_elbow",), "forearm")):
                parts[np.isin(names, joints)] = f"{side}_{part}"
            wrist = JOINTS.index(f"{side}_wrist")
            fingers = [j for j, name in enumerate(JOINTS) if name.startswith(f"{side}_")
                       and name.rstrip("123") in (f"{side}_{f}" for f in
                                                  ("index", "middle", "pinky", "ring", "thumb"))]
            parts[np.isin(dominant, [wrist, *fingers])] = f"{side}_hand"
        parts[np.isin(names, ("head", "jaw", "neck"))] = "head"
        main = ~np.isin(names, ("left_eye_smplhf", "right_eye_smplhf"))  # not the eyeballs
        parts[~main] = "eyes"
        self.vertex_parts = parts.tolist()
        self.scene_vertices = torch.from_numpy(main)

        if segments is None:
            segments = self._derived_segments(parts, rest_joints, main)
        for part, ids in segments.items():
            if len(ids) and (ids.min() < 0 or ids.max() >= count):
                raise InputError(f"body_segments/{SEGMENT_FILES[part]}.json",
                                 f"vertex ids outside the model's {count} vertices")
        self.contact_parts = {k: torch.from_numpy(np.asarray(v, dtype=np.int64))
                              for k, v in segments.items()}
        self._setup_spheres(rest_joints, dominant)

    def _derived_segments(self, parts: np.ndarray, joints: torch.Tensor, main: np.ndarray
                          ) -> dict[str, np.ndarray]:
        """Contact parts from the rest mesh when PROX's body_segments are not given."""
        from ..geometry import vertex_normals

        v = self.v_template
        n = vertex_normals(v[None], self.faces)[0]
        y, ny, nz = v[:, 1].numpy(), n[:, 1].numpy(), n[:, 2].numpy()
        hip_y = float(joints[0, 1])
        knee_y = float(joints[4, 1])
        spine = np.isin(parts, ["torso"])
        parts_of = lambda name: parts == name  # noqa: E731
        sets = {
            "left_hand": parts_of("left_hand"), "right_hand": parts_of("right_hand"),
            "left_foot": parts_of("left_foot") & (ny < -0.5),
            "right_foot": parts_of("right_foot") & (ny < -0.5),
            "back": spine & (nz < -0.6) & (y > hip_y + 0.12),
            "gluteus": (nz < -0.4) & (y < hip_y + 0.08) & (y > hip_y - 0.16)
            & np.isin(parts, ["torso", "left_thigh", "right_thigh"]),
            "thighs": np.isin(parts, ["left_thigh", "right_thigh"]) & (nz < -0.5)
            & (y < hip_y - 0.16) & (y > knee_y + 0.08),
        }
        return {k: np.flatnonzero(m & main) for k, m in sets.items()}

    def _setup_spheres(self, joints: torch.Tensor, dominant: np.ndarray) -> None:
        """Spheres inside arms, legs and torso (rest pose, attached to a joint); pairs
        that are apart at rest may not meet (the self-penetration term)."""
        centres, radii, owner, groups = [], [], [], []
        v = self.v_template
        segments = [("arm", 16, 18, 3), ("arm", 18, 20, 3), ("leg", 1, 4, 4), ("leg", 4, 7, 4)]
        for group, a, b, count in segments + [(g, a + 1, b + 1, c) for g, a, b, c in segments]:
            side = "L" if JOINTS[a].startswith("left") else "R"
            head, tail = joints[a], joints[b]
            near = torch.from_numpy(dominant == a)
            axis = (tail - head) / (tail - head).norm()
            for t in (np.arange(count) + 0.5) / count:
                c = head + (tail - head) * float(t)
                offset = v[near] - c
                radial = (offset - (offset @ axis)[:, None] * axis).norm(dim=1)
                radii.append(float(radial.median()) * 0.85 if near.any() else 0.03)
                centres.append(c)
                owner.append(a)
                groups.append(f"{group}.{side}")
        for joint in (3, 6, 9):  # the spine: left, centre, right
            near = torch.from_numpy(dominant == joint)
            width = float(v[near, 0].max() - v[near, 0].min()) / 2 if near.any() else 0.1
            r = width * 0.6
            for dx in (-(width - r), 0.0, width - r):
                centres.append(joints[joint] + torch.tensor([dx, 0.0, 0.0]))
                radii.append(r)
                owner.append(joint)
                groups.append("torso")
        centres_t = torch.stack(centres)
        self.register_buffer("sphere_rest", centres_t)
        self.register_buffer("sphere_radius", torch.tensor(radii))
        self.register_buffer("sphere_joint", torch.tensor(owner))
        allowed = {("arm.L", "torso"), ("arm.R", "torso"), ("leg.L", "leg.R")}
        dist = torch.cdist(centres_t, centres_t)
        rad = self.sphere_radius[:, None] + self.sphere_radius[None]
        self.collision_pairs = torch.tensor(
            [(i, j) for i in range(len(groups)) for j in range(i + 1, len(groups))
             if tuple(sorted((groups[i], groups[j]))) in allowed
             and dist[i, j] > rad[i, j] + 0.02], dtype=torch.long)

    # ----------------------------------------------------------------- parameters
    def init_params(self, batch_size: int, posture: str = "standing") -> Params:
        zeros = lambda *shape: torch.zeros(batch_size, *shape)  # noqa: E731
        params = {
            "global_orient": zeros(3), "transl": zeros(3), "body_pose": zeros(21, 3),
            "hand_pose": zeros(2 * self.hand_pca) if self.hand_pca else zeros(30, 3),
            "betas": zeros(self.num_betas), "expression": zeros(self.num_expression),
            "jaw_pose": zeros(3),
        }
        for joint, value in _POSTURES[posture].items():
            params["body_pose"][:, BODY_JOINTS.index(joint)] = torch.tensor(value)
        if self.vposer is not None:  # the standing start is the prior's mean, as SMPLify-X
            pose = params.pop("body_pose")
            with torch.no_grad():
                params["pose_embedding"] = (self.vposer.encode(pose) if posture != "standing"
                                            else zeros(LATENT))
        return params

    def shape_group(self) -> list[str]:
        return ["betas"]

    def pose_group(self) -> list[str]:
        return ["pose_embedding"] if self.vposer is not None else ["body_pose"]

    def body_pose(self, params: Params) -> torch.Tensor:
        """(B, 21, 3) axis-angle of the body joints (decoded when VPoser is used)."""
        if self.vposer is None:
            return params["body_pose"]
        return matrix_to_axis_angle(self.vposer.decode(params["pose_embedding"]))

    def root_pivot(self, params: Params) -> torch.Tensor:
        """The pelvis joint of the shaped rest body."""
        coeffs = torch.cat([params["betas"], params["expression"]], 1)
        shaped = self.v_template + torch.einsum("bl,vdl->bvd", coeffs, self.shapedirs)
        return torch.einsum("v,bvd->bd", self.J_regressor[0], shaped)

    def up_axis(self) -> torch.Tensor:
        return torch.tensor([0.0, 1.0, 0.0])

    def forward_axis(self) -> torch.Tensor:
        return torch.tensor([0.0, 0.0, 1.0])

    def _hand_offsets(self, hand: torch.Tensor) -> torch.Tensor:
        """(B, 2, 45) finger rotations relative to the mean hand, of ``hand_pose`` (decoded
        from its PCA coefficients when fitted with PCA)."""
        if self.hand_pca:
            hand = torch.einsum("bsp,spk->bsk", hand.view(-1, 2, self.hand_pca),
                                self.hand_basis)
        return hand.reshape(-1, 2, 45)

    def finger_pose(self, params: Params) -> torch.Tensor:
        """(B, 30, 3) axis-angle of the left then the right fingers: the mean hand plus
        the ``hand_pose`` offsets."""
        return (self._hand_offsets(params["hand_pose"]) + self.hand_mean).reshape(-1, 30, 3)

    # ----------------------------------------------------------------- forward
    def forward(self, params: Params, vertices: bool | VertexSubset = True,
                spheres: bool = True) -> BodyOutput:
        """Pose the body; the keypoints need the mesh (face landmarks), so it is always
        posed (a subset is picked from it)."""
        subset = vertices.ids if isinstance(vertices, VertexSubset) else None
        batch = params["transl"].shape[0]
        coeffs = torch.cat([params["betas"], params["expression"]], 1)
        shaped = self.v_template + torch.einsum("bl,vdl->bvd", coeffs, self.shapedirs)
        joints = torch.einsum("jv,bvd->bjd", self.J_regressor, shaped)
        eyes = params["jaw_pose"].new_zeros(batch, 2, 3)
        pose = torch.cat([params["global_orient"][:, None], self.body_pose(params),
                          params["jaw_pose"][:, None], eyes, self.finger_pose(params)], 1)
        rotations = axis_angle_to_matrix(pose)  # (B, 55, 3, 3)
        eye = torch.eye(3, dtype=rotations.dtype)
        posed = shaped + ((rotations[:, 1:] - eye).reshape(batch, -1) @ self.posedirs).view(
            batch, -1, 3)

        world = []  # each joint's rigid transform, root first (parents precede children)
        for j, parent in enumerate(self.parents):
            local = torch.cat([rotations[:, j], (joints[:, j] - (joints[:, parent] if j
                              else 0))[..., None]], 2)
            local = torch.cat([local, local.new_tensor([0, 0, 0, 1]).expand(batch, 1, 4)], 1)
            world.append(local if j == 0 else world[parent] @ local)
        world_t = torch.stack(world, 1)  # (B, 55, 4, 4)
        posed_joints = world_t[..., :3, 3]
        skinning = world_t.clone()
        skinning[..., :3, 3] = posed_joints - torch.einsum("bjxy,bjy->bjx",
                                                           world_t[..., :3, :3], joints)
        blended = torch.einsum("vj,bjxy->bvxy", self.skin_weights, skinning)
        transl = params["transl"][:, None]
        vertices = torch.einsum("bvxy,bvy->bvx", blended[..., :3, :3], posed) \
            + blended[..., :3, 3] + transl

        points = torch.cat([posed_joints + transl, vertices[:, self.extra_vertices]], 1)
        keypoints = vertices.new_zeros(batch, N_KEYPOINTS, 3)
        keypoints[:, BODY] = points[:, BODY_25]
        keypoints[:, LEFT_HAND] = points[:, LEFT_HAND_21]
        keypoints[:, RIGHT_HAND] = points[:, RIGHT_HAND_21]
        triangles = vertices[:, self.landmark_faces]  # (B, 51, 3, 3)
        keypoints[:, FACE] = torch.einsum("blkd,lk->bld", triangles, self.landmark_bary)
        out = BodyOutput(vertices=vertices if subset is None else vertices[:, subset],
                         keypoints=keypoints)
        if spheres:
            carry = skinning[:, self.sphere_joint]
            centres = torch.einsum("bsxy,sy->bsx", carry[..., :3, :3], self.sphere_rest) \
                + carry[..., :3, 3] + transl
            out.spheres = torch.cat([centres, self.sphere_radius.expand(batch, -1)[..., None]],
                                    -1)
        return out

    @property
    def keypoint_mask(self) -> torch.Tensor:
        return torch.ones(N_KEYPOINTS, dtype=torch.bool)

    # ----------------------------------------------------------------- priors
    def pose_prior(self, params: Params) -> torch.Tensor:
        if self.vposer is not None:
            return (params["pose_embedding"] ** 2).sum(1)
        return (params["body_pose"] ** 2).sum((1, 2))

    def joint_limits(self, params: Params) -> torch.Tensor:
        return limit_excess(self.body_pose(params), self.limit_lo, self.limit_hi)

    def bending_prior(self, params: Params) -> torch.Tensor:
        pose = self.body_pose(params)
        j = BODY_JOINTS.index
        flexion = torch.stack([-pose[:, j("left_elbow"), 1], pose[:, j("right_elbow"), 1],
                               pose[:, j("left_knee"), 0], pose[:, j("right_knee"), 0]], 1)
        return torch.exp(-flexion).sum(1)

    def hand_prior(self, params: Params) -> torch.Tensor:
        """Finger articulation, plus the (unfitted) jaw and expression kept near rest."""
        return ((params["hand_pose"] ** 2).flatten(1).sum(1) + (params["jaw_pose"] ** 2).sum(1)
                + (params["expression"] ** 2).sum(1))

    def shape_prior(self, params: Params) -> torch.Tensor:
        return (params["betas"] ** 2).sum(1)

    # ----------------------------------------------------------------- export
    def export(self, params: Params, index: int) -> dict:
        value = lambda name: params[name][index].detach().tolist()  # noqa: E731
        fingers = self._hand_offsets(params["hand_pose"][index:index + 1])[0].reshape(30, 3)
        body_pose = self.body_pose(params)[index].detach().tolist()
        return {
            "model": "smplx", "gender": self.gender, "model_file": self.source,
            "global_orient": value("global_orient"), "transl": value("transl"),
            "body_pose": dict(zip(BODY_JOINTS, body_pose)),
            "pose_embedding": value("pose_embedding") if self.vposer is not None else None,
            "left_hand_pose": fingers[:15].tolist(), "right_hand_pose": fingers[15:].tolist(),
            "hand_pca": value("hand_pose") if self.hand_pca else None,
            "hand_convention": {  # SMPLify-X's: smplx.create(..., flat_hand_mean=False)
                "poses": "left/right_hand_pose here and in 000.pkl are relative to the mean hand",
                "flat_hand_mean": False, "use_pca": bool(self.hand_pca),
                "num_pca_comps": self.hand_pca or None,
                "pkl_hand_values": self.hand_pca or 45},
            "betas": value("betas"), "expression": value("expression"),
            "jaw_pose": value("jaw_pose"), "pose_parameterization": "SMPL-X axis-angle",
        }

    def prox_result(self, params: Params, index: int) -> dict[str, np.ndarray]:
        """The arrays PROX and SMPLify-X write to ``results/<frame>/000.pkl`` (camera at
        the origin, decoded axis-angle ``body_pose``; hands as PCA coefficients when fitted
        with PCA, like theirs, else the 45 finger rotations per hand; both relative to the
        mean hand, to be read with ``flat_hand_mean=False``)."""
        def row(name: str) -> np.ndarray:
            return params[name][index:index + 1].detach().numpy().reshape(1, -1)

        body_pose = self.body_pose(params)[index:index + 1].detach().numpy().reshape(1, -1)

        hands = row("hand_pose")
        half = hands.shape[1] // 2
        return {
            "camera_rotation": np.eye(3, dtype=np.float32)[None],
            "camera_translation": np.zeros((1, 3), dtype=np.float32),
            "betas": row("betas"), "global_orient": row("global_orient"),
            "transl": row("transl"),
            "left_hand_pose": hands[:, :half], "right_hand_pose": hands[:, half:],
            "jaw_pose": row("jaw_pose"), "leye_pose": np.zeros((1, 3), dtype=np.float32),
            "reye_pose": np.zeros((1, 3), dtype=np.float32), "expression": row("expression"),
            "body_pose": body_pose,
            **({"pose_embedding": row("pose_embedding")} if self.vposer is not None else {}),
        }

