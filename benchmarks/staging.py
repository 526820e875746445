"""The benchmark's interactions: a posed ground-truth body sequence per kind and the
furniture built around it, so that the body touches the furniture without penetrating it.
Everything is in the body's frame: facing -y, left +x, floor at z = 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation
from trimesh.transformations import rotation_matrix

from prox_engine.body.anny_body import AnnyBody
from prox_engine.synthetic import chair, open_box, transform

from . import poses
from .poses import body_points, phases, posed, stature, to_floor

GAP = 0.003  # furniture surfaces stand this far off the body they support
CUSHION = (0.02, 0.04)  # soft seats and mattresses: the body sinks this far into the scan
HANDS = ["left_hand", "right_hand"]
FEET = ["left_foot", "right_foot"]
LEGS = ["left_shin", "right_shin", *FEET]


@dataclass
class Staging:
    """A posed body sequence and the furniture built around it, in the body's frame."""

    vertices: np.ndarray  # (F, V, 3)
    keypoints: np.ndarray  # (F, 118, 3)
    furniture: list[trimesh.Trimesh]
    contacts: list[str]  # the contact parts (AnnyBody.contact_parts) that touch it


def stage_sit(body: AnnyBody, phenotype: dict[str, float], frames: int,
              rng: np.random.Generator) -> Staging:
    """Upright on a chair: seat under the buttocks and thighs, backrest at the back."""
    lean = rng.uniform(-0.12, -0.04)  # leaning back a little, against the backrest
    hip = poses.seated_hip(body, phenotype, lambda h: poses.sit(0.0, lean, h))
    verts, kps, _ = to_floor(*posed(body, [poses.sit(p, lean, hip)
                                           for p in phases(frames, rng)], phenotype))
    seat = chair(*body_points(body, verts), width=rng.uniform(0.45, 0.55),
                 cushion=rng.uniform(*CUSHION))
    return Staging(verts, kps, [seat], ["gluteus", "thighs", "back", *FEET])


def stage_legup(body: AnnyBody, phenotype: dict[str, float], frames: int,
                rng: np.random.Generator) -> Staging:
    """On a chair, the right leg stretched out with the heel on a low table in front."""
    lean, lift, knee = rng.uniform(-0.12, -0.04), rng.uniform(-0.1, 0.1), rng.uniform(0.2, 0.5)
    pose_at = lambda p, h: poses.leg_up(p, lean, h, lift, knee)  # noqa: E731
    hip = poses.seated_hip(body, phenotype, lambda h: pose_at(0.0, h))
    verts, kps, _ = to_floor(*posed(body, [pose_at(p, hip) for p in phases(frames, rng)],
                                    phenotype))
    points, parts = body_points(body, verts)
    seat = chair(points, parts, width=rng.uniform(0.45, 0.55), cushion=rng.uniform(*CUSHION))
    low = table_under(points, parts == "right_foot", 0.0, rng)
    return Staging(verts, kps, [seat, *low], ["gluteus", "thighs", "back", *FEET])


