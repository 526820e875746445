"""The free default body model: anny 0.6.2 (Apache-2.0, MakeHuman data CC0).

Parameters (all leaf tensors, batch first):
- ``global_orient`` (B, 3) axis-angle and ``transl`` (B, 3): the root (pelvis) pose in the
  fitting frame.
- ``body_pose`` (B, len(BODY_BONES), 3): axis-angle in each bone's own frame
  (``local-bone``: x = flexion for knees, elbows and spine, y = twist along the bone).
- ``hand_pose`` (B, len(FINGER_BONES), 3): the same for the finger bones.
- ``shape`` (B, 6): logits of the phenotype (gender, age, muscle, weight, height,
  proportions), which anny clamps to [0, 1] with zero gradient, hence the sigmoid.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import roma
import torch

from .. import assets
from ..geometry import vertex_normals
from ..keypoints import BODY, LEFT_HAND, N_KEYPOINTS, RIGHT_HAND
from ..with_gradient import with_gradient
from .anchored_points import AnchoredPoints
from .anny_keypoints import AnnyKeypointPath
from .anny_kinematics import AnnySkeleton
from .base import BodyModel, BodyOutput, KeypointPath, Params, VertexSubset, limit_excess
from .by_frame import FRAME, FrameRows, by_frame, frame_products, one_frame, rows_alike
from .shape_prior import PhenotypePrior
from .skinning import Binding, linear_blend_skinning

SIDES = ("L", "R")
SPINE = ["spine05", "spine04", "spine03", "spine02", "spine01"]
NECK = ["neck01", "neck02", "neck03", "head"]
ARM = ["clavicle", "shoulder01", "upperarm01", "upperarm02", "lowerarm01", "lowerarm02",
       "wrist"]
LEG = ["upperleg01", "upperleg02", "lowerleg01", "lowerleg02", "foot"]
BODY_BONES = SPINE + NECK + [f"{b}.{s}" for s in SIDES for b in ARM + LEG]
FINGER_BONES = [f"{b}.{s}" for s in SIDES for b in
                ["finger1-1", "finger1-2", "finger1-3", "metacarpal1", "finger2-1", "finger2-2",
                 "finger2-3", "metacarpal2", "finger3-1", "finger3-2", "finger3-3",
                 "metacarpal3", "finger4-1", "finger4-2", "finger4-3", "metacarpal4",
                 "finger5-1", "finger5-2", "finger5-3"]]
PHENOTYPES = ["gender", "age", "muscle", "weight", "height", "proportions"]
# The rest quantities AnnyBody.shape_expanded expands (with the rest vertices).
_EXPANDED = ("bone_poses", "offsets", "local_anchors")
SHAPE_NUDGE = 0.003  # logits: the central differences of AnnyBody.shape_expanded

# Anatomical limits (radians) of each bone's axis-angle components (x, y, z) in its own
# frame; signs measured on anny: hip flexion is -x, knee, elbow and trunk flexion +x,
# shoulder flexion +x, arm down toward the body -z on the left and +z on the right.
_LIMITS = {
    "spine": ((-0.25, -0.25, -0.2), (0.45, 0.25, 0.2)),
    "neck": ((-0.35, -0.45, -0.3), (0.4, 0.45, 0.3)),
    "head": ((-0.5, -0.6, -0.4), (0.5, 0.6, 0.4)),
    "clavicle": ((-0.3, -0.3, -0.3), (0.3, 0.3, 0.3)),
    "shoulder01": ((-0.3, -0.3, -0.3), (0.3, 0.3, 0.3)),
    "upperarm01.L": ((-1.2, -1.0, -0.9), (2.8, 1.0, 2.5)),
    "upperarm01.R": ((-1.2, -1.0, -2.5), (2.8, 1.0, 0.9)),
    "upperarm02": ((-0.15, -1.3, -0.15), (0.15, 1.3, 0.15)),
    "lowerarm01": ((-0.05, -0.2, -0.15), (2.6, 0.2, 0.15)),
    "lowerarm02": ((-0.1, -1.5, -0.1), (0.1, 1.5, 0.1)),
    "wrist": ((-1.2, -0.3, -0.6), (1.2, 0.3, 0.6)),
    "upperleg01": ((-2.3, -0.5, -0.8), (0.5, 0.5, 0.8)),
    "upperleg02": ((-0.1, -0.6, -0.1), (0.1, 0.6, 0.1)),
    "lowerleg01": ((-0.05, -0.2, -0.1), (2.6, 0.2, 0.1)),
    "lowerleg02": ((-0.1, -0.4, -0.1), (0.1, 0.4, 0.1)),
    # Plantarflexion (+x) to 50 degrees, an adult ankle's range: a kneeler's feet lie flat
    # along the floor behind the shins.
    "foot": ((-0.8, -0.3, -0.4), (0.87, 0.3, 0.4)),
}
# COCO-23 regressor labels (anny) in BODY_25 order; neck and mid-hip are means of pairs.
_BODY25_FROM_COCO = {
    0: "nose", 2: "right_shoulder", 3: "right_elbow", 4: "right_wrist", 5: "left_shoulder",
    6: "left_elbow", 7: "left_wrist", 9: "right_hip", 10: "right_knee", 11: "right_ankle",
    12: "left_hip", 13: "left_knee", 14: "left_ankle", 15: "right_eye", 16: "left_eye",
    17: "right_ear", 18: "left_ear", 19: "left_big_toe", 20: "left_small_toe",
    21: "left_heel", 22: "right_big_toe", 23: "right_small_toe", 24: "right_heel",
}
ADULT_AGE_YEARS = 35.0
# Phenotypes with an age-conditioned prior, and their columns in ``shape``.
_PRIOR_COLUMNS = {"height": 4, "weight": 3, "muscle": 2, "proportions": 5}
# Starting poses (local-bone axis-angle); the fitter keeps the one that explains the
# keypoints best: from standing, thighs seen end-on are as likely to swing back as forward.
def _legs(hip: float, knee: float) -> dict[str, list[float]]:
    return {"upperleg01.L": [hip, 0.0, 0.0], "upperleg01.R": [hip, 0.0, 0.0],
            "lowerleg01.L": [knee, 0.0, 0.0], "lowerleg01.R": [knee, 0.0, 0.0]}


_POSTURES = {
    "standing": {},
    "sitting": _legs(-1.4, 1.4),
    "leaning": {"spine03": [0.25, 0.0, 0.0], "spine02": [0.25, 0.0, 0.0],
                "spine01": [0.25, 0.0, 0.0]},
    "kneeling": _legs(-0.2, 2.0),
    "crouching": {**_legs(-2.0, 2.3), "spine02": [0.3, 0.0, 0.0]},
    "lying": _legs(-0.2, 0.4),
}


# The postures whose legs a fit with its legs hidden is also tried with.
_LEG_POSTURES = ("standing", "sitting", "kneeling", "crouching")
# An arm held forward (shoulder flexed, elbow half bent): where arm restarts begin.
_ARM_FORWARD = {"upperarm01": ([0.35, 0.0, -0.55], [0.35, 0.0, 0.55]),
                "upperarm02": ([0.0, 0.0, 0.0],) * 2,
                "lowerarm01": ([0.6, 0.0, 0.0],) * 2,
                "lowerarm02": ([0.0, 0.0, 0.0],) * 2}


def _limit_key(bone: str) -> str:
    if bone in _LIMITS:
        return bone
    base = bone.split(".")[0]
    if base.startswith("spine"):
        return "spine"
    if base.startswith("neck"):
        return "neck"
    return base


class AnnyBody(BodyModel):
    """anny with a fitted subset of bones; see the module docstring for the parameters."""

    name = "anny"

    def __init__(self, model: torch.nn.Module, age_years: float = ADULT_AGE_YEARS) -> None:
        super().__init__()
        import anny
        from anny.shape_distribution import SimpleShapeDistribution

        self.model = model
        labels = list(model.bone_labels)
        self.bone_labels = labels
        self.register_buffer("body_index", torch.tensor([labels.index(b) for b in BODY_BONES]))
        self.register_buffer("hand_index", torch.tensor([labels.index(b) for b in FINGER_BONES]))
        self.faces = model.get_triangular_faces().long()
        lo, hi = zip(*(_LIMITS[_limit_key(b)] for b in BODY_BONES))
        self.register_buffer("limit_lo", torch.tensor(lo, dtype=torch.float32))
        self.register_buffer("limit_hi", torch.tensor(hi, dtype=torch.float32))
        self.skeleton = AnnySkeleton(model, torch.cat([self.body_index, self.hand_index]))
        self.register_buffer("flexion_index", torch.tensor(
            [BODY_BONES.index(f"{b}.{s}") for s in SIDES for b in ("lowerarm01", "lowerleg01")]))

        # Shape prior: anny's age-conditioned phenotype distribution, at an adult age.
        self.shape_distribution = SimpleShapeDistribution(model)
        age = self.shape_distribution.morphological_age_mapping.morphological_to_anny_age(
            torch.tensor([age_years]))
        self.register_buffer("prior_age", age)
        self._setup_phenotype_table()
        # The starting shape is the prior's mean adult (genders alike): a starting body
        # taller than the mean person puts every monocular fit too far away.
        alpha, beta, _, _ = self.phenotype_prior.parameters(age.double().numpy())
        means = (alpha / (alpha + beta)).reshape(2, len(_PRIOR_COLUMNS)).mean(0)
        mean = [0.5, float(age), 0.5, 0.5, 0.5, 0.5]
        for column, value in zip(_PRIOR_COLUMNS.values(), means.tolist()):
            mean[column] = value
        self.register_buffer("shape_init", torch.logit(torch.tensor([mean]).clamp(1e-3,
                                                                                  1 - 1e-3)))

        regressor = anny.KeypointsRegressor.coco(model)
        weights = torch.zeros(N_KEYPOINTS, len(model.template_vertices))
        for index, label in _BODY25_FROM_COCO.items():
            weights[index] = regressor.regression_weights[regressor.labels.index(label)]
        weights[1] = (weights[2] + weights[5]) / 2  # neck: mid-shoulders
        weights[8] = (weights[9] + weights[12]) / 2  # mid-hip
        self.register_buffer("keypoint_weights", weights[BODY])
        self._rest_cache: dict[str, torch.Tensor] | None = None
        self._expansion: dict | None = None  # see shape_expanded
        # The whole mesh, posed as any other vertex subset is (model buffers, not copies;
        # the skinning binding compacted once).
        self._whole = VertexSubset(torch.arange(len(model.template_vertices)), {
            "template": model.template_vertices, "blendshapes": model.blendshapes,
            "binding": Binding(model.vertex_bone_weights, model.vertex_bone_indices)})
        self._setup_phenotype_coefficients()
        self._setup_static_geometry()
        self._setup_rest_basis(*self._setup_keypoint_anchors())
        # where the forward pass reads the bones it places keypoints and spheres on in the
        # bone chain's depth order
        for name, bones in (("anchor_slot", self.anchor_bone), ("hand_head_slot", self.hand_heads),
                            ("sphere_slot", self.sphere_bone)):
            self.register_buffer(name, self.skeleton.inverse[bones])
        self.anchored = AnchoredPoints(self.keypoint_source, self.anchor_point,
                                       self.anchor_slot, self.anchor_weight, self.hand_head_slot,
                                       len(self.keypoint_weights) + len(self.fingertips))

    @classmethod
    def load(cls, age_years: float = ADULT_AGE_YEARS) -> "AnnyBody":
        """Load the model baked by ``prox setup`` (fast; never builds or downloads)."""
        path = assets.anny_model_path()
        if not path.exists():
            raise FileNotFoundError(f"{path}: anny model data missing; run 'prox setup' first")
        assets.configure_warp()
        import anny
        import anny.skinning.warp_skinning as skinning
        from anny.models.model_data import ModelData

        # anny re-decorates its skinning kernel on every call (~2 ms, a sixth of a body
        # evaluation); the kernel depends only on hashable dtypes and counts.
        if not hasattr(skinning.get_kernel, "cache_info"):
            skinning.get_kernel = functools.lru_cache(maxsize=None)(skinning.get_kernel)

        model = anny.Anny.from_model_data(
            ModelData.load_safetensors(str(path)), pose_parameterization="local-bone",
            bone_orientation="cached", root_identity_orientation=False).to(torch.float32)
        model.requires_grad_(False)
        return cls(model, age_years)

    # ----------------------------------------------------------------- static geometry
    def _setup_static_geometry(self) -> None:
        """Contact sets, parts, hand keypoints and collision spheres from the rest body."""
        with torch.no_grad():
            rest = self.model(None, {"age": float(self.prior_age)})
        vertices = rest["rest_vertices"][0]
        poses = rest["rest_bone_poses"][0]
        normals = vertex_normals(vertices[None], self.faces)[0]
        dominant = self.model.vertex_bone_indices.gather(
            1, self.model.vertex_bone_weights.argmax(1, keepdim=True))[:, 0]
        bone_of = np.asarray(self.bone_labels)[dominant.numpy()]

        main = _largest_component(self.faces.numpy(), len(vertices))
        self.scene_vertices = torch.from_numpy(main)
        parts = np.array(["torso"] * len(vertices), dtype=object)
        for side, name in (("L", "left"), ("R", "right")):
            parts[np.char.endswith(bone_of.astype(str), f".{side}")] = f"{name}_limb"
        self._label_parts(parts, bone_of)
        parts[~main] = "eyes_tongue"
        self.vertex_parts = parts.tolist()

        z, ny, nz = vertices[:, 2].numpy(), normals[:, 1].numpy(), normals[:, 2].numpy()
        hip_z = float(poses[self.bone_labels.index("upperleg01.L"), 2, 3])
        knee_z = float(poses[self.bone_labels.index("lowerleg01.L"), 2, 3])
        is_ = lambda *names: np.isin(bone_of, names)  # noqa: E731
        contact = {
            "left_hand": (parts == "left_hand"),
            "right_hand": (parts == "right_hand"),
            "left_foot": (parts == "left_foot") & (nz < -0.5),
            "right_foot": (parts == "right_foot") & (nz < -0.5),
            "back": is_(*SPINE) & (ny > 0.6) & (z > hip_z + 0.12),
            "gluteus": (ny > 0.4) & (z < hip_z + 0.08) & (z > hip_z - 0.16)
            & is_("root", "pelvis.L", "pelvis.R", "upperleg01.L", "upperleg01.R", "spine05"),
            "thighs": is_("upperleg01.L", "upperleg01.R", "upperleg02.L", "upperleg02.R")
            & (ny > 0.5) & (z < hip_z - 0.16) & (z > knee_z + 0.08),
        }
        # Hands are dense (1609 vertices each): every third vertex is enough for contact.
        self.contact_parts = {k: torch.from_numpy(np.flatnonzero(v & main)[::3 if "hand" in k
                                                                             else 1])
                              for k, v in contact.items()}

        # Hand keypoints: wrist head, then per finger the heads of its three phalanges and
        # the fingertip vertex (the finger3 vertex farthest along its bone).
        hand_bones, tips = [], []
        for side in SIDES:
            hand_bones.append(f"wrist.{side}")
            for f in range(1, 6):
                hand_bones += [f"finger{f}-{k}.{side}" for k in (1, 2, 3)]
                bone = f"finger{f}-3.{side}"
                pose = poses[self.bone_labels.index(bone)]
                along = (vertices - pose[:3, 3]) @ pose[:3, 1]
                along[torch.from_numpy(bone_of != bone)] = -math.inf
                tips.append(int(along.argmax()))
        self.register_buffer("hand_heads", torch.tensor(
            [self.bone_labels.index(b) for b in hand_bones]))
        self.register_buffer("fingertips", torch.tensor(tips))
        self._setup_keypoint_source()
        self._setup_spheres(vertices, poses, bone_of)

    def _setup_keypoint_source(self) -> None:
        """Where each of the N_KEYPOINTS keypoints comes from in the row of points the
        forward pass gathers them from: the body keypoints, the fingertips, the hand bones'
        heads (:attr:`hand_heads`), and a zero for the face."""
        body, tips = len(self.keypoint_weights), len(self.fingertips)
        heads = body + tips
        source = torch.full((N_KEYPOINTS,), heads + len(self.hand_heads))  # the zero
        source[BODY] = torch.arange(body)
        for side, slot in enumerate((LEFT_HAND, RIGHT_HAND)):
            hand = [heads + side * 16]  # the wrist, then each finger's 3 heads and its tip
            for finger in range(5):
                hand += [heads + side * 16 + 1 + 3 * finger + k for k in range(3)]
                hand.append(body + side * 5 + finger)
            source[slot] = torch.tensor(hand)
        self.register_buffer("keypoint_source", source)

    def _label_parts(self, parts: np.ndarray, bone_of: np.ndarray) -> None:
        from anny.face_segmentation import get_face_segmentation_mask

        faces = self.faces.numpy()
        for label, name in (("hand.L", "left_hand"), ("hand.R", "right_hand"),
                            ("foot.L", "left_foot"), ("foot.R", "right_foot"),
                            ("head", "head")):
            mask = get_face_segmentation_mask(self.model, [label]).numpy()
            parts[np.unique(faces[mask])] = name
        for bone, name in (("upperleg", "thigh"), ("lowerleg", "shin"),
                           ("upperarm", "upper_arm"), ("lowerarm", "forearm")):
            for side, side_name in (("L", "left"), ("R", "right")):
                sel = np.char.startswith(bone_of.astype(str), bone) & np.char.endswith(
                    bone_of.astype(str), f".{side}") & (parts == f"{side_name}_limb")
                parts[sel] = f"{side_name}_{name}"
        parts[np.isin(parts, ["left_limb", "right_limb"])] = "torso"

    def _setup_spheres(self, vertices: torch.Tensor, poses: torch.Tensor,
                       bone_of: np.ndarray) -> None:
        """Spheres inside arms, legs and torso; pairs that are apart at rest may not meet."""
        centres, radii, bones, groups = [], [], [], []

        def chain(group: str, head: str, tail: str, members: list[str], count: int) -> None:
            a = poses[self.bone_labels.index(head), :3, 3]
            b = poses[self.bone_labels.index(tail), :3, 3]
            sel = torch.from_numpy(np.isin(bone_of, members))
            for t in (np.arange(count) + 0.5) / count:
                c = a + (b - a) * float(t)
                d = (vertices[sel] - c).norm(dim=1)
                axis = (b - a) / (b - a).norm()
                ring = ((vertices[sel] - c) @ axis).abs() < (b - a).norm() / (2 * count)
                r = float(d[ring].median()) * 0.85 if ring.any() else float(d.min())
                centres.append(c)
                radii.append(r)
                bones.append(self.bone_labels.index(head))
                groups.append(group)

        for s in SIDES:
            chain(f"arm.{s}", f"upperarm01.{s}", f"lowerarm01.{s}",
                  [f"upperarm01.{s}", f"upperarm02.{s}"], 3)
            chain(f"arm.{s}", f"lowerarm01.{s}", f"wrist.{s}",
                  [f"lowerarm01.{s}", f"lowerarm02.{s}"], 3)
            chain(f"leg.{s}", f"upperleg01.{s}", f"lowerleg01.{s}",
                  [f"upperleg01.{s}", f"upperleg02.{s}"], 4)
            chain(f"leg.{s}", f"lowerleg01.{s}", f"foot.{s}",
                  [f"lowerleg01.{s}", f"lowerleg02.{s}"], 4)
        # Torso: a column of three spheres (left, centre, right) per spine bone.
        for bone in SPINE:
            sel = torch.from_numpy(bone_of == bone)
            if not sel.any():
                continue
            pts = vertices[sel]
            lo, hi = pts.min(0).values, pts.max(0).values
            r = float(hi[1] - lo[1]) / 2 * 0.85
            mid = (lo + hi) / 2
            half = max(float(hi[0] - lo[0]) / 2 - r, 0.0)
            for dx in (-half, 0.0, half):
                centres.append(mid + torch.tensor([dx, 0.0, 0.0]))
                radii.append(r)
                bones.append(self.bone_labels.index(bone))
                groups.append("torso")
        centres_t = torch.stack(centres)
        local = torch.einsum("sij,sj->si", torch.linalg.inv(poses[bones]),
                             torch.cat([centres_t, torch.ones(len(centres), 1)], 1))
        self.register_buffer("sphere_local", local)  # homogeneous, in the bone's rest frame
        self.register_buffer("sphere_radius", torch.tensor(radii))
        self.register_buffer("sphere_bone", torch.tensor(bones))
        allowed = {("arm.L", "torso"), ("arm.R", "torso"), ("leg.L", "leg.R")}
        dist = torch.cdist(centres_t, centres_t)
        rad = self.sphere_radius[:, None] + self.sphere_radius[None]
        pairs = [(i, j) for i in range(len(groups)) for j in range(i + 1, len(groups))
                 if tuple(sorted((groups[i], groups[j]))) in allowed
                 and dist[i, j] > rad[i, j] + 0.02]
        self.collision_pairs = torch.tensor(pairs, dtype=torch.long)

    # ----------------------------------------------------------------- parameters
    postures = tuple(_POSTURES)
    lying_postures = ("lying",)

    def init_params(self, batch_size: int, posture: str = "standing") -> Params:
        def zeros(*shape: int) -> torch.Tensor:
            return torch.zeros(batch_size, *shape)

        params = {
            "global_orient": zeros(3), "transl": zeros(3),
            "body_pose": zeros(len(BODY_BONES), 3), "hand_pose": zeros(len(FINGER_BONES), 3),
            "shape": self.shape_init.repeat(batch_size, 1),
        }
        for bone, value in _POSTURES[posture].items():
            params["body_pose"][:, BODY_BONES.index(bone)] = torch.tensor(value)
        return params

    def shape_group(self) -> list[str]:
        return ["shape"]

    def arm_restarts(self, params: Params) -> list[Params]:
        variants = []
        for sides in (("L",), ("R",), ("L", "R")):
            pose = params["body_pose"].clone()
            for bone, values in _ARM_FORWARD.items():
                for side in sides:
                    pose[:, BODY_BONES.index(f"{bone}.{side}")] = torch.tensor(
                        values[SIDES.index(side)])
            variants.append({**params, "body_pose": pose})
        return variants

    def leg_postures(self, params: Params, thighs_kept: torch.Tensor | None = None
                     ) -> dict[str, Params]:
        variants = {}
        for posture in _LEG_POSTURES:
            legs = _legs(0.0, 0.0)
            legs.update({bone: v for bone, v in _POSTURES[posture].items() if bone in legs})
            pose = params["body_pose"].clone()
            for bone, value in legs.items():
                index = BODY_BONES.index(bone)
                posed = torch.tensor(value).expand_as(pose[:, index])
                if thighs_kept is not None and bone.startswith("upperleg"):
                    posed = torch.where(thighs_kept[:, None], pose[:, index], posed)
                pose[:, index] = posed
            variants[posture] = {**params, "body_pose": pose}
        return variants

    def point_feet(self, params: Params, which: torch.Tensor) -> Params:
        pose = params["body_pose"].clone()
        for side, rows in zip(("R", "L"), which.T):
            bone = BODY_BONES.index(f"foot.{side}")
            pose[rows, bone] = torch.stack([self.limit_hi[bone, 0], *pose.new_zeros(2)])
        return {**params, "body_pose": pose}

    def relax_feet(self, params: Params, keep: torch.Tensor) -> Params:
        pose = params["body_pose"].clone()
        for side, scale in zip(("R", "L"), keep.T):
            bone = BODY_BONES.index(f"foot.{side}")
            pose[:, bone] = pose[:, bone] * scale[:, None]
        return {**params, "body_pose": pose}

    def root_pivot(self, params: Params) -> torch.Tensor:
        return params["transl"].new_zeros(params["transl"].shape)  # the root is the origin

    def up_axis(self) -> torch.Tensor:
        return torch.tensor([0.0, 0.0, 1.0])

    def rest_height(self, params: Params) -> torch.Tensor:
        """The rest skeleton's span along the up axis: its bone heads are linear in the
        phenotype's coefficients, so no pose (0.1 ms instead of 5 for the mesh)."""
        def height(shape: torch.Tensor) -> torch.Tensor:
            coeffs = self.phenotype_coefficients(torch.sigmoid(shape))
            heads = self.rest_sizes[0]
            up = (self.rest_template[:heads] + coeffs @ self.rest_basis[:, :heads]).view(
                len(coeffs), -1, 3) @ self.up_axis()
            return up.max(1).values - up.min(1).values
        return by_frame(height, params.get(FRAME), params["shape"].detach())

    def forward_axis(self) -> torch.Tensor:
        return torch.tensor([0.0, -1.0, 0.0])

    # ----------------------------------------------------------------- forward
    def _setup_phenotype_coefficients(self) -> None:
        """anny's phenotype blendshape coefficients as one gather and product: each of its
        blendshapes is the product of one variation weight per phenotype (a hat function
        of the value over the phenotype's evenly spaced anchors), and those of the
        phenotypes held fixed (race, cup size, firmness) are constants, folded in here.
        anny's own loops cost a millisecond per forward and backward."""
        from anny.models.model_data import PHENOTYPE_VARIATIONS

        model = self.model
        fixed = torch.ones(len(model.stacked_phenotype_blend_shapes_mask))
        column, source, centre, step = 0, [], [], []
        mask = model.stacked_phenotype_blend_shapes_mask.bool()
        for feature, variations in PHENOTYPE_VARIATIONS.items():
            count = len(variations)
            if feature in PHENOTYPES:
                anchors = model.anchors[feature]
                source += [PHENOTYPES.index(feature)] * count
                centre += anchors.tolist()
                step += [float(anchors[1] - anchors[0])] * count
            else:  # at anny's default of 0.5 (race: thirds)
                values = (torch.full((count,), 1 / count) if feature == "race" else
                          torch.relu(1 - (0.5 - torch.linspace(0, 1, count)).abs() * (count - 1)))
                for i, value in enumerate(values):
                    fixed = torch.where(mask[:, column + i], fixed * value, fixed)
                source += [-1] * count
                centre += [0.0] * count
                step += [1.0] * count
            column += count
        free = torch.tensor(source) >= 0
        picks = [row[free[row]] for row in (torch.nonzero(r).flatten() for r in mask)]
        width = max(len(p) for p in picks)
        slots = free.nonzero().flatten()
        index = torch.full((len(picks), width), len(slots))  # padded: a column of ones
        for k, p in enumerate(picks):
            index[k, :len(p)] = torch.searchsorted(slots, p)
        self.register_buffer("phenotype_source", torch.tensor(source)[free])
        self.register_buffer("phenotype_centre", torch.tensor(centre)[free])
        self.register_buffer("phenotype_step", torch.tensor(step)[free])
        self.register_buffer("phenotype_lo", torch.tensor([float(model.anchors[f][0]) for f in
                                                           PHENOTYPES])[self.phenotype_source])
        self.register_buffer("phenotype_hi", torch.tensor([float(model.anchors[f][-1]) for f in
                                                           PHENOTYPES])[self.phenotype_source])
        self.register_buffer("phenotype_index", index)
        projection = model.phenotype_blendshape_projection
        self.register_buffer("phenotype_projection", fixed[:, None] * projection
                             if projection is not None else torch.diag(fixed))

    def phenotype_coefficients(self, phenotype: torch.Tensor) -> torch.Tensor:
        """Blendshape coefficients (B, C) of phenotypes (B, 6) in [0, 1], as anny's."""
        value = phenotype[:, self.phenotype_source]
        value = torch.minimum(torch.maximum(value, self.phenotype_lo), self.phenotype_hi)
        weight = torch.relu(1 - (value - self.phenotype_centre).abs() / self.phenotype_step)
        weight = torch.cat([weight, weight.new_ones(len(weight), 1)], 1)
        return weight[:, self.phenotype_index].prod(-1) @ self.phenotype_projection

    def _setup_keypoint_anchors(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The body keypoints and fingertips without skinning the mesh. A skinned vertex is
        sum_j w_vj T_j [x_v; 1], so a keypoint that is a weighted sum of vertices is
        sum_j T_j [a_kj; h_kj] with a_kj = sum_v W_kv w_vj x_v and h_kj = sum_v W_kv w_vj:
        one anchor per (keypoint, bone) pair that shares a vertex (a few hundred), linear in
        the shape's blendshape coefficients like the vertices themselves. Returns the
        anchors a at coefficients 0 (pairs, 3) and their blendshapes (C, pairs, 3)."""
        model = self.model
        count = len(model.template_vertices)
        weights = torch.cat([self.keypoint_weights, torch.zeros(len(self.fingertips), count)])
        weights[len(self.keypoint_weights) + torch.arange(len(self.fingertips)),
                self.fingertips] = 1.0
        point, vertex = weights.nonzero(as_tuple=True)
        bone = model.vertex_bone_indices[vertex].long()  # (N, bones per vertex)
        share = weights[point, vertex, None] * model.vertex_bone_weights[vertex]
        keys = point[:, None] * len(self.bone_labels) + bone
        used = share != 0
        pairs, slot = torch.unique(keys[used], return_inverse=True)
        mix = torch.zeros(len(pairs), count).index_put_(
            (slot, vertex[:, None].expand_as(keys)[used]), share[used], accumulate=True)
        self.register_buffer("anchor_point", pairs // len(self.bone_labels))
        self.register_buffer("anchor_bone", pairs % len(self.bone_labels))
        self.register_buffer("anchor_weight", mix.sum(1))  # h
        return mix @ model.template_vertices, torch.einsum("pv,cvd->cpd", mix, model.blendshapes)

    def _setup_rest_basis(self, anchors: torch.Tensor, anchor_blendshapes: torch.Tensor
                          ) -> None:
        """Bone heads, bone orientations (before anny's Procrustes) and keypoint anchors
        are each linear in the blendshape coefficients: one matrix for the three, so a
        shape costs one product (anny's three einsums cost 3x as much)."""
        model = self.model
        parts = [(model.template_bone_heads, model.bone_heads_blendshapes),
                 (model.bone_template_orientation_matrices, model.bone_orientation_blendshapes),
                 (anchors, anchor_blendshapes)]
        self.rest_sizes = [template.numel() for template, _ in parts]
        self.register_buffer("rest_template", torch.cat([t.reshape(-1) for t, _ in parts]))
        self.register_buffer("rest_basis", torch.cat([b.reshape(len(b), -1) for _, b in parts],
                                                     1))

    @contextmanager
    def shape_expanded(self, params: Params, vertices: bool | VertexSubset
                       ) -> Iterator[Callable[[torch.Tensor], None]]:
        """Within it, a free shape's rest quantities (bone poses and offsets, keypoint
        anchors, the rest vertices of ``vertices``) are their first-order expansion about
        the shape of ``params`` (B, 6), one per row, its slopes central differences
        (:data:`SHAPE_NUDGE` each way along each logit) found for every row in one
        batched forward, each frame's rows as the frame alone (:func:`by_frame`): a
        forward and backward on the scene terms' vertices then costs 3.0 ms instead of
        7.8 (2.5 frozen), for 5 ms an expansion (26 for 8 rows;
        forward-mode autograd took 14 and 74, and gave gradients as near the model's). A
        scene stage moves the logits by 0.1-0.2, where the expansion is within half a
        millimetre of the model. It gives the function that narrows the expansion to some
        rows of ``params``."""
        subset = self._subset(vertices)
        base = params["shape"].detach().clone()  # the optimiser moves the shape in place

        def nudged(base: torch.Tensor) -> torch.Tensor:
            """Each row of ``base``, then each nudged along each logit, then back."""
            nudge = torch.eye(base.shape[1]) * SHAPE_NUDGE
            return torch.cat([base, (base[:, None] + nudge).flatten(0, 1),
                              (base[:, None] - nudge).flatten(0, 1)])

        def expansion(base: torch.Tensor, rest: dict[str, torch.Tensor]
                      ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
            """The values and slopes of rows ``base`` from the rest quantities of their
            nudged rows."""
            rows, size = len(base), base.shape[1]
            values = [*(rest[k] for k in _EXPANDED), rest["coeffs"]]
            *at, coeffs = (v[:rows] for v in values)
            *slopes, coeff_slope = (  # (B, 6, n): central differences
                (v[rows:rows + rows * size] - v[rows + rows * size:]).reshape(rows, size, -1)
                / (2 * SHAPE_NUDGE) for v in values)
            if subset is not None:
                blend = subset.data["blendshapes"]  # (C, V, 3)
                at.append(subset.data["template"] + torch.einsum("bc,cvd->bvd", coeffs, blend))
                slopes.append(coeff_slope @ blend.flatten(1))
            return at, [s.contiguous() for s in slopes]

        frames = params.get(FRAME)
        if one_frame(frames):
            at, slopes = expansion(base, self._rest_of_logits(nudged(base), None))
        else:  # each frame's nudged rows (13 a row: rows enough to round alike) in one
            # batch, and what follows from them frame by frame
            framed = FrameRows(frames)
            bases = framed.split(base)
            counts = [len(rows) * (1 + 2 * base.shape[1]) for rows in bases]
            blocks = torch.cat([nudged(rows) for rows in bases])
            rest = self._rest_of_logits(blocks, torch.arange(len(bases)).repeat_interleave(
                torch.tensor(counts)))
            parts = [expansion(rows, dict(zip(rest, values))) for rows, values in
                     zip(bases, zip(*(v.split(counts) for v in rest.values())))]
            at, slopes = ([framed.join([part[which][i] for part in parts])
                           for i in range(len(parts[0][which]))] for which in (0, 1))

        def expanded(rows: torch.Tensor | None) -> dict:
            """The expansion of ``rows`` (None: all), each frame's slopes apart."""
            def pick(v: torch.Tensor) -> torch.Tensor:
                return v if rows is None else v[rows]

            kept = None if frames is None else pick(frames)
            framed = None if one_frame(kept) else FrameRows(kept)
            slope = [pick(v) for v in slopes]
            return {"shape": pick(base), "subset": subset, "frames": framed,
                    "at": [pick(v) for v in at],
                    "slope": slope if framed is None else [framed.split(v) for v in slope]}

        def narrow(rows: torch.Tensor) -> None:
            self._expansion = expanded(rows)

        self._expansion = expanded(None)
        try:
            yield narrow
        finally:
            self._expansion = None

    def _subset(self, vertices: bool | VertexSubset) -> VertexSubset | None:
        """The vertices a ``vertices`` request poses: all, a subset, or none."""
        return self._whole if vertices is True else vertices or None

    def _expanded(self, shape: torch.Tensor, vertices: VertexSubset | None
                  ) -> dict[str, torch.Tensor] | None:
        """The rest quantities of the expansion in force for a free ``shape`` of its rows
        and ``vertices``, or None."""
        found = self._expansion
        if (found is None or not shape.requires_grad or vertices is not found["subset"]
                or shape.shape != found["shape"].shape):
            return None
        step = (shape - found["shape"])[:, None]  # (B, 1, 6)
        framed = found["frames"]
        if framed is None:
            values = [at + (step @ slope).view(at.shape)
                      for at, slope in zip(found["at"], found["slope"])]
        else:  # each frame's step times its own slopes, as the frame alone
            values = [at + frame_products(step, framed, blocks).view(at.shape)
                      for at, blocks in zip(found["at"], found["slope"])]
        rest = dict(zip(_EXPANDED, values))
        if vertices is not None:
            rest[vertices] = values[-1]
        return rest

    def _rest(self, shape: torch.Tensor, vertices: VertexSubset | None,
              frames: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Rest bone poses, keypoint anchors and (for a ``vertices`` subset, under the
        subset as key) rest vertices for shape logits, as anny's ``cached`` bone
        orientation computes them; kept while the shape is frozen, or expanded about a
        point (see :meth:`shape_expanded`); each frame's rows (``frames``) worked out as
        the frame alone (:func:`by_frame`)."""
        expanded = self._expanded(shape, vertices)
        if expanded is not None:
            return expanded
        cached = self._rest_cache
        frozen = not shape.requires_grad
        if not (frozen and cached is not None and torch.equal(cached["shape"], shape)
                and _same_frames(cached["frames"], frames)):
            cached = {"shape": shape.detach().clone(), "frames": frames,
                      **self._rest_of_logits(shape, frames)}
            if frozen:
                self._rest_cache = cached
        if vertices and vertices not in cached:
            cached[vertices] = by_frame(lambda coeffs: vertices.data["template"] + torch.einsum(
                "bc,cvd->bvd", coeffs, vertices.data["blendshapes"]), frames, cached["coeffs"])
        return cached

    def _rest_of_logits(self, shape: torch.Tensor, frames: torch.Tensor | None
                        ) -> dict[str, torch.Tensor]:
        """:meth:`_rest_of` the phenotypes of shape logits (B, 6), each frame's rows
        (``frames``) as the frame alone: the sigmoid frame by frame (its last elements
        take a scalar path), and the blendshape products so too unless every frame has
        rows enough to round alike in one product (:func:`rows_alike`); what follows from
        the products works on each row (a bone at a time) and goes in one batch."""
        if rows_alike(frames):
            return self._rest_of(*self._shape_products(by_frame(torch.sigmoid, frames, shape)))
        return self._rest_of(*by_frame(lambda rows: self._shape_products(torch.sigmoid(rows)),
                                       frames, shape))

    def _shape_products(self, phenotype: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The blendshape coefficients (B, C) of phenotypes (B, 6) in [0, 1], and the rest
        skeleton's and keypoint anchors' values (B, n) they give (:meth:`_setup_rest_basis`)."""
        coeffs = self.phenotype_coefficients(phenotype)
        return coeffs, self.rest_template + coeffs @ self.rest_basis

    def _rest_of(self, coeffs: torch.Tensor, rest: torch.Tensor) -> dict[str, torch.Tensor]:
        """The rest bone poses and offsets and keypoint anchors (see :meth:`_rest`) of
        blendshape coefficients (B, C) and their products (:meth:`_shape_products`)."""
        model = self.model
        heads, orientation, anchors = rest.split(self.rest_sizes, 1)
        heads = heads.view(len(coeffs), -1, 3)
        orientation = roma.special_procrustes(orientation.view(len(coeffs), -1, 3, 3))
        if model.rest_orientation_refiner is not None:
            orientation = model.rest_orientation_refiner(orientation, heads)
        poses = roma.Rigid(orientation, heads).to_homogeneous()
        return {"coeffs": coeffs, "bone_poses": poses, "offsets": self.skeleton.offsets(poses),
                "local_anchors": self._local_anchors(anchors.view(len(coeffs), -1, 3), poses)}

    def _local_anchors(self, anchors: torch.Tensor, rest_poses: torch.Tensor) -> torch.Tensor:
        """(B, pairs, 3) the keypoint anchors (a, h) in their bones' rest frames, P^-1 [a;
        h] = [R^T (a - h t); h] for a bone at rest at [R | t]: a posed bone W moves its
        anchor to W [R^T (a - h t); h] without the skinning transform W P^-1."""
        held = rest_poses[:, self.anchor_bone]
        offset = anchors - self.anchor_weight[:, None] * held[..., :3, 3]
        return (held[..., :3, :3].transpose(-1, -2) @ offset[..., None])[..., 0]

    def keypoint_path(self, params: Params, vertices: VertexSubset | None = None
                      ) -> KeypointPath:
        return AnnyKeypointPath(self, params, vertices)

    def vertex_subset(self, ids: torch.Tensor) -> VertexSubset:
        """The vertices ``ids`` with their rest template, blendshapes and skinning weights
        gathered once: posing 7553 of the 13718 (the scene terms' vertices) takes 2.4 of
        a shape-free forward+backward's 9.6 ms less."""
        subset = super().vertex_subset(ids)
        model, ids = self.model, subset.ids
        subset.data = {"template": model.template_vertices[ids].contiguous(),
                       "blendshapes": model.blendshapes[:, ids].contiguous(),
                       "binding": Binding(model.vertex_bone_weights[ids],
                                          model.vertex_bone_indices[ids])}
        return subset

    def forward(self, params: Params, vertices: bool | VertexSubset = True,
                spheres: bool = True) -> BodyOutput:
        subset = self._subset(vertices)
        rest = self._rest(params["shape"], subset, frames=params.get(FRAME))
        rotvecs = torch.cat([params["global_orient"][:, None], params["body_pose"],
                             params["hand_pose"]], 1)
        batch = len(rotvecs)
        poses = self.skeleton.pose(rotvecs, params["transl"], rest["offsets"])  # depth order
        skinned = None
        if subset is not None:
            transforms, _ = self.skeleton.transforms(poses, rest["bone_poses"])
            skinned = linear_blend_skinning(rest[subset], subset.data["binding"], transforms)
        keypoints = self.anchored(poses, rest["local_anchors"])
        if not spheres:
            return BodyOutput(vertices=skinned, keypoints=keypoints)
        centres = (poses[:, self.sphere_slot, :3, :] @ self.sphere_local[..., None])[..., 0]
        return BodyOutput(vertices=skinned, keypoints=keypoints, spheres=torch.cat(
            [centres, self.sphere_radius.expand(batch, -1)[..., None]], -1))

    @property
    def keypoint_mask(self) -> torch.Tensor:
        mask = torch.zeros(N_KEYPOINTS, dtype=torch.bool)
        mask[BODY] = True
        mask[LEFT_HAND] = True
        mask[RIGHT_HAND] = True
        return mask

    # ----------------------------------------------------------------- priors
    def pose_prior(self, params: Params) -> torch.Tensor:
        return (params["body_pose"] ** 2).sum((1, 2))

    def joint_limits(self, params: Params) -> torch.Tensor:
        return limit_excess(params["body_pose"], self.limit_lo, self.limit_hi)

    def bending_prior(self, params: Params) -> torch.Tensor:
        pose = params["body_pose"]
        bent = torch.exp(-pose.detach()[:, self.flexion_index, 0])  # flexion < 0: backwards
        gradient = torch.zeros_like(pose)
        gradient[:, self.flexion_index, 0] = -bent
        return with_gradient(pose, bent.sum(1), gradient)

    def hand_prior(self, params: Params) -> torch.Tensor:
        return (params["hand_pose"] ** 2).sum((1, 2))

    def _setup_phenotype_table(self) -> None:
        """anny's conditional Beta distributions (boys then girls, :data:`_PRIOR_COLUMNS`)
        as one table of alpha and beta on the union of their age anchors: piecewise-linear
        in age like the originals (exactly, since every anchor is a knot of the union),
        but one interpolation per call instead of sixteen."""
        dists = [getattr(self.shape_distribution, f"{who}_conditional_{name}_distribution")
                 for who in ("boys", "girls") for name in _PRIOR_COLUMNS]
        anchors = torch.unique(torch.cat([d.age_anchors for d in dists]))
        alpha, beta = zip(*(d.get_distribution_params(anchors) for d in dists))
        self.phenotype_prior = PhenotypePrior(anchors, torch.stack(alpha, 1),
                                              torch.stack(beta, 1),
                                              list(_PRIOR_COLUMNS.values()),
                                              float(self.prior_age))

    def shape_prior(self, params: Params) -> torch.Tensor:
        """-log p(phenotype | adult age) under anny's calibrated Beta distributions, with
        its gradient worked out alongside (:class:`PhenotypePrior`)."""
        return self.phenotype_prior(params["shape"])

    # ----------------------------------------------------------------- export
    def export(self, params: Params, index: int) -> dict:
        def aa(value: torch.Tensor) -> list:
            return value[index].detach().tolist()

        return {
            "model": "anny", "model_version": "0.6.2",
            "global_orient": aa(params["global_orient"]), "transl": aa(params["transl"]),
            "body_pose": dict(zip(BODY_BONES, aa(params["body_pose"]))),
            "hand_pose": dict(zip(FINGER_BONES, aa(params["hand_pose"]))),
            "phenotype": dict(zip(PHENOTYPES, torch.sigmoid(params["shape"][index]).tolist())),
            "pose_parameterization": "local-bone axis-angle",
        }


def _largest_component(faces: np.ndarray, count: int) -> np.ndarray:
    """Mask of the vertices in the largest connected part of the mesh."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(count, count))
    _, labels = connected_components(graph, directed=False)
    return labels == np.bincount(labels).argmax()


def _same_frames(a: torch.Tensor | None, b: torch.Tensor | None) -> bool:
    """Whether rows of frames ``a`` and ``b`` (see :func:`by_frame`) are grouped alike."""
    return (a is None) == (b is None) and (a is None or torch.equal(a, b))
