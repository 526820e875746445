"""Scene-aware depth: keypoints fix a body only up to a scale about the camera centre (a
taller person farther away projects to the same pixels), which is why monocular fits are
off by tens of centimetres in depth. Scaling a fitted body about the camera keeps its
reprojection exactly, so the scale can be searched globally, scoring each candidate by how
well the body touches the scene without entering it. Gradient descent on the PROX terms
alone only sees the scene near the body's current depth and stalls in furniture.

Besides contact and penetration, a body must be supported: something under it (feet on
the floor, buttocks on a seat, a back on a mattress) rests on an upward-facing surface.
Scaling about a camera above that surface lifts the body off it (smaller) or sinks it in
(larger), so support and penetration bracket the scale from both sides, whereas a single
contact part may touch some other surface at a wrong scale (a sole against a table leg,
the thighs against a table's front edge)."""
from __future__ import annotations

import math
from collections.abc import Callable

import torch

from .keypoints import ANKLES, HIDDEN, HIPS, KNEES, MID_HIP, NECK, SEEN, TOES, toes_unseen
from .losses import gmof, nearest_contacts, part_vertices
from .scene import Scene

SCALES = torch.exp(torch.linspace(math.log(0.7), math.log(1.4), 97))
PENETRATION_SCALE = 0.02  # a vertex 2 cm inside counts fully as penetrating
PENETRATION_WEIGHT = 10.0  # 10 % of the body inside the scene outweighs every contact
SCALE_SIGMA = 0.06  # spread of adult body size around the fitted (prior-mean) size
SUPPORT_WEIGHT = 1.0  # an unsupported body costs as much as missing every contact part
DOWNWARD = -0.5  # body vertices whose world normal points this far down can rest on a surface
UPWARD = 0.7  # scene surfaces whose normal points this far up can carry a body
# Support is met by the contact parts that can carry a body (a seated body's buttocks,
# thighs and back, the feet) or by the body's lowest vertices (within LOWEST of its height
# span: a lying body's side, a kneeling body's shins) resting on a surface, and a quarter
# of it (LOWEST_SHARE) only by the lowest vertices: hands never carry a body, and a tall
# person leaning on a table, fitted too small, would otherwise "sit" on it with the feet
# in the air. More than about a third makes a seated body whose feet were fitted a little
# high sink until they reach the floor.
LOWEST = 0.15
LOWEST_SHARE = 0.25
# ... but a body on its feet (every thigh and shin of the fit within FEET_CARRY_LEG of
# plumb) with a foot the detector clearly saw is carried by its lowest vertices alone, in
# the search that places it (Fitter._scale_search): hands on a table, or thighs against
# its edge, do not hold up a standing person. Held-out seed 100's table leaner (1.88 m,
# knees hidden by the table, feet in view), fitted at the mean size, floated 25-45 cm over
# the floor, held by the table: three frames 400-565 mm off. Not in the choices between
# starts and restarts, where it made a standing start lose to one kneeling on the table.
FEET_CARRY_LEG = math.radians(45)
CARRYING_PARTS = ("back", "gluteus", "thighs", "left_foot", "right_foot")
# The search evaluates the scales CHUNK at a time, nearest the fitted size first, and
# skips those whose size prior and joints' rays alone exceed the best total found
# (bounded_search): about half of them, the same pick. A first round of FIRST_CHUNK finds
# a total that spares the next rounds' scales their dearer terms sooner (see SLACK).
CHUNK = 16
FIRST_CHUNK = 8
# A scale whose cost exceeds by more than SLACK what it may cost to beat the lowest total
# evaluated cannot win (sums in another order round differently): its dearer terms are not
# worked out (best_scale's cost_at).
SLACK = 1e-4
# Penetration and support are judged on every third body vertex (about 2 cm apart on an
# adult): 97 scales of the whole mesh were a fifth of a frame's time.
STRIDE = 3
# A foot's toes turn about its ankle, and the scene stages bend a foot out of a floor, but
# they do not move the body along its rays: the toes' penetration (foot vertices more than
# TOE_REACH from the ankle on the standing mean body) is not counted, nor, on a kneeler,
# are the seen toes' keypoints asked to be in front of the scan. A kneeler fitted with the
# toes pointing down was otherwise shrunk toward the camera until they left the floor
# (seed 82's upright leg: seen toes 5-14 cm behind the floor, the body 5-7 % too near); a
# seated body scaled too large still sinks its heels, and a walker placed too far its toes.
TOE_REACH = 0.10
# A scan registered to the camera 1-3 cm and a degree off, or a soft cushion, puts
# correctly placed soles a few centimetres into the floor: shallower penetration is not
# counted.
PENETRATION_MARGIN = 0.02
# Joints the detector clearly saw are in front of the scan: a body scaled until they are
# behind a bed, wall or table from the camera costs this much (all of them hidden) on top.
VISIBILITY_WEIGHT = 1.0
# ... and legs it reports faintly or not at all (knees and ankles under
# keypoints.HIDDEN, where the image shows them) are likely behind something: a body
# whose guessed legs are in view costs this much (all of them in view) on top. A fit
# that raises a kneeler's hidden knees above the low table in front of them, or a
# seated reacher's above the table, pays it at every scale, and the start choice sees
# it. Over the 1080 frames of the tuning and spent seeds it moved 16 by more than 15 mm,
# 12 better (kneel -11.9 mm, reach -6.1); at 1.0 it threw two seated frames 600 mm off.
FAINT_WEIGHT = 0.5
# A body through a surface thinner than itself (an arm through a 12 cm partition, a
# tabletop through the thighs) has only a ring of its surface vertices inside it, but its
# axis (the collision spheres' centres, inside arms, legs and trunk) is inside. Each
# centre more than PENETRATION_MARGIN inside counts as a share, weighted as the vertices.
AXIS_WEIGHT = PENETRATION_WEIGHT