def stage_sofa(body: AnnyBody, phenotype: dict[str, float], frames: int,
               rng: np.random.Generator) -> Staging:
    """Reclined by 25-35 degrees on a sofa: a flat backrest tilted with the trunk against
    the back, the seat under the buttocks and thighs, an armrest close to one side."""
    recline = np.radians(rng.uniform(25.0, 35.0))
    orient = (-recline, 0.0, 0.0)
    hip = poses.seated_hip(body, phenotype, lambda h: poses.sofa(0.0, recline, h), orient)
    pose_list = [poses.sofa(p, recline, hip) for p in phases(frames, rng)]
    verts, kps, shift = to_floor(*posed(body, pose_list, phenotype, orient))
    points, parts = body_points(body, verts)
    front = points[np.isin(parts, LEGS), 1].max() + 0.01
    behind = points[:, 1] > front
    arm_top = points[behind & (np.abs(points[:, 0]) < 0.2), 2].min() + rng.uniform(0.18, 0.25)
    low = (points[:, 1] > front - 0.1) & (points[:, 2] < arm_top + 0.02)
    near = rng.choice([-1, 1])
    x = {side: side * ((side * points[low, 0]).max()
                       + (rng.uniform(0.02, 0.06) if side == near else rng.uniform(0.5, 0.9)))
         for side in (-1, 1)}
    seat_top = (points[behind & (points[:, 0] > x[-1]) & (points[:, 0] < x[1]), 2].min() - GAP
                + rng.uniform(*CUSHION))
    arm_width = rng.uniform(0.15, 0.25)
    outer = (x[-1] - arm_width, x[1] + arm_width)

    # The backrest in the trunk frame (upright), then tilted back with the body.
    trunk = rotation_matrix(-recline, [1.0, 0.0, 0.0])
    trunk[:3, 3] = shift
    upright = transform(points, np.linalg.inv(trunk))
    above = (points[:, 2] > seat_top) & (points[:, 0] > outer[0]) & (points[:, 0] < outer[1])
    back = upright[above, 1].max() + GAP
    # Its front bottom edge 3 cm into the seat, its top around the shoulders.
    bottom = (seat_top - 0.03 - shift[2] + np.sin(recline) * back) / np.cos(recline)
    top = transform(kps[0, [2, 5]], np.linalg.inv(trunk))[:, 2].max() + rng.uniform(0.0, 0.15)
    backrest = open_box([outer[1] - outer[0], 0.2, top - bottom],
                        [sum(outer) / 2, back + 0.1, (top + bottom) / 2], bottom=True)
    backrest.apply_transform(trunk)
    rear = backrest.bounds[1, 1]
    seat = open_box([x[1] - x[-1], rear - front, seat_top],
                    [(x[1] + x[-1]) / 2, (rear + front) / 2, seat_top / 2])
    arms = [open_box([arm_width, rear - front + 0.05, arm_top],
                     [x[side] + side * arm_width / 2, (rear + front - 0.05) / 2, arm_top / 2])
            for side in (-1, 1)]
    return Staging(verts, kps, [seat, backrest, *arms], ["gluteus", "thighs", "back", *FEET])


def stage_bed(body: AnnyBody, phenotype: dict[str, float], frames: int,
              rng: np.random.Generator) -> Staging:
    """Lying on a bed, on the back (knees a little bent) or on either side (knees bent
    more), head raised on a pillow, sunk 2-4 cm into the mattress."""
    side = rng.choice([0, -1, 1])  # 0: on the back
    knees = rng.uniform(0.0, 0.5) if side == 0 else rng.uniform(0.5, 1.1)
    height, sink = rng.uniform(0.45, 0.6), rng.uniform(*CUSHION)
    arch = 0.1 * phenotype["gender"] if side == 0 else 0.0
    supine = Rotation.from_rotvec([-np.pi / 2, 0.0, 0.0])
    orient = (Rotation.from_rotvec([0.0, side * np.pi / 2, 0.0]) * supine).as_rotvec()
    pose_list = [poses.lying(p, knees, arch) for p in phases(frames, rng)]
    verts, kps, _ = to_floor(*posed(body, pose_list, phenotype, orient),
                             lift=height + GAP - sink)
    points, _ = body_points(body, verts)
    lo, hi = points.min(0), points.max(0)
    half = np.abs(points[:, 0]).max() + rng.uniform(0.1, 0.35)
    foot, head = lo[1] - rng.uniform(0.1, 0.3), hi[1] + rng.uniform(0.1, 0.2)
    bed = [open_box([2 * half, head - foot, height], [0.0, (foot + head) / 2, height / 2])]
    board = height + rng.uniform(0.4, 0.7)
    bed.append(open_box([2 * half, 0.06, board], [0.0, head + 0.03, board / 2]))
    start = kps[:, [2, 5], 1].max() + 0.04  # the pillow begins above the shoulders
    under = (points[:, 1] > start) & (np.abs(points[:, 0]) < 0.3)
    pillow = points[under, 2].min() - GAP - height
    if pillow > 0.03:
        bed.append(open_box([0.6, head - start, pillow],
                            [0.0, (head + start) / 2, height + pillow / 2]))
    return Staging(verts, kps, bed, ["back", "gluteus"] if side == 0 else ["thighs"])


