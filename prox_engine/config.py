"""Fitting configurations: named YAML files in ``prox_engine/configs`` or a user's file."""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from functools import cache
from pathlib import Path
from typing import get_args, get_origin, get_type_hints

import yaml

from .errors import InputError
from .keypoints import SIDE_PAIRS

CONFIG_DIR = Path(__file__).parent / "configs"
BODY_MODELS = ("anny", "smplx")
GENDERS = ("neutral", "male", "female")
TERMS = ("body", "hands", "face", "pose_prior", "shape", "bending", "hand_prior",
         "self_penetration", "penetration", "contact", "depth", "temporal")


@dataclass
class Stage:
    """Weights of each term in one annealing stage (0 switches a term off)."""

    name: str
    weights: dict[str, float]
    optimize_shape: bool = True
    optimize_hands: bool = False
    max_iter: int | None = None  # None: the configuration's max_iter / max_calls
    max_calls: int | None = None


@dataclass
class FitConfig:
    name: str
    stages: list[Stage]
    description: str = ""
    data_rho: float = 100.0  # Geman-McClure scale of the reprojection error (pixels)
    ignore_keypoints: list[int] = field(default_factory=lambda: [1, 9, 12])
    joint_limit_weight: float = 1e4  # every stage: anatomical limits are constraints
    init_depth_weight: float = 100.0  # start search: hold the similar-triangles depth
    swap_sides: bool = True  # consider OpenPose exchanging left and right legs or arms
    scale_search: bool = True  # resolve depth against the scene before the scene stages
    scale_support: bool = True  # the scale search asks that the body rest on a surface
    # ... and that the joints the detector clearly saw be in front of the scan
    scale_visibility: bool = True
    # ... and that the legs it reports faintly be out of view (see
    # scale_search.FAINT_WEIGHT)
    scale_faint_legs: bool = True
    # ... and weighs the size prior (scale_search.size_prior) by this: at 0.1 it lets the
    # scene move a body by up to about 25 % (4.5 sigma) when that brings every contact
    # part onto a surface, but not by 6-12 % only to touch a wall behind it with the back
    scale_size_weight: float = 0.1
    # ... or by this in a sequence's warm-started frames, where it centres on the anchor's
    # size (sequence_anchor_size)
    sequence_size_weight: float = 0.1
    # ... and counts a body through a thin surface by its axis (see scale_search.AXIS_WEIGHT)
    scale_axes: bool = True
    # ... and counts a standing body's contact parts but the feet as missing (see
    # scale_search.STANDING_PARTS)
    scale_standing_feet: bool = True
    # ... and does not count the toes as penetrating (see scale_search.TOE_REACH)
    scale_free_toes: bool = True
    # ... nor asks a kneeler's seen toes to be in view (see scale_search.TOE_REACH)
    scale_free_toe_rays: bool = True
    # ... and searches the unseen feet of kneeling legs pointed along the shins (see
    # scale_search.FLAT_SHIN)
    point_unseen_feet: bool = True
    # ... and, placing the body (not choosing between starts), rests a body on its feet
    # with a foot in view on its lowest vertices alone (see scale_search.FEET_CARRY_LEG)
    scale_feet_carry: bool = False
    # A body fitted from scratch and placed, whose unseen toes it sinks into the scene, has
    # those feet turned toward their neutral ankle before the scene stages (see
    # fitting.SUNK_TOES)
    lift_sunk_feet: bool = False
    # Sequence mode warm-starts each frame from its neighbour's fit; off, the frame keeps
    # that fit's shape, and its depth is the one its keypoint stage reaches from the
    # neighbour's, which drifts along the camera rays frame after frame. On, each frame's
    # scale is searched against the scene too, before its contact stage, which rescales
    # the body: the size then changes from frame to frame, as single frames' do.
    sequence_scale_search: bool = False
    # ... its size prior centred on the anchor frame's size (a person's size does not
    # change between frames); off, on the neighbour's, so that each frame's search could
    # move the size a few per cent on from the last (Fitter._sizes).
    sequence_anchor_size: bool = False
    # Sequence mode's temporal term counts the keypoints' motion about the mid-hip (the
    # posture's change) rather than their motion (losses.temporal): the contact stage holds
    # the root, so a body that walked 20 cm could only meet its neighbour's keypoints by
    # leaning and bending toward where it was.
    temporal_about_root: bool = False
    # Sequence mode fits one anchor frame from scratch and the others from their
    # neighbours, so all start from its posture, shape and depth: the first frame whose
    # body keypoints' summed confidence is this share of the best frame's (noise moves the
    # sums by a few per cent; a truncated, occluded or blurred frame loses 20-40). 0: the
    # first frame.
    anchor_seen: float = 0.9
    # Of those frames, the anchor is the first (of up to pipeline.ANCHOR_TRIES) whose start
    # keeps the detector's left and right: a frame whose sides the fit relabels, rightly or
    # not, passes that labelling and posture on to the whole sequence.
    anchor_as_detected: bool = True
    # Sequence mode fits a frame again from scratch when its neighbour's fit lost the
    # keypoints (pipeline.REFIT_RATIO), and goes on from that fit.
    sequence_refit: bool = True
    # ... and when one limb's keypoints alone end far off (pipeline.LIMB_RATIO): an arm
    # that moved faster than the chain could follow.
    sequence_limb_refit: bool = True
    # ... and, where set, when the labelling taken from its neighbour's fit overrides the
    # detector's left and right of the same part for the second frame running: a chain
    # that keeps overriding the detector may carry a wrong anchor's labelling (seed 33's
    # reacher, 299 -> 137 mm), but the anchor is chosen as labelled as detected, and of
    # the 5 such refits over 16 seeds 4 were worse than the warm fit (`prox-side-refit`).
    sequence_side_refit: bool = False
    # ... and when its fit floats over every surface (quality.FLOATING), keeping the fit
    # from scratch if that floats less (see pipeline._unless_floating).
    sequence_floating_refit: bool = True
    # ... and when the labelling taken from its neighbour's fit overrides the detector's
    # left and right of a part that the frame's own start search keeps as detected,
    # keeping the fit nearer the keypoints (pipeline._checked_labels): a neighbour fitted
    # with its legs crossed (a swap the detector made and its fit missed) otherwise
    # passes them on (seed 3's leg-up sitter, five frames 240 mm worse than single
    # frames). The start search runs only where the chain overrides the detector.
    sequence_label_check: bool = True
    # Sequence mode also fits every frame from scratch, in batches of this many frames,
    # and keeps, a window of as many frames at a time, each frame's fit on the path of
    # least motion through its warm-started fit and its fit from scratch (motion_path,
    # pipeline._Paths); 0: the chain's fits alone.
    sequence_path_window: int = 0
    # ... and, where set, after each window the chain goes on from the fit the path kept
    # for the window's last frame, not from its own: a chain that went wrong otherwise
    # stayed wrong to the recording's end, its frames rescued one by one by their fits
    # from scratch (pipeline.fit_recording). Recordings of up to a window fit as without.
    sequence_chain_from_path: bool = False
    # ... and, where over 0, the path leaves off a frame's fit whose keypoints' and
    # posture's terms (pipeline.IMAGE_TERMS) are over this many times its other fit's.
    sequence_path_worse: float = 0.0
    # ... and, where set, its anchor is the frame of the first window whose fit from
    # scratch moves least to the others' (summed; of the frames seen at least anchor_seen
    # times as well as the best of them), not the first well-seen frame labelled as
    # detected (pipeline._Paths.chains_from_medoid).
    anchor_by_motion: bool = False
    # Distinct starting bodies per frame fitted side by side through the first
    # start_stages stages, after which each frame keeps the one with the lowest objective:
    # a posture or orientation the rigid start search ranks second often fits better.
    start_candidates: int = 2
    start_stages: int = 2
    # With a scale search, the starts are compared by objective + this weight times the
    # search's cost (how badly the body meets the scene at its best scale, 0-2).
    start_scene_weight: float = 0.0
    # ... plus the size prior at that scale (scale_search.size_prior): the keypoint stages
    # hold the prior's mean body, so a start that meets the scene only scaled far from 1
    # asks for an unusually small or large person.
    start_choice_size: bool = False
    # Off, the starts are compared without the posture priors (pose and bending), which
    # measure how far a posture is from standing straight: a kneeling start paid for that
    # about ten times what a seated one did for the same keypoints and scene.
    start_choice_priors: bool = True
    # Off, the starts are compared without the arms' keypoints (elbows, wrists, hands):
    # starts differ in their trunk and legs, and an arm one start left in a wrong minimum
    # (a reach seen from the front) is for the arm restarts, after the choice, to settle.
    start_choice_arms: bool = True
    # Off, in the frames given a seated second start because their thighs are hidden
    # (start_thighs_hidden, keypoints.thighs_hidden), the starts are compared without the
    # feet's keypoints (ankles, toes, heels) too: one start is seated and the other
    # standing, the keypoint stages' pose prior pulls both toward standing, and only the
    # scene can tell (seed 35's seated reacher, whose seated start met the seen feet 100
    # px^2 worse after two stages, went on standing, shrunk 19 %: 213 and 251 mm). Where
    # only the ankles are unseen the feet's faint guesses stay: they told a crouching
    # kneeler from a standing one.
    start_choice_feet: bool = True
    # Where the detector sees the nose and eyes, a start turned away from the camera costs
    # up to this (px^2): the turned-away body with its sides swapped explains the same
    # keypoints, and without the face nothing tells the two apart.
    facing_cost: float = 5000.0
    # Where the detector sees no ankle (legs cut off or hidden), the second start is the
    # best whose thighs differ from the best's (bent forward or along the trunk): the
    # keypoints cannot tell sitting from standing there, the scene can.
    start_other_thighs: bool = False
    # ... also where the ankles are seen but neither hip nor knee (keypoints.HIDDEN): a
    # seated reacher's thighs behind a table (tuning seed 0: 215 -> 131 mm over its six
    # frames; `prox-thighs-by-ankles` is the ablation)
    start_thighs_hidden: bool = True
    # After the start choice, each frame's arms are also restarted held forward (one or
    # both), fitted side by side through the next stage, and the lowest objective is kept:
    # an arm seen from the front projects alike pointing forward or back.
    arm_restarts: bool = True
    # After the arm choice, each leg whose ankle the detector clearly saw is also restarted
    # with its shin turned about the knee onto the ankle's other point at the shin's
    # length on its camera ray (a shin seen from in front projects alike tucked back, its
    # foot in the air or on a footrest, or down to the floor), fitted side by side through
    # the next stage; each frame keeps the lowest objective plus start_scene_weight times
    # the scale search's cost: the keypoints cannot tell the two apart, the scene can.
    leg_restarts: bool = False
    # ... and where the knee is not clearly seen, the whole leg turned about the hip onto
    # the ankle's other point at its distance from the hip, each leg and both together.
    hip_restarts: bool = False
    # ... and each leg whose knee the fit misses by more than fitting.KNEE_MISS px posed
    # onto its knee's and ankle's camera rays from the hip (Fitter._legs_onto_rays).
    knee_restarts: bool = False
    # At the same point, with or without the leg restarts, each forearm whose wrist the
    # detector reports (at least keypoints.HIDDEN) turned about the elbow onto the wrist's
    # other point on its camera ray (a forearm seen from the camera projects alike
    # pointing toward it or away, into a mattress).
    forearm_restarts: bool = False
    # ... and each arm whose elbow the detector reports (at least keypoints.HIDDEN) turned
    # whole about the shoulder onto the elbow's other point on its camera ray (an arm
    # reaching toward the camera projects alike reaching back from the shoulder; the
    # `prox-shoulder-restarts` variant: a turned arm can move the whole body).
    shoulder_restarts: bool = False
    # Where the detector reports no knee or ankle at keypoints.HIDDEN or more and the
    # fitted knees lie in the image (legs behind furniture), the fit is also tried, just
    # before the scale search, with the legs posed as each start posture's (standing,
    # sitting, kneeling, crouching), and each frame keeps the one ranked best as starts
    # are (Fitter._hidden_leg_postures).
    hidden_leg_postures: bool = False
    # ... each first refitted through the last keypoint stage (Fitter._refit_candidates).
    hidden_leg_refit: bool = False
    # ... and, where the knees are seen and nothing below them, the shins alone posed so
    # (Fitter._hidden_leg_postures).
    hidden_shin_postures: bool = False
    # ... ranked with these contact parts counted as missing for every posture: hidden
    # legs are no evidence of what they touch (Fitter._hidden_leg_postures)
    hidden_leg_uncounted: list[str] = field(default_factory=list)
    # ... also where the fitted knees lie outside the image (cut off by its edge, the legs
    # are as unknown as behind furniture: whatever the start guessed, the keypoint stages
    # keep).
    hidden_legs_cut_off: bool = False
    # A frame fitted from scratch whose fit floats over every surface (quality.FLOATING)
    # is fitted again from its other start, which is kept if it floats less and fits the
    # keypoints clearly better (pipeline.RESTART_DATA); not where no ankle is seen, whose
    # underside is the legs' guessed posture (pipeline._fit_fresh).
    floating_restart: bool = False
    # A frame fitted from scratch whose fit takes one of swap_check_parts ("legs", "arms")
    # as swapped against the detector and ends more than swap_check_px from its keypoints
    # (as it labelled them) is fitted again with the labels as detected, and the fit
    # nearer its keypoints is kept (pipeline._swapped_far); 0 px: never.
    swap_check_px: float = 0.0
    swap_check_parts: list[str] = field(default_factory=lambda: ["legs"])
    # ... the fit as detected kept only where its error is under this share of the swapped
    # fit's: the start choice preferred the swap by objective and scene cost, so a tie
    # keeps it (pipeline._kept_nearer).
    swap_check_nearer: float = 1.0
    max_iter: int = 20  # L-BFGS iterations per call
    max_calls: int = 2  # calls per stage, stopped earlier when the loss settles
    ftol: float = 1e-5
    # Prior weights (pose, shape, bending, hands) enter the loss squared, as SMPLify-X and
    # PROX write theirs (so their stage values can be copied as they are).
    squared_priors: bool = False
    # Whether the scene stages may translate the body. Off, they turn and bend it where it
    # stands: the scale search (in sequence mode, the keypoint stage) placed it along its
    # camera rays, and the penetration term would otherwise shift the whole body off its
    # keypoints, by 2-9 cm, to escape a floor or seat scanned a few centimetres off (tuning
    # seeds 0, 8 and 9, PJE: 101 -> 91, 126 -> 112 and 127 -> 108 mm;
    # `prox-scene-translates` is the ablation).
    scene_stages_translate: bool = False
    # A frame fitted from scratch whose scene stages end with this many times the data
    # term they started with (plus fitting.SCENE_GUARD_FLOOR) is given back the body from
    # before them (0: never): held where they stand, a body sunk into a seat deeper than
    # its cushion can leave it only by bending, and the penetration term then throws the
    # limbs the keypoints barely hold into the air. Not in sequence mode's warm-started
    # frames: a body left in its seat is handed on to the next frame, which then starts
    # sunk (seeds 0, 8, 16, 35, 36, 38 and 41: 92.3 -> 93.7 mm with it there).
    scene_data_guard: float = 0.0
    # Depth (m) a body may sink into the scan before the penetration term pushes it out:
    # cushions and mattresses give 2-4 cm under a person, and a scan registered a
    # centimetre or two off puts a correctly placed body that deep. 0 (the paper's term)
    # in `prox`. 1 cm (`prox-cushion`) gained 3.5 mm on tuning seeds 0 / 8 / 16, but on
    # held-out seeds 21, 22 and 23 only 1.2, -0.2 and 1.2 mm, while the share of vertices
    # more than 1 cm inside the true scan rose 0.9 -> 2.1, 0.09 -> 0.21 and 0.04 -> 0.78 %;
    # 2 cm is `prox-soft`.
    penetration_tolerance: float = 0.0
    # Depth (m) inside a surface at which the scene stages' contact term has the flesh a
    # body rests on (buttocks, thighs, back: losses.SOFT_PARTS) touch it, and beyond which
    # their penetration term counts it (added to penetration_tolerance): flesh and
    # cushions give under a seated or lying person, whose unloaded surface then lies that
    # deep in the scan; the feet and hands stay on it. 0: on the surface, as the paper's
    # terms.
    soft_sink: float = 0.0
    # Depth (m) a body whose trunk lies within level_rho of level may sink into the scan,
    # beyond scale_search.PENETRATION_MARGIN, before the scale search counts it as
    # penetrating: a mattress gives under the whole of a lying body, heels and head too.
    # Rested on top, lying bodies were placed 1-4 cm high, too near the camera. 0 in
    # `prox`; 2 cm in `prox-lying-sink`, which gained on spent seeds' beds but not on
    # fresh ones (in sequence mode it lost).
    lying_sink: float = 0.0
    # Depth (m) the feet may enter the scan before the penetration term counts them (added
    # to penetration_tolerance; the contact term still has them on the surface): a scan
    # registered a centimetre or two off the camera puts correctly placed soles that deep
    # in its floor, and the scene stages, which hold the root, could only bend the legs out
    # (seed 81's leg-up sitter: a shin turned 40 degrees, 60 -> 95 mm). The scale search
    # does not count penetration that shallow either (scale_search.PENETRATION_MARGIN).
    # 0 in `prox`: 2 cm (`prox-feet-tolerant`) gained 0.8-5.2 mm on tuning and spent seeds
    # and 4.5 on held-out seed 89, but there sank feet into floors the scan had right (1.9
    # % of vertices more than 1 cm inside the true scan against 0.3; issue 11 asks 0.5).
    foot_tolerance: float = 0.0
    # The penetration term reads one body vertex per cell of a grid this size (m) over the
    # standing body, counted for the cell's vertices (losses.penetration_vertices): anny's
    # 13348 scene vertices become 6424, the face, hands and feet thinned, the trunk and
    # limbs kept, and the sum stays the paper's to a few per cent. Tuning seeds 0 / 8 / 16
    # against every vertex: PJE 105.3 -> 105.9 mm (paired median +0.1; 1 frame better, 3
    # worse by more than 15 mm); the scene stages 1.02-1.05 -> 0.86 s a frame (speed
    # benchmark, seed 3). 0 reads every vertex (`prox-every-vertex`).
    penetration_spacing: float = 0.01
    # Every stage (as the joint limits): the trunk (mid-hip to neck) is drawn toward world
    # up, robustly, while within about upright_rho (radians) of it, barely beyond (a
    # reclining or lying body keeps its angle). A trunk leaning toward or away from the
    # camera projects almost alike, and the scale search rests the feet of a body leaning
    # back on the floor too far away. Only over legs seen down to an ankle: on a frame cut
    # off at the knees the legs are guessed, and an upright trunk over guessed straight
    # legs made a seated person a standing one, metres off.
    upright_weight: float = 0.0
    upright_rho: float = 0.35
    # The start choice of a frame with no ankle seen whose thighs are seen hanging
    # (keypoints.thighs_hanging) counts these contact parts as missing for every start:
    # cut off at the knees, standers with a wall behind them chose the other thighs' start
    # (start_other_thighs), seated on nothing with the back and buttocks on the wall.
    hanging_thighs_uncounted: list[str] = field(default_factory=list)
    # Every stage: a trunk within level_rho (radians) of the horizontal is drawn level
    # (keypoint_terms.trunk_terms, a reward, 0 beyond: a fit that never comes that near
    # level does not change at all): a lying trunk seen along the camera's rays was
    # fitted pitched up toward the camera, hips 30 cm off. The start choice and the
    # restarts' choices leave it out: it shapes fits, it does not rank a lying posture
    # over a seated one.
    level_weight: float = 0.0
    level_rho: float = 0.4
    # Every stage: the shin of a leg the detector reports down to the knee and no further
    # (keypoints.cut_legs: cut off by the image's edge, or wholly hidden below the knee)
    # is drawn toward hanging plumb, as much as the trunk is upright
    # (keypoint_terms.plumb_shins). Nothing else places that shin, and the scale search stands
    # the body on the guess.
    plumb_shin_weight: float = 0.0
    # ... only in frames where the detector reports no point below either knee (cut off
    # under the knees; keypoints.nothing_below_knees). Where the other leg's foot is
    # reported, a leg missing below the knee is hidden, not cut off, and may be kneeling.
    plumb_cut_frames_only: bool = False
    contact_rho: float = 0.05
    contact_max_angle: float = 45.0
    contact_max_distance: float = 0.15  # vertices farther than this are not attracted
    contact_parts: list[str] = field(default_factory=lambda: [
        "left_hand", "right_hand", "left_foot", "right_foot", "back", "gluteus", "thighs"])
    depth_rho: float = 0.05
    depth_max_points: int = 1500
    sequence_stages: list[int] = field(default_factory=lambda: [-1])
    batch_size: int = 1
    flip: bool = False  # mirror Kinect images and depth (not keypoints) as PROX does
    sdf_dim: int = 256
    # With depth frames, the scan's registration to the camera is refined from the pixels
    # off the body (registration.py): a degree off moves a person standing on the scanned
    # floor 10-15 cm in depth. `prox-given-registration` is the ablation.
    refine_registration: bool = True
    # The body model (prox_engine.body.load_body): anny, or SMPL-X from the user's files.
    model: str = "anny"
    model_path: str | None = None  # folder with SMPLX_{NEUTRAL,MALE,FEMALE}.npz
    gender: str = "neutral"
    hand_pca: int = 12  # SMPL-X hand PCA components; 0 fits every finger joint
    body_segments: str | None = None  # PROX's body_segments/ folder (contact vertices)
    vposer_path: str | None = None  # VPoser v1.0 snapshot (or folder): the pose prior

    def uses(self, term: str) -> bool:
        return any(stage.weights.get(term, 0) > 0 for stage in self.stages)