# A foot whose toes the detector does not see has the pose prior's neutral ankle, its toes
# at right angles to the shin. On a kneeling leg (the thigh within KNEELING_THIGH of
# straight down, the shin within FLAT_SHIN of the floor) that puts the toes through the
# floor at the true depth and, at a nearer one, under a body floating on them: the search
# shrank kneelers toward the camera by 3-12 %. Such a foot is searched pointed along its
# shin, as a kneeler's lies. (A lying body's legs are flat too; pointing its feet cost
# the bed kind 4 mm.)
FLAT_SHIN = math.radians(35)
KNEELING_THIGH = math.radians(45)


# A standing body's size and depth are settled by its feet on the floor: for a body whose
# thighs and shins all hang within STANDING_LEG of plumb, on knees and ankles the detector
# did not report as hidden (legs guessed under a table may hang plumb under a seated
# reacher; hips are its least reliable joints), the search counts every contact part but
# the feet (STANDING_PARTS) as missing, whatever it nears. Counting them, it moved people
# standing before a wall 1.2-2.6 % farther, toward it, to touch it with the back, the
# buttocks or the hands (held-out seeds 73, 76 and 79 lost the wall kind to rgb). The
# feet keep the weight they have among all the parts: counted alone, their share weighed
# 3.5 times as much against penetration, support and size, and held-out seed 80's walker
# lost 20 mm.
STANDING_LEG = math.radians(30)
STANDING_PARTS = ("left_foot", "right_foot")


def _slope(keypoints: torch.Tensor, up: torch.Tensor, start: list[int], end: list[int]
           ) -> torch.Tensor:
    """Sines of the elevation (B, len(start)) of the segments from ``start`` to ``end``
    in BODY_25 ``keypoints`` (B, 25, 3); ``up`` world up in their frame."""
    segment = keypoints[:, end] - keypoints[:, start]
    return (segment @ up) / segment.norm(dim=-1).clamp_min(1e-9)