def stage_table(body: AnnyBody, phenotype: dict[str, float], frames: int,
                rng: np.random.Generator) -> Staging:
    """Standing, leaning forward with both palms on a table."""
    bend = rng.uniform(0.55, 0.85)
    verts, kps, _ = to_floor(*posed(body, [poses.lean_on_table(p, bend)
                                           for p in phases(frames, rng)], phenotype))
    points, parts = body_points(body, verts)
    table = table_under(points, np.isin(parts, HANDS), 0.0, rng)
    return Staging(verts, kps, table, [*HANDS, *FEET])


def stage_reach(body: AnnyBody, phenotype: dict[str, float], frames: int,
                rng: np.random.Generator) -> Staging:
    """On a stool, reaching forward-right to put the right hand on a table."""
    twist = rng.uniform(0.1, 0.5)
    hip = poses.seated_hip(body, phenotype, lambda h: poses.reach(0.0, twist, h))
    verts, kps, _ = to_floor(*posed(body, [poses.reach(p, twist, hip)
                                           for p in phases(frames, rng)], phenotype))
    points, parts = body_points(body, verts)
    stool = chair(points, parts, width=rng.uniform(0.35, 0.45), backrest=False)
    hand = parts == "right_hand"
    heading = np.arctan2(points[hand, 0].mean(), -points[hand, 1].mean())
    table = table_under(points, hand, heading, rng)
    return Staging(verts, kps, [stool, *table], ["gluteus", "thighs", "right_hand", *FEET])


def stage_walk(body: AnnyBody, phenotype: dict[str, float], frames: int,
               rng: np.random.Generator) -> Staging:
    """Walking along -y, 8 frames a gait cycle, a foot on the floor in every frame."""
    step, swing = 2 * np.pi / 8, rng.uniform(0.3, 0.45)
    verts, kps = posed(body, [poses.walk(p, swing) for p in phases(frames, rng, step)],
                       phenotype)
    cycle = 0.8 * stature(body, phenotype)  # stride of two steps, metres
    shift = np.zeros((frames, 1, 3))
    shift[:, 0, 1] = -cycle * step / (2 * np.pi) * np.arange(frames)
    shift[:, 0, 2] = -verts[:, :, 2].min(1)
    verts, kps = verts + shift, kps + shift
    centre = np.array([*verts[:, :, :2].mean((0, 1)), 0.0])
    return Staging(verts - centre, kps - centre, [], FEET)


def stage_wall(body: AnnyBody, phenotype: dict[str, float], frames: int,
               rng: np.random.Generator) -> Staging:
    """Standing and gesturing with the back 15-30 cm from a wall, which nothing touches:
    the scene must not pull the person onto it."""
    verts, kps, _ = to_floor(*posed(body, [poses.gesture(p) for p in phases(frames, rng)],
                                    phenotype))
    points, _ = body_points(body, verts)
    front = points[:, 1].max() + rng.uniform(0.15, 0.3)
    wall = open_box([3.0, 0.12, 2.6], [points[:, 0].mean(), front + 0.06, 1.3])
    return Staging(verts, kps, [wall], FEET)


# Kneeling variants with both palms on a low table: the pose, the range of its forward
# lean and the contact parts that touch something.
ON_A_LOW_TABLE = {"knees": (poses.kneel, (0.2, 0.45), HANDS),
                  "squat": (poses.squat, (0.3, 0.6), [*HANDS, *FEET])}
