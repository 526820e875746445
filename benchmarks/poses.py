"""Ground-truth bodies of the benchmark: adult phenotypes, interaction poses and posed
sequences.

Poses are anny local-bone axis-angles (radians) at a sequence ``phase``; their sinusoidal
terms move the head, arms or torso a little between frames, never the parts that touch
the scene. Signs: hip flexion -x on ``upperleg01``, knee, elbow and trunk flexion +x,
shoulder flexion +x on ``upperarm01``, arm toward the body -z on ``.L`` and +z on ``.R``.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import torch

from prox_engine.body.anny_body import AnnyBody
from prox_engine.synthetic import body_params, sitting_pose

Pose = dict[str, list[float]]


def sample_phenotype(rng: np.random.Generator, body: AnnyBody,
                     height_z: float) -> dict[str, float]:
    """A plausible adult: clearly male or female, height ``height_z`` standard deviations
    from anny's adult mean for that gender, the rest uniform in a moderate range."""
    gender = rng.uniform(0.85, 1.0) if rng.random() < 0.5 else rng.uniform(0.0, 0.15)
    mean = 0.39 - 0.04 * gender  # anny's adult height means: 0.39 men, 0.35 women, sd 0.07
    height = float(np.clip(mean + 0.07 * (height_z + rng.uniform(-0.15, 0.15)), 0.15, 0.6))
    return {"gender": gender, "age": float(torch.sigmoid(body.shape_init[0, 1])),
            "muscle": rng.uniform(0.1, 0.7), "weight": rng.uniform(0.2, 0.8),
            "height": height, "proportions": rng.uniform(0.25, 0.75)}