def _elevations(keypoints: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Sines of the elevation (B, 2) of the thighs (hip to knee) and shins (knee to
    ankle), right leg then left, in BODY_25 ``keypoints`` (B, 25, 3); ``up`` world up in
    their frame."""
    return _slope(keypoints, up, HIPS, KNEES), _slope(keypoints, up, KNEES, ANKLES)


def _plumb_legs(keypoints: torch.Tensor, up: torch.Tensor, within: float) -> torch.Tensor:
    """(B,) bool: every thigh and shin of the fitted BODY_25 ``keypoints`` (B, 25, 3)
    within ``within`` (rad) of hanging plumb, ``up`` world up in their frame."""
    return (torch.cat(_elevations(keypoints, up), 1) < -math.cos(within)).all(1)


def standing_legs(keypoints: torch.Tensor, detected: torch.Tensor, up: torch.Tensor
                  ) -> torch.Tensor:
    """(B,) bool: every thigh and shin of the fitted BODY_25 ``keypoints`` (B, 25, 3)
    within STANDING_LEG of hanging plumb (``up`` world up in their frame), and no knee or
    ankle reported hidden (``detected`` (B, 25), the detector's confidences, at least
    HIDDEN)."""
    seen = (detected[:, [*KNEES, *ANKLES]] >= HIDDEN).all(1)
    return seen & _plumb_legs(keypoints, up, STANDING_LEG)


def feet_carried(keypoints: torch.Tensor, detected: torch.Tensor, up: torch.Tensor
                 ) -> torch.Tensor:
    """(B,) bool: every thigh and shin of the fitted BODY_25 ``keypoints`` (B, 25, 3)
    within FEET_CARRY_LEG of hanging plumb (``up`` world up in their frame), and an ankle
    or a toe clearly seen (``detected`` (B, 25), the detector's confidences, over SEEN)."""
    foot_seen = (detected[:, [*ANKLES, *TOES]] > SEEN).any(1)
    return foot_seen & _plumb_legs(keypoints, up, FEET_CARRY_LEG)


def lying(keypoints: torch.Tensor, up: torch.Tensor, within: float) -> torch.Tensor:
    """(B,) bool: the trunk (mid-hip to neck) of the fitted BODY_25 ``keypoints`` (B, 25,
    3) within ``within`` (rad) of level, ``up`` world up in their frame."""
    return _slope(keypoints, up, [MID_HIP], [NECK])[:, 0].abs() < math.sin(within)


def standing_counts(standing: torch.Tensor, parts: torch.Tensor) -> torch.Tensor:
    """(B, P) bool: the contact parts the search counts for each body: all of them, but
    for the ``standing`` (B,) bool bodies only ``parts`` (P,) bool (:data:`STANDING_PARTS`)."""
    return parts[None] | ~standing[:, None]


def kneeling_legs(keypoints: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """(B, 2) bool, per leg (right, left): kneeling (see :data:`FLAT_SHIN`) in the fitted
    BODY_25 ``keypoints`` (B, 25, 3), ``up`` world up in their frame."""
    thigh, shin = _elevations(keypoints, up)
    return (shin.abs() < math.sin(FLAT_SHIN)) & (thigh < -math.cos(KNEELING_THIGH))


def unseen_feet_on_kneeling_legs(keypoints: torch.Tensor, seen: torch.Tensor,
                                 up: torch.Tensor) -> torch.Tensor:
    """(B, 2) bool, per leg (right, left): neither of the foot's toes clearly seen
    (``seen`` (B, 25); a seen heel does not turn the foot) and the leg kneeling (see
    :data:`FLAT_SHIN`) in the fitted BODY_25 ``keypoints`` (B, 25, 3), ``up`` world up in
    their frame."""
    return toes_unseen(seen) & kneeling_legs(keypoints, up)  # a kneeler's heel is in view


def kneelers_toes(keypoints: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """(B, 25) bool: the toes (keypoints.TOES) of the bodies with a kneeling leg (see
    :data:`FLAT_SHIN`) in the fitted BODY_25 ``keypoints`` (B, 25, 3), ``up`` world up in
    their frame: the scale search does not ask them to be in view (see :data:`TOE_REACH`)."""
    toes = torch.zeros(keypoints.shape[:2], dtype=torch.bool)
    toes[:, TOES] = True
    return toes & kneeling_legs(keypoints, up).any(1, keepdim=True)


def toe_vertices(parts: list[str], rest: torch.Tensor, ankles: torch.Tensor) -> torch.Tensor:
    """(2, V) bool, per foot (right, left): its vertices on a body at rest (``rest`` (V,
    3), per-vertex ``parts``) more than TOE_REACH from its ankle (``ankles`` (2, 3), right
    and left, as keypoints.ANKLES)."""
    return torch.stack([torch.tensor([p == side for p in parts])
                        & ((rest - ankle).norm(dim=1) > TOE_REACH)
                        for side, ankle in zip(("right_foot", "left_foot"), ankles)])


def carrying_vertices(contact_parts: dict[str, torch.Tensor], count: int) -> torch.Tensor:
    """(``count``,) bool: the contact vertices of the parts that can carry a body."""
    return part_vertices(contact_parts, CARRYING_PARTS, count)


def sampled_vertices(scene_vertices: torch.Tensor) -> torch.Tensor:
    """The vertices (indices) that :func:`best_scale` judges penetration and support on:
    every STRIDE-th of the ``scene_vertices`` ((V,) bool)."""
    return torch.nonzero(scene_vertices).flatten()[::STRIDE]


def normal_vertices(scene_vertices: torch.Tensor, contact_parts: list[torch.Tensor]
                    ) -> torch.Tensor:
    """The vertices (sorted indices) whose normals :func:`best_scale` reads: the
    :func:`sampled_vertices` and the ``contact_parts``' (two fifths of anny's mesh)."""
    return torch.unique(torch.cat([sampled_vertices(scene_vertices), *contact_parts]))


@torch.no_grad()
def best_scale(vertices: torch.Tensor, normals: torch.Tensor, scene_vertices: torch.Tensor,
               carrying: torch.Tensor, contact_parts: list[torch.Tensor], scene: Scene,
               use_contact: bool, use_penetration: bool, rho: float, max_angle_deg: float,
               max_distance: float, use_support: bool = True,
               seen_joints: list[torch.Tensor] | None = None,
               toes: torch.Tensor | None = None, axes: torch.Tensor | None = None,
               faint_joints: list[torch.Tensor] | None = None,
               ceilings: torch.Tensor | None = None,
               counted_parts: torch.Tensor | None = None,
               sizes: torch.Tensor | None = None, feet: torch.Tensor | None = None,
               sinks: torch.Tensor | None = None, *,
               size_weight: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per frame, the scale about the camera centre that minimises the share of contact
    parts not touching the scene (each part by its best vertex) plus the share of
    vertices more than PENETRATION_MARGIN inside it plus, with ``use_support``, how far
    the body's underside is from resting on an upward-facing surface, plus the share of
    ``seen_joints`` (per frame, (J, 3) camera frame: those the detector clearly saw) that
    are behind the scan from the camera, plus the share of ``faint_joints`` (likewise:
    those it reported faintly) in front of it, plus a weak prior on body size. The ``toes``
    ((V,) bool, :func:`toe_vertices`) do not count as penetrating; the ``axes`` ((B, S,
    3), points inside the body: its collision spheres' centres) do (AXIS_WEIGHT).
    ``vertices`` and ``normals`` (B, V, 3) in camera coordinates (the normals read only at
    :func:`normal_vertices`), ``scene_vertices`` (V,) bool,
    ``carrying`` (V,) bool (:func:`carrying_vertices`), ``contact_parts`` vertex indices
    per part, of which a body counts those ``counted_parts`` ((B, P) bool;
    :func:`standing_counts`) and the others as missing. The size prior, weighted
    ``size_weight``, reads each body's size at a scale as ``sizes`` ((B,); without, 1)
    times the scale (:func:`size_prior`).
    The ``feet`` ((B,) bool, :func:`feet_carried`) bodies rest only on their lowest
    vertices (FEET_CARRY_LEG); each body's vertices may sink its ``sinks`` ((B,) m)
    deeper than PENETRATION_MARGIN before they count as penetrating.
    Returns (B,) scales and (B,) their costs without the size prior (0: every part
    touches, nothing enters, the body rests on a surface): how well the body can meet the
    scene at all, comparable between bodies fitted at different sizes. Scales that cannot
    win are not evaluated (:func:`bounded_search`), nor those whose total (cost and size
    prior) cannot go under the body's ``ceilings`` ((B,)): a body whose total cannot
    returns one over its ceiling, or scale 1 and an infinite cost. All bodies' scales are
    evaluated together, a round of the search at a time (the start choice searches up to
    26 bodies at once in batches: one call of each scene query per body and round cost a
    fifth of the search)."""
    sizes = torch.ones(len(vertices)) if sizes is None else sizes
    margins = PENETRATION_MARGIN + (torch.zeros(len(vertices)) if sinks is None else sinks)
    prior = size_prior(SCALES, size_weight, sizes[:, None])  # (B, 97)
    sampled = sampled_vertices(scene_vertices)
    placed, carrying = vertices[:, sampled], carrying[sampled]
    counted = torch.ones(len(sampled)) if toes is None else ~toes[sampled]
    every_part = torch.cat(contact_parts) if contact_parts else torch.zeros(0, dtype=torch.long)
    touching, facing = vertices[:, every_part], normals[:, every_part]  # one lookup for all
    part_sizes = [len(ids) for ids in contact_parts]
    rays = torch.zeros(len(vertices), len(SCALES))  # seen joints behind the scan, faint in view
    if seen_joints is not None:
        rays = rays + VISIBILITY_WEIGHT * _ray_shares(seen_joints, scene, behind=True)
    if faint_joints is not None:
        rays = rays + FAINT_WEIGHT * _ray_shares(faint_joints, scene, behind=False)
    undersides = ([_underside(placed[b], normals[b, sampled], carrying, scene)
                   for b in range(len(vertices))] if use_support else [])

    def penetration(bodies: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        depth = torch.relu(-scene.signed_distance(scales * placed[bodies])
                           - margins[bodies, None])
        return PENETRATION_WEIGHT * ((depth / PENETRATION_SCALE).clamp(max=1.0) * counted
                                     ).mean(1)

    def through(bodies: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        inside = scene.signed_distance(scales * axes[bodies]) < -PENETRATION_MARGIN
        return AXIS_WEIGHT * inside.float().mean(1)

    def missing(bodies: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        nearest = nearest_contacts(scales * touching[bodies], facing[bodies], part_sizes,
                                   scene, max_angle_deg, max_distance)
        misses = _miss(nearest, rho).T
        if counted_parts is not None:
            misses = torch.where(counted_parts[bodies].T, misses, 1.0)
        return misses.mean(0)

    def unsupported(bodies: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        share = LOWEST_SHARE if feet is None else torch.where(feet[bodies], 1.0, LOWEST_SHARE)
        return SUPPORT_WEIGHT * _unsupported(placed[bodies], scales[:, 0],
                                             [undersides[b] for b in bodies.tolist()],
                                             scene, rho, share)

    # summed in this order, worked out cheapest first
    terms = [term for term, used in ((penetration, use_penetration),
                                     (through, use_penetration and axes is not None),
                                     (missing, use_contact and bool(contact_parts)),
                                     (unsupported, use_support)) if used]
    cheapest_first = sorted(terms, key=[unsupported, through, missing, penetration].index)

    def cost_at(bodies: torch.Tensor, picked: torch.Tensor, limits: torch.Tensor
                ) -> torch.Tensor:
        """Contact, penetration and support costs (R,) of the ``bodies`` (R,) at
        SCALES[picked] (R,); inf where the terms worked out first already exceed the
        ``limits`` (R,): the others, all >= 0, are not worked out there."""
        scales = SCALES[picked, None, None]
        found = {}
        partial, rows = torch.zeros(len(picked)), torch.arange(len(picked))
        for term in cheapest_first:
            found[term] = torch.zeros(len(picked)).index_put_(
                (rows,), term(bodies[rows], scales[rows]))
            partial[rows] += found[term][rows]
            rows = rows[partial[rows] <= limits[rows]]
        cost = torch.zeros(len(picked))
        for term in terms:
            cost = cost + found[term]
        return torch.full_like(cost, math.inf).index_put_((rows,), cost[rows])

    ceilings = torch.full((len(vertices),), math.inf) if ceilings is None else ceilings
    best, lowest_cost = [], []
    for b, (picked, cost) in enumerate(bounded_search(cost_at, rays, prior, ceilings)):
        if len(picked) == 0:
            best.append(torch.tensor(1.0))
            lowest_cost.append(torch.tensor(math.inf))
            continue
        pick = int((cost + prior[b, picked]).argmin())
        best.append(SCALES[picked[pick]])
        lowest_cost.append(cost[pick])
    return torch.stack(best), torch.stack(lowest_cost)


def size_prior(scales: torch.Tensor, weight: float, sizes: torch.Tensor | None = None
               ) -> torch.Tensor:
    """The weak prior on body size, weighted ``weight`` (see FitConfig.scale_size_weight),
    of a body scaled by ``scales`` whose size is ``sizes`` (1 without) times the size the
    prior centres on (the prior-mean body's, or a sequence's anchor's: Fitter._sizes)."""
    size = scales if sizes is None else scales * sizes
    return weight * (torch.log(size) / SCALE_SIGMA) ** 2 / 2


def bounded_search(cost_at: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
                   rays: torch.Tensor, prior: torch.Tensor, ceilings: torch.Tensor
                   ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per body, the indices into SCALES (ascending) at which the search evaluates
    ``cost_at`` (bodies (R,), indices (R,), limits (R,) -> (R,) costs >= 0 of contact,
    penetration and support, or inf where over the limit: the most each scale can cost and
    still beat the lowest total evaluated) and their costs with the body's ``rays`` ((B,
    97)) added. The other terms being >= 0, ``rays`` plus the size ``prior`` ((97,), or
    (B, 97) per body) bounds each scale's total from below: each body's scales are
    evaluated in the order of that bound, FIRST_CHUNK and then CHUNK at a time, and those
    whose bound exceeds the lowest total found, or the body's ``ceilings`` (B,), are not,
    since they cannot win; each round evaluates every body's next chunk in one call. The
    same pick as evaluating every scale, where it is under the ceiling; none (empty) where
    no bound is."""
    prior = prior.expand_as(rays)
    bound = rays + prior
    sizes = [FIRST_CHUNK, *[CHUNK] * math.ceil((len(SCALES) - FIRST_CHUNK) / CHUNK)]
    sizes[-1] -= sum(sizes) - len(SCALES)
    chunks = [bound[b].argsort().split(sizes) for b in range(len(bound))]
    evaluated = [torch.tensor(math.inf) for _ in chunks]  # the lowest total evaluated
    picked: list[list[torch.Tensor]] = [[] for _ in chunks]
    costs: list[list[torch.Tensor]] = [[] for _ in chunks]
    running = list(range(len(chunks)))
    for round_ in range(len(sizes)):
        asked = [(b, chunks[b][round_][bound[b, chunks[b][round_]]
                                       <= torch.minimum(evaluated[b], ceilings[b])])
                 for b in running]
        asked = [(b, chunk) for b, chunk in asked if len(chunk)]
        if not asked:
            break
        bodies = torch.cat([torch.full((len(chunk),), b) for b, chunk in asked])
        found = cost_at(bodies, torch.cat([chunk for _, chunk in asked]), torch.cat(
            [evaluated[b] - bound[b, chunk] + SLACK for b, chunk in asked]))
        for (b, chunk), cost in zip(asked, found.split([len(c) for _, c in asked])):
            cost = cost + rays[b, chunk]
            evaluated[b] = torch.minimum(evaluated[b], (cost + prior[b, chunk]).min())
            picked[b].append(chunk)
            costs[b].append(cost)
        running = [b for b, _ in asked]
    searched = []
    for chosen, cost in zip(picked, costs):
        if not chosen:
            searched.append((torch.zeros(0, dtype=torch.long), torch.zeros(0)))
            continue
        chosen, cost = torch.cat(chosen), torch.cat(cost)
        order = chosen.argsort()  # ties go to the smaller scale, as over the whole grid
        searched.append((chosen[order], cost[order]))
    return searched


def _ray_shares(joints: list[torch.Tensor], scene: Scene, behind: bool) -> torch.Tensor:
    """(B, len(SCALES)) per body, the share of its ``joints`` (J, 3; camera frame) behind
    the scan (``behind``) or in front of it at each scale, 0 without joints: one ray per
    joint, all bodies' cast together."""
    shares = torch.zeros(len(joints), len(SCALES))
    if not any(len(j) for j in joints):
        return shares
    visible = scene.visible_scale(torch.cat(joints), float(SCALES[-1]))
    for b, limits in enumerate(visible.split([len(j) for j in joints])):
        if len(limits):
            back = SCALES[:, None] > limits
            shares[b] = (back if behind else ~back).float().mean(1)
    return shares


def _underside(points: torch.Tensor, normals: torch.Tensor, carrying: torch.Tensor,
               scene: Scene) -> tuple[torch.Tensor, torch.Tensor]:
    """The vertices (indices into ``points`` (N, 3), camera frame, with outward
    ``normals`` (N, 3)) that can rest on a surface: facing down, and among the body's
    lowest (within LOWEST of its height span: scaling about the camera keeps the order,
    so they are read at the body's fitted size, the same whichever scales are evaluated)
    or ``carrying`` (N,) bool; and which of those are among the lowest."""
    height = (SCALES[0] * points) @ scene.up_in_camera()
    lowest = height - height.min() <= LOWEST * (height.max() - height.min())
    under = (scene.world_normals(normals)[:, 2] < DOWNWARD) & (lowest | carrying)
    ids = torch.nonzero(under).flatten()
    return ids, lowest[ids]


def _unsupported(points: torch.Tensor, scales: torch.Tensor,
                 undersides: list[tuple[torch.Tensor, torch.Tensor]], scene: Scene, rho: float,
                 share: float | torch.Tensor = LOWEST_SHARE) -> torch.Tensor:
    """(R,) robust gap (0: resting, 1: far) between the underside (:func:`_underside`)
    of each body, ``points`` (R, N, 3) camera frame scaled by ``scales`` (R, 1), and
    ``undersides`` (R) (``share`` of it, one for all or (R,): its lowest vertices only),
    and the upward-facing scene surfaces nearest to them."""
    sizes = [len(ids) for ids, _ in undersides]
    rows = torch.repeat_interleave(torch.arange(len(points)), torch.tensor(sizes))
    ids = torch.cat([ids for ids, _ in undersides])
    under = scales[rows] * points[rows, ids]
    gaps = scene.contact_distance.nearest_upward(
        scene.to_world(under), scene.signed_distance(under).abs(),
        torch.cat([low for _, low in undersides]), sizes, UPWARD)
    lowest, any_ = _miss(gaps, rho).unbind(1)
    return share * lowest + (1 - share) * any_


def _miss(nearest: torch.Tensor, rho: float) -> torch.Tensor:
    """How far a set of points is from touching, given its nearest qualifying point's
    distance ``nearest`` (m, inf when none qualifies): the robust distance (0 touching,
    toward 1 far away), 1 when none qualifies."""
    return torch.where(nearest.isfinite(), gmof(nearest ** 2, rho) / rho ** 2, 1.0)