KNEELING = (*ON_A_LOW_TABLE, "one knee")


def stage_kneel(body: AnnyBody, phenotype: dict[str, float], frames: int,
                rng: np.random.Generator) -> Staging:
    """On the floor: one of the :data:`KNEELING` variants, drawn."""
    return kneeling(body, phenotype, frames, rng, str(rng.choice(KNEELING)))


def kneeling(body: AnnyBody, phenotype: dict[str, float], frames: int,
             rng: np.random.Generator, variant: str) -> Staging:
    """Kneeling on both knees with the palms on a low table, squatting on flat feet with
    the palms on a low table, or down on one knee with nothing else touched."""
    if variant == "one knee":
        back = rng.uniform(0.0, 0.15)
        front = poses.front_knee_hip(body, phenotype, back)
        verts, kps, _ = to_floor(*posed(body, [poses.one_knee(p, front, back)
                                               for p in phases(frames, rng)], phenotype))
        return Staging(verts, kps, [], ["left_foot"])
    pose_at, leans, contacts = ON_A_LOW_TABLE[variant]
    lean = rng.uniform(*leans)
    verts, kps, _ = to_floor(*posed(body, [pose_at(p, lean) for p in phases(frames, rng)],
                                    phenotype))
    points, parts = body_points(body, verts)
    low = table_under(points, np.isin(parts, HANDS), 0.0, rng)
    return Staging(verts, kps, low, contacts)


STAGES = {"sit": stage_sit, "sofa": stage_sofa, "bed": stage_bed, "table": stage_table,
          "reach": stage_reach, "walk": stage_walk, "wall": stage_wall,
          "kneel": stage_kneel, "legup": stage_legup}


def table_under(points: np.ndarray, touching: np.ndarray, heading: float,
                rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """A table whose top is just under the ``touching`` points, lying toward ``heading``
    (radians about z from -y), its near edge just clear of the rest of the body."""
    turn = rotation_matrix(heading, [0.0, 0.0, 1.0])
    p = transform(points, np.linalg.inv(turn))  # the table toward -y
    top, thickness = p[touching, 2].min() - GAP, rng.uniform(0.03, 0.05)
    width, depth = rng.uniform(1.0, 1.5), rng.uniform(0.6, 0.9)
    centre = p[touching, 0].mean()
    across = np.abs(p[:, 0] - centre) < width / 2
    cut = across & (p[:, 2] < top) & (p[:, 2] > top - thickness - 0.02)  # the slab's height
    resting = touching & (p[:, 2] < top + 0.01)
    edge = min(p[cut, 1].min() - 0.01 if cut.any() else np.inf, p[resting, 1].max() + 0.05)
    if not (p[resting, 1] < edge).any():
        raise ValueError("the pose leaves the hand off the table")
    slab, *legs = table(centre - width / 2, centre + width / 2, edge - depth, edge, top,
                        thickness)
    legs = [leg for leg in legs if not _blocked(leg, p)]  # a leg in the body's way is lost
    return [m.apply_transform(turn) for m in (slab, *legs)]


def table(x0: float, x1: float, y0: float, y1: float, top: float,
          thickness: float) -> list[trimesh.Trimesh]:
    """A closed table top over [x0, x1] x [y0, y1] and four legs at its corners."""
    slab = open_box([x1 - x0, y1 - y0, thickness], [(x0 + x1) / 2, (y0 + y1) / 2,
                                                    top - thickness / 2], bottom=True)
    leg = top - thickness
    return [slab] + [open_box([0.05, 0.05, leg], [x, y, leg / 2])
                     for x in (x0 + 0.06, x1 - 0.06) for y in (y0 + 0.06, y1 - 0.06)]


def _blocked(mesh: trimesh.Trimesh, points: np.ndarray, margin: float = 0.03) -> bool:
    lo, hi = mesh.bounds
    return bool(((points > lo - margin) & (points < hi + margin)).all(1).any())