def posed(body: AnnyBody, pose_list: list[Pose], phenotype: dict[str, float],
          orient: Sequence[float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (F, V, 3) and keypoints (F, 118, 3) of a pose sequence with root rotation
    ``orient`` (axis-angle), root at the origin."""
    verts, kps = [], []
    for pose in pose_list:
        params = body_params(body, pose, 0.0, phenotype)
        params["global_orient"][0] = torch.tensor(orient, dtype=torch.float32)
        with torch.no_grad():
            output = body(params)
        verts.append(output.vertices[0].numpy())
        kps.append(output.keypoints[0].numpy())
    return np.stack(verts).astype(np.float64), np.stack(kps).astype(np.float64)


def stature(body: AnnyBody, phenotype: dict[str, float]) -> float:
    """Standing height (m) of a phenotype."""
    return round(float(np.ptp(posed(body, [{}], phenotype)[0][0, :, 2])), 3)


def phases(frames: int, rng: np.random.Generator, step: float = 0.7) -> list[float]:
    """``frames`` phases ``step`` apart from a random start."""
    start = rng.uniform(0.0, 2 * np.pi)
    return [start + step * t for t in range(frames)]


def to_floor(verts: np.ndarray, kps: np.ndarray, lift: float = 0.0
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shift a sequence so that its first frame is centred on x = y = 0 and its lowest
    point is ``lift`` above the floor; return the shifted arrays and the shift."""
    shift = np.array([*-verts[0, :, :2].mean(0), lift - verts[:, :, 2].min()])
    return verts + shift, kps + shift, shift


def body_points(body: AnnyBody, verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scene vertices (``body.scene_vertices``) of all frames (N, 3) and their parts."""
    main = body.scene_vertices.numpy()
    return verts[:, main].reshape(-1, 3), np.tile(np.asarray(body.vertex_parts)[main],
                                                  len(verts))


def _mirror(bone: str, value: list[float]) -> Pose:
    """``value`` on the left bone and its mirror image (y and z negated) on the right."""
    x, y, z = value
    return {f"{bone}.L": [x, y, z], f"{bone}.R": [x, -y, -z]}


def seated_hip(body: AnnyBody, phenotype: dict[str, float], pose_at: Callable[[float], Pose],
               orient: Sequence[float] = (0.0, 0.0, 0.0)) -> float:
    """The hip flexion of ``pose_at(hip)`` at which the thighs reach down as far as the
    buttocks, so that both rest on a flat seat (women's buttocks protrude more)."""
    thighs, gluteus = (body.contact_parts[part].numpy() for part in ("thighs", "gluteus"))

    def gap(hip: float) -> float:
        verts = posed(body, [pose_at(hip)], phenotype, orient)[0][0]
        return float(verts[thighs, 2].min() - verts[gluteus, 2].min())

    return float(min(np.linspace(1.2, 1.6, 9), key=lambda hip: abs(gap(hip) - 0.005)))


def sit(phase: float, lean: float, hip: float) -> Pose:
    """Upright on a chair, hands on the thighs, hips flexed by ``hip``, the trunk leaning
    forward by ``lean`` (back when negative)."""
    pose = sitting_pose(phase)
    pose.update(_mirror("upperleg01", [-hip, 0.0, -0.08]))
    pose["spine02"] = [lean, 0.0, 0.0]
    return pose


def leg_up(phase: float, lean: float, hip: float, lift: float, knee: float) -> Pose:
    """Sitting as :func:`sit`, the right leg stretched out forward (its hip flexed ``lift``
    more than the left's, the knee bent by ``knee``) with the heel on something low."""
    pose = sit(phase, lean, hip)
    pose.update({"upperleg01.R": [-hip - lift, 0.0, 0.1], "lowerleg01.R": [knee, 0.0, 0.0],
                 "foot.R": [0.3, 0.0, 0.0]})
    return pose


def sofa(phase: float, recline: float, hip: float) -> Pose:
    """Sitting on a sofa; the caller reclines the whole body by ``recline`` about x, so the
    hips open by as much to hold the thighs as ``hip`` does on a chair, and the neck bends
    to look ahead."""
    s = float(np.sin(phase))
    return {
        **_mirror("upperleg01", [-(hip - recline), 0.0, -0.12]),
        **_mirror("lowerleg01", [1.35, 0.0, 0.0]),
        **_mirror("upperarm01", [0.45 + recline, 0.0, -0.5]),
        "lowerarm01.L": [1.0 + 0.2 * s, 0.0, 0.0], "lowerarm01.R": [1.0, 0.0, 0.0],
        "neck01": [0.6 * recline, 0.0, 0.0], "head": [0.1 * s, 0.2 * s, 0.0],
    }


def lying(phase: float, knees: float, arch: float) -> Pose:
    """Supine (the caller turns the body face up), knees bent by ``knees``, the lower back
    arched by ``arch``, arms resting beside the body, head raised on a pillow."""
    s = float(np.sin(phase))
    return {
        **_mirror("upperleg01", [-knees / 2, 0.0, 0.0]),
        **_mirror("lowerleg01", [knees, 0.0, 0.0]),
        "spine03": [-arch, 0.0, 0.0],
        **_mirror("upperarm01", [-0.2, 0.5, -0.5]),
        "lowerarm01.L": [0.15 + 0.15 * s, 0.0, 0.0], "lowerarm01.R": [0.0, 0.0, 0.0],
        "neck01": [0.35, 0.0, 0.0], "head": [0.0, 0.3 * s, 0.0],
    }


def lean_on_table(phase: float, bend: float) -> Pose:
    """Standing, the spine bent forward by ``bend``, both palms down on a table in front."""
    s = float(np.sin(phase))
    return {
        **{bone: [bend / 3, 0.0, 0.0] for bone in ("spine03", "spine02", "spine01")},
        **_mirror("upperarm01", [0.5, 0.0, -0.3]),
        **_mirror("lowerarm02", [0.0, 0.6, 0.0]),
        **_mirror("wrist", [1.1, 0.0, 0.0]),
        "neck01": [0.1 * s, 0.0, 0.0], "head": [0.0, 0.25 * s, 0.0],
    }


def reach(phase: float, twist: float, hip: float) -> Pose:
    """Sitting on a stool (hips flexed by ``hip``), trunk bent and turned by ``twist``
    (positive: to the person's right), the right arm reaching forward-right, the left hand
    on the thigh."""
    s = float(np.sin(phase))
    pose = sit(phase, 0.0, hip)
    pose.update({
        "spine03": [0.15, twist / 2, 0.0], "spine02": [0.1, twist / 2, 0.0],
        "upperarm01.R": [1.05, 0.0, 0.1], "lowerarm01.R": [-0.05, 0.0, 0.0],
        "wrist.R": [0.4, 0.0, 0.0], "head": [0.1 * s, -0.2, 0.0],
    })
    return pose


def _palms_on_low_table(phase: float, lean: float, arms: float, neck: float) -> Pose:
    """The upper body of a person low down with both palms on a low table in front: the
    trunk leaning forward by ``lean``, the upper arms raised by ``arms``, the head looking
    about, the neck bent by ``neck``."""
    s = float(np.sin(phase))
    return {
        **{bone: [lean / 3, 0.0, 0.0] for bone in ("spine03", "spine02", "spine01")},
        **_mirror("upperarm01", [arms, 0.0, -0.3]), **_mirror("lowerarm02", [0.0, 0.6, 0.0]),
        **_mirror("wrist", [1.1, 0.0, 0.0]),
        "neck01": [neck + 0.1 * s, 0.0, 0.0], "head": [0.0, 0.25 * s, 0.0],
    }


def kneel(phase: float, lean: float) -> Pose:
    """On both knees, the shins flat on the floor and the toes pointed behind, the trunk
    leaning forward by ``lean`` from the hips, both palms down on a low table in front."""
    return {
        **_mirror("upperleg01", [-0.1 - lean / 2, 0.0, 0.0]),
        **_mirror("lowerleg01", [1.67 + lean / 2, 0.0, 0.0]), **_mirror("foot", [0.9, 0.0, 0.0]),
        **_palms_on_low_table(phase, lean, arms=0.6, neck=0.0),
    }


def squat(phase: float, lean: float) -> Pose:
    """Squatting on flat feet, knees apart, the trunk leaning forward by ``lean``, both
    palms down on a low table in front."""
    return {
        **_mirror("upperleg01", [-2.1, 0.0, -0.15]), **_mirror("lowerleg01", [2.4, 0.0, 0.0]),
        **_mirror("foot", [-0.3, 0.0, 0.0]), **_mirror("lowerarm01", [0.2, 0.0, 0.0]),
        **_palms_on_low_table(phase, lean, arms=0.9, neck=-0.2),
    }


def one_knee(phase: float, front: float, back: float) -> Pose:
    """On the right knee (its thigh ``back`` behind vertical, the shin flat on the floor),
    the left foot flat in front (hip flexed by ``front``, the shin upright), the left
    forearm held forward, the right arm hanging."""
    s = float(np.sin(phase))
    return {
        "upperleg01.L": [-front, 0.0, -0.1], "lowerleg01.L": [front, 0.0, 0.0],
        "upperleg01.R": [back, 0.0, 0.05], "lowerleg01.R": [np.pi / 2 - back, 0.0, 0.0],
        "foot.R": [0.9, 0.0, 0.0],
        "upperarm01.L": [0.5 + 0.1 * s, 0.0, -0.3], "lowerarm01.L": [1.0, 0.0, 0.0],
        "upperarm01.R": [0.1, 0.0, 0.6], "lowerarm01.R": [0.3 + 0.2 * s, 0.0, 0.0],
        "head": [0.1 * s, 0.2 * s, 0.0],
    }


def front_knee_hip(body: AnnyBody, phenotype: dict[str, float], back: float) -> float:
    """The front hip flexion of :func:`one_knee` at which the front sole is as low as the
    back knee, so that both rest on the floor (it depends on the legs' proportions)."""
    parts = np.asarray(body.vertex_parts)
    sole, knee = parts == "left_foot", np.isin(parts, ["right_thigh", "right_shin"])

    def gap(front: float) -> float:
        verts = posed(body, [one_knee(0.0, front, back)], phenotype)[0][0]
        return float(verts[sole, 2].min() - verts[knee, 2].min())

    return float(min(np.linspace(1.5, 1.9, 9), key=lambda front: abs(gap(front))))


def walk(phase: float, swing: float) -> Pose:
    """One instant of a gait cycle (``phase``), legs swinging by ``swing``, arms in
    counter-phase."""
    s, c = float(np.sin(phase)), float(np.cos(phase))
    knee = lambda p: 0.15 + 0.6 * max(0.0, float(np.sin(p + 1.2)))  # noqa: E731
    return {
        "upperleg01.L": [-swing * s, 0.0, 0.0], "upperleg01.R": [swing * s, 0.0, 0.0],
        "lowerleg01.L": [knee(phase), 0.0, 0.0], "lowerleg01.R": [knee(phase + np.pi), 0.0, 0.0],
        "foot.L": [0.15 * c, 0.0, 0.0], "foot.R": [-0.15 * c, 0.0, 0.0],
        "upperarm01.L": [-0.6 * swing * s, 0.0, -0.75],
        "upperarm01.R": [0.6 * swing * s, 0.0, 0.75],
        **_mirror("lowerarm01", [0.35, 0.0, 0.0]),
        "spine02": [0.05, 0.1 * s, 0.0],
    }


def gesture(phase: float) -> Pose:
    """Standing, talking with the hands: forearms up and moving, the head turning."""
    s, c = float(np.sin(phase)), float(np.cos(phase))
    return {
        "upperarm01.L": [0.3 + 0.2 * s, 0.0, -0.9], "upperarm01.R": [0.3 - 0.2 * c, 0.0, 0.9],
        "lowerarm01.L": [1.2 + 0.3 * c, 0.0, 0.0], "lowerarm01.R": [1.0 + 0.3 * s, 0.0, 0.0],
        "head": [0.0, 0.3 * s, 0.0], "upperleg01.L": [0.0, 0.0, -0.05],
        "upperleg01.R": [0.0, 0.0, 0.05],
    }