# libyaml's safe loader when PyYAML was built with it (its wheels are): 2 ms for prox.yaml
# against the pure-Python loader's 23, paid by every job's work-horse for each file read.
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _read(path: Path, seen: set[Path]) -> dict:
    """A configuration file's settings over those of the one it names as ``base`` (a
    built-in name or a path relative to it), recursively."""
    try:
        raw = yaml.load(path.read_text(), Loader=_LOADER)
    except FileNotFoundError as exc:
        raise InputError(path, "configuration file not found") from exc
    except yaml.YAMLError as exc:
        raise InputError(path, f"invalid YAML ({exc})") from exc
    if not isinstance(raw, dict):
        raise InputError(path, "a configuration must be a mapping")
    base = raw.pop("base", None)
    if base is None:
        return raw
    parent = Path(str(base))
    parent = (CONFIG_DIR / f"{base}.yaml" if not parent.suffix
              else parent if parent.is_absolute() else path.parent / parent)
    if parent.resolve() in seen | {path.resolve()}:
        raise InputError(path, f"'base: {base}' makes a cycle")
    return {**_read(parent, seen | {path.resolve()}), **raw}


def load_config(name_or_path: str | Path, model: str = "anny") -> FitConfig:
    """Load ``rgb``, ``prox``, ``smplifyd``, ``proxd`` or a YAML file path; a file may
    name a ``base`` configuration whose settings it overrides. A built-in name resolves to
    the ``model``'s own version when there is one (``smplx-prox`` for SMPL-X: PROX's
    weights)."""
    path = Path(name_or_path)
    if not path.suffix:
        own = CONFIG_DIR / f"{model}-{name_or_path}.yaml"
        path = own if own.exists() else CONFIG_DIR / f"{name_or_path}.yaml"
        if not path.exists():
            known = ", ".join(sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")))
            raise InputError(name_or_path, f"unknown configuration (known: {known})")
    raw = _read(path, set())
    if not isinstance(raw.get("stages"), list) or not raw["stages"]:
        raise InputError(path, "configuration needs a non-empty 'stages' list")
    stages = []
    for i, entry in enumerate(raw.pop("stages")):
        if not isinstance(entry, dict):
            raise InputError(path, f"stage {i} must be a mapping")
        entry = dict(entry)
        name = str(entry.pop("name", f"stage{i}"))
        shape = bool(entry.pop("optimize_shape", True))
        hands = bool(entry.pop("optimize_hands", False))
        budget = {k: int(entry.pop(k)) for k in ("max_iter", "max_calls") if k in entry}
        unknown = set(entry) - set(TERMS)
        if unknown:
            raise InputError(path, f"stage {name}: unknown terms {sorted(unknown)}")
        try:
            weights = {k: float(v) for k, v in entry.items()}
        except (TypeError, ValueError) as exc:
            raise InputError(path, f"stage {name}: weights must be numbers") from exc
        stages.append(Stage(name, weights, shape, hands, **budget))
    known = {f.name for f in fields(FitConfig)} - {"stages", "name"}
    unknown = set(raw) - known
    if unknown:
        raise InputError(path, f"unknown settings {sorted(unknown)}")
    raw = _typed(path, raw)
    parts = set(raw.get("swap_check_parts", [])) - set(SIDE_PAIRS)
    if parts:
        raise InputError(path, f"swap_check_parts: unknown parts {sorted(parts)} "
                               f"(known: {', '.join(SIDE_PAIRS)})")
    return FitConfig(name=path.stem, stages=stages, **raw)


def _typed(path: Path, raw: dict) -> dict:
    """The settings ``raw`` as FitConfig types them, or an InputError naming ``path`` and
    the setting: a worker given a weight of ``"high"`` failed deep inside a fit. A number
    YAML 1.1 reads as text (``1e-6``, written without a point) is read as the number."""
    hints = _field_types()
    typed = {}
    for name, value in raw.items():
        try:
            typed[name] = _as(hints[name], value)
        except (TypeError, ValueError):
            raise InputError(path, f"{name}: expected {_words(hints[name])}, got {value!r}"
                             ) from None
    return typed


@cache
def _field_types() -> dict:
    """FitConfig's fields' types, resolved once (1.5 ms, as much again as reading a file)."""
    return get_type_hints(FitConfig)


def _as(kind, value):
    """``value`` as the type ``kind`` (bool, int, float, str, an optional or a list of
    them); TypeError or ValueError where it is not one."""
    if get_origin(kind) is list:
        if not isinstance(value, list):
            raise TypeError(value)
        return [_as(get_args(kind)[0], item) for item in value]
    if type(None) in get_args(kind):
        return None if value is None else _as(get_args(kind)[0], value)
    if kind is float and not isinstance(value, bool) and isinstance(value, (int, float, str)):
        return float(value)
    if isinstance(value, kind) and not (kind is int and isinstance(value, bool)):
        return value
    raise TypeError(value)


def _words(kind) -> str:
    """How an error names the type ``kind``."""
    if get_origin(kind) is list:
        return "a list of " + {int: "whole numbers", str: "texts"}[get_args(kind)[0]]
    if type(None) in get_args(kind):
        return f"{_words(get_args(kind)[0])} or nothing"
    return {bool: "true or false", int: "a whole number", float: "a number",
            str: "a text"}[kind]
