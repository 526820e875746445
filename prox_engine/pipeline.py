"""Fitting whole recordings: read the PROX layout, fit frame by frame (or in sequence or
batches), write results atomically, and summarise. Used by the CLI and the workers."""
from __future__ import annotations

import statistics
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import torch

from . import metrics, quality
from .body.base import BodyModel
from .camera import Camera, DepthCamera
from .config import FitConfig
from .dataset import (Recording, frame_times, load_calibration, load_cam2world,
                      load_depth_camera, load_scene_mesh)
from .depth import load_depth_points
from .errors import InputError
from .fitting import Fitter, FitResult, Frame
from .keypoints import BODY, BODY_25, ankle_seen, load_keypoints
from .motion_path import least_motion_path, medoid, motion
from .output import atomic_write_bytes, frame_paths, ply_bytes, write_json, write_pickle
from .registration import OFF, Registration, register_scan
from .scene import Scene

Progress = Callable[[int, int, str], None]
# Sequence mode refits a frame from scratch when its neighbour's fit ends this many times
# further from the keypoints than the anchor's, and this many pixels: it lost them (a cut
# in the video, a jump of the detector to another person). At 10 px, 37 of the 40 refits
# over 13 seeds were of blurred frames (10 px of noise alone puts a good fit 12.5 px off);
# at 40 px none of 864 benchmark frames is refitted (their warm fits end 4-30 px off):
# 648 tuning and spent frames 83.7 -> 83.0 mm PJE, seeds 62-65 (the first three seen
# before) 84.5 / 91.5 / 101.6 / 86.9 -> 74.9 / 87.9 / 99.8 / 86.9, held-out seed 66 84.3 ->
# 83.0, with sequence_side_refit off as well; over those 918 frames walk -6.2, bed -4.2,
# reach +5.4 (a blurred reacher's fit from scratch took an arm's posture its chain missed).
REFIT_RATIO, REFIT_MIN_PX = 2.0, 40.0
# ... and when one limb's keypoints (metrics.limb_errors) end this many times the anchor's
# mean error off on average, this many pixels, and this many times any other limb's: an
# arm that moved faster than its chain could follow (FitConfig.sequence_limb_refit),
# where blur spreads its error over every limb. 22 refits over 17 seeds: 648 tuning and
# spent frames 83.0 -> 82.3 mm PJE, seeds 62-66 86.5 -> 84.7, held-out seed 68 81.8 ->
# 81.1, no kind worse (reach -5.2 and -6.7); without the stand-out test blurred lying
# bodies were refitted too (bed +11.2 on the 648 frames, seed 59's 90 -> 418 mm).
LIMB_RATIO, LIMB_MIN_PX, LIMB_STANDOUT = 4.0, 20.0, 2.5
# Sequence mode starts at most this many well-seen frames (one start search each) looking
# for an anchor labelled as detected (FitConfig.anchor_as_detected).
ANCHOR_TRIES = 5


@dataclass
class RecordingResult:
    recording: str
    summary: dict
    failures: list[tuple[str, str]] = field(default_factory=list)


def fit_recording(base: Path, recording: str, out: Path, config: FitConfig, body: BodyModel,
                  max_frames: int | None = None, sequence: bool = False,
                  progress: Progress | None = None,
                  on_stage: Callable[[str], None] | None = None,
                  source: str | None = None) -> RecordingResult:
    """Fit the frames of one recording and write ``OUT/<rec>/...``.

    ``progress(done, total, frame)`` is called after each batch of frames, ``on_stage(name)``
    as each step starts ("scene", then the fitter's stages); an exception raised by either
    stops the fit. ``source`` names the input in summary.json, where `prox report` looks
    for the scene (default: BASE's absolute path).

    Problems with the recording's shared files (calibration, camera pose, scene) raise
    :class:`InputError`; a bad frame is reported in the summary and skipped.
    """
    rec = Recording(Path(base), recording)
    names = rec.frames()
    if max_frames is not None:
        names = names[:max_frames]
    if not names:
        raise InputError(rec.keypoint_dir, "no *_keypoints.json files")
    camera = load_calibration(rec.calibration_path)
    depth_camera = (load_depth_camera(rec.depth_calibration_path, rec.calibration_path)
                    if config.uses("depth") and rec.depth_calibration_path else None)
    if on_stage:
        on_stage("scene")
    t0 = time.perf_counter()
    vertices, faces = load_scene_mesh(rec.scene_path)
    cam2world = load_cam2world(rec.cam2world_path)
    registration = (register_scan(rec, names, cam2world, vertices, faces, camera, depth_camera,
                                  config.flip)
                    if config.refine_registration else Registration(cam2world, False, OFF))
    scene = Scene.load(vertices, faces, registration.cam2world, rec.sdf_paths,
                       dim=config.sdf_dim)
    scene_seconds = time.perf_counter() - t0
    fitter = Fitter(body, camera, config, scene, on_stage)

    failures: list[tuple[str, str]] = []
    frames_summary: list[dict] = []
    batch = 1 if sequence else max(1, config.batch_size)
    done = 0
    anchor: FitResult | None = None
    anchor_px = 0.0  # the anchor's reprojection error

    search = {"seconds": 0.0, "evaluations": 0}  # the anchor search's cost

    def as_detected(name: str) -> bool:
        """Whether the frame's best start keeps the detector's left and right."""
        try:
            frame = _load_frame(rec, name, camera, config, depth_camera)
        except InputError:
            return False
        t0 = time.perf_counter()
        labelling = fitter.start_labelling(frame)
        search["seconds"] += time.perf_counter() - t0
        search["evaluations"] += fitter.evaluations
        return labelling == ()

    def written(pairs: list[tuple[Frame, FitResult]], failed: int) -> None:
        """Write the frames' fits; count them and ``failed`` frames done."""
        nonlocal done
        for frame, result in pairs:
            frames_summary.append(_write_frame(out, recording, frame, result, body, camera,
                                               scene, config, sequence))
        done += len(pairs) + failed
        if progress and (pairs or failed):
            progress(done, len(names), pairs[-1][0].name if pairs else failures[-1][0])

    paths = (_Paths(fitter, config.sequence_path_window, config.sequence_path_worse)
             if sequence and config.sequence_path_window > 0 else None)
    if not sequence:
        chains = [names]
    elif paths and config.anchor_by_motion:
        chains = paths.chains_from_medoid(rec, names, lambda name: _load_frame(
            rec, name, camera, config, depth_camera), config.anchor_seen)
    else:
        chains = _chains(rec, names, config.anchor_seen,
                         as_detected if config.anchor_as_detected else None)
    for chain in chains:
        previous = anchor  # a backward chain starts from the anchor frame's fit
        went_on = ""  # an event for the chain's next fit, where it went on from the path's
        if paths:
            paths.before = anchor
        for start in range(0, len(chain), batch):
            frames = []
            for name in chain[start:start + batch]:
                try:
                    frames.append(_load_frame(rec, name, camera, config, depth_camera))
                except InputError as exc:
                    failures.append((name, str(exc)))
                    previous = None  # do not warm-start across a gap
            fresh = not (sequence and previous is not None)
            results: list[FitResult] = []
            if frames:
                try:
                    results = (paths.fresh_fits(frames) if paths and fresh else
                               _fit_fresh(fitter, frames) if fresh else
                               _fit_from(fitter, frames[0], previous, anchor or previous,
                                         anchor_px, paths.lend if paths else None))
                except (RuntimeError, ValueError) as exc:  # numerical failure: skip, go on
                    failures += [(f.name, f"optimisation failed ({exc})") for f in frames]
                if anchor is None and start == 0 and results and search["evaluations"]:
                    _charge(results[0], "anchor_search", search["seconds"],
                            search["evaluations"])
                if went_on and results and not fresh:
                    results[0].events.append(went_on)
                went_on = ""
                previous = results[-1] if results else None
                if anchor is None and start == 0 and previous is not None:
                    anchor, anchor_px = previous, _error_px(fitter, previous, frames[-1])
            pairs = list(zip(frames, results))
            failed = len(chain[start:start + batch]) - len(pairs)
            kept = paths.add(pairs, fresh) if paths else pairs
            if paths and kept and previous is not None and config.sequence_chain_from_path:
                if paths.before is not previous:
                    went_on = (f"sequence: warm-started from {paths.before.name}'s fit from "
                               "scratch, which the path of least motion kept, not the chain's")
                previous = paths.before
            written(kept, failed)
        if paths:
            written(paths.flush(), 0)

    order = {name: i for i, name in enumerate(names)}
    frames_summary.sort(key=lambda f: order[f["frame"]])
    quality.recording_flags(frames_summary, frame_times([f["frame"] for f in frames_summary]))
    summary = _summarise(recording, source or str(Path(base).absolute()), config, sequence,
                         frames_summary, failures, scene_seconds)
    summary["registration"] = registration.summary()
    write_json(Path(out) / recording / "summary.json", summary)
    return RecordingResult(recording, summary, failures)


# A fit from a frame's other start replaces its floating first fit only with a data term
# under this share of the first's: over 648 frames of twelve seeds, 27 floated and were
# refitted; of the 8 refits that floated less with such a data term, 6 were 14-297 mm
# better and 2 worse (7 and 187 mm); the 19 that floated less with a data term 0.94-6.4
# times the first's were 2374 mm worse all told (seated reachers refitted standing,
# shrunk toward the camera until their feet met the floor).
RESTART_DATA = 0.9


def _fit_fresh(fitter: Fitter, frames: list[Frame],
               replaced: dict[str, FitResult] | None = None) -> list[FitResult]:
    """``frames`` fitted from scratch; with ``config.floating_restart``, each whose fit
    floats over every surface is fitted again from the start its fit did not go on from
    (see :func:`_kept_less_floating`, with RESTART_DATA): the start choice judges how each
    start meets the scene after two stages, and where the stages after it lift the
    chosen body off every surface, the reason it was chosen over a start that fits the
    keypoints better is gone (seed 16's kneeler, crouching 8 cm over the floor, 441 ->
    144 mm). Not where the detector saw no ankle: the underside is then the legs'
    guessed posture, its gap no evidence against the fit, and the refit rests its own
    guessed legs on a surface at whatever depth that takes (seed 8's sitter, cut off at
    the knees: refitted 26 % too far, 130 -> 772 mm). Each other frame whose fit takes
    the legs or arms (``config.swap_check_parts``) as swapped against the detector and
    ends far from its keypoints is fitted again as detected (:func:`_swapped_far`); so is
    a floating frame's fit kept after its refit. A batch's frames fitted again are fitted
    together, whatever they are fitted again for: one fit, and one more for the kept
    refits that need checking. With ``replaced``, each frame's first fit that one fitted
    again replaced goes there by the frame's name (its cost counted in the fit kept)."""
    results = list(fitter.fit(frames))
    first = list(results)
    floating: dict[int, float] = {}  # frame -> seconds its floating check took
    if fitter.config.floating_restart and fitter.scene is not None:
        for b, (frame, result) in enumerate(zip(frames, results)):
            if result.start is not None and ankle_seen(frame.keypoints.data[:, 2]):
                check = _floating_check(fitter, result)
                if result.underside_gap > quality.FLOATING:
                    floating[b] = check
                else:
                    _charge(result, "floating_check", check, 0)
    far = _swapped_far(fitter, frames, results, set(range(len(frames))) - floating.keys())
    again = sorted([*floating, *far])
    if not again:
        return results
    refits = fitter.fit([frames[b] for b in again],
                        start=[1 - results[b].start if b in floating else None for b in again],
                        as_detected=[b in far for b in again])
    for b, other in zip(again, refits):
        results[b] = (_kept_less_floating(fitter, results[b], other, floating[b], RESTART_DATA,
                                          ("", "first", "from the other start", "refit"))
                      if b in floating else _kept_nearer(fitter, frames[b], results[b],
                                                         far[b], other))
    far = _swapped_far(fitter, frames, results, set(floating))
    if far:
        as_detected = fitter.fit([frames[b] for b in far], as_detected=[True] * len(far))
        for b, other in zip(far, as_detected):
            results[b] = _kept_nearer(fitter, frames[b], results[b], far[b], other)
    if replaced is not None:
        replaced.update((frame.name, fit) for frame, fit, kept in zip(frames, first, results)
                        if fit is not kept)
    return results


class _Paths:
    """Sequence mode's frames held until a window of them (FitConfig.sequence_path_window)
    is in, then each fitted from scratch too, where its chain did not (:func:`_fit_fresh`,
    the frames together: as single frames fit them), and handed back with the fit on the
    path of least motion through each frame's two (:mod:`motion_path`), from the fit kept
    for the frame before them (``before``: a chain's first frame has none, a backward
    chain's the anchor's). With FitConfig.anchor_by_motion the first window's frames are
    fitted from scratch before the chain, to choose its anchor by, and those fits serve
    the chain and the path. Where the chain falls back on a fit from scratch (a refit, a
    label or floating check: :func:`_fit_from`), it takes the path's (:meth:`lend`)."""

    def __init__(self, fitter: Fitter, window: int, worse: float = 0.0) -> None:
        self.fitter, self.window, self.worse = fitter, window, worse
        self.before: FitResult | None = None
        self.pending: list[tuple[Frame, FitResult, bool]] = []
        self.ahead: dict[str, FitResult] = {}  # fits from scratch made before the chain
        self.first: dict[str, FitResult] = {}  # their first fits, where refits replaced them
        self.lent: dict[str, tuple[FitResult, FitResult]] = {}  # copy lent, its original

    def chains_from_medoid(self, rec: Recording, names: list[str],
                           load: Callable[[str], Frame], anchor_seen: float
                           ) -> list[list[str]]:
        """Sequence mode's order (see :func:`_chains`) from the anchor whose fit from
        scratch moves least to the others of the first window's frames (summed; of the
        frames seen at least ``anchor_seen`` times as well as the best of them), those
        fits kept for the chain and the path (FitConfig.anchor_by_motion)."""
        frames = []
        for name in names[:self.window]:
            try:
                frames.append(load(name))
            except InputError:
                continue  # reported when the chain comes to it
        try:
            fits = self._fresh(frames) if frames else []
        except (RuntimeError, ValueError):
            fits = []
        if not fits:
            return _chains(rec, names, anchor_seen, None)
        self.ahead = {frame.name: fit for frame, fit in zip(frames, fits)}
        seen = [_seen(rec, frame.name) for frame in frames]
        well_seen = [i for i, s in enumerate(seen) if s >= anchor_seen * max(seen)]
        anchor = names.index(frames[medoid([fit.vertices for fit in fits], well_seen)].name)
        return [names[anchor:], names[:anchor][::-1]]

    def fresh_fits(self, frames: list[Frame]) -> list[FitResult]:
        """``frames`` fitted from scratch: their fits made ahead, the others fitted
        together (:func:`_fit_fresh`)."""
        missing = [frame for frame in frames if frame.name not in self.ahead]
        made = dict(zip([frame.name for frame in missing],
                        self._fresh(missing) if missing else []))
        return [self.ahead.pop(frame.name) if frame.name in self.ahead else made[frame.name]
                for frame in frames]

    def _fresh(self, frames: list[Frame]) -> list[FitResult]:
        """``frames`` fitted from scratch (:func:`_fit_fresh`), the first fits that refits
        replaced kept for :meth:`lend`."""
        return _fit_fresh(self.fitter, frames, self.first)

    def lend(self, frame: Frame) -> FitResult:
        """The frame's fit from scratch as the chain makes it alone, for the chain to fall
        back on (:func:`_fit_from`), made once for the chain and the path: the path's fit
        (made ahead, else made now and held for the path), or that fit's first fit where a
        refit replaced it (:func:`_fit_fresh`). Lent as a copy that costs nothing (the
        path's fit counts the cost), the same copy each time; where the chain keeps a copy
        of the path's own fit, the flush weighs them as one."""
        if frame.name not in self.lent:
            if frame.name not in self.ahead:
                self.ahead[frame.name] = self._fresh([frame])[0]
            original = self.first.pop(frame.name, None) or self.ahead[frame.name]
            self.lent[frame.name] = (replace(original, seconds=0.0, stage_seconds={},
                                             stage_evaluations={}, events=list(original.events)),
                                     original)
        return self.lent[frame.name][0]

    def add(self, pairs: list[tuple[Frame, FitResult]], fresh: bool
            ) -> list[tuple[Frame, FitResult]]:
        """Hold the chain's fits ``pairs`` (``fresh``: fitted from scratch, as a single
        frame); the frames and fits kept once a window is in, else none."""
        self.pending += [(frame, result, fresh) for frame, result in pairs]
        return self.flush() if len(self.pending) >= self.window else []

    def flush(self) -> list[tuple[Frame, FitResult]]:
        """The frames held and the fit kept for each, in order."""
        pending, self.pending = self.pending, []
        candidates = [[result] for _, result, _ in pending]
        again = [i for i, (_, _, fresh) in enumerate(pending) if not fresh]
        if again:
            try:
                for i, fit in zip(again, self.fresh_fits([pending[i][0] for i in again])):
                    candidates[i].append(fit)
            except (RuntimeError, ValueError) as exc:  # the chain's fits stand
                for i in again:
                    pending[i][1].events.append(f"sequence: no fit from scratch ({exc})")
        for i, (frame, result, _) in enumerate(pending):
            self.first.pop(frame.name, None)
            copy, original = self.lent.pop(frame.name, (None, None))
            if result is copy and len(candidates[i]) == 2 and candidates[i][1] is original:
                _charge_all(copy, original)
                candidates[i] = [copy]
            elif len(candidates[i]) == 2:
                _leave_off_far_worse(candidates[i], self.worse)
        before = None if self.before is None else self.before.vertices
        path = least_motion_path([[c.vertices for c in cs] for cs in candidates], before)
        kept = [cs[pick] for cs, pick in zip(candidates, path)]
        for i, (cs, pick) in enumerate(zip(candidates, path)):
            if len(cs) == 1:
                continue
            dropped = cs[1 - pick]
            _discard(kept[i], dropped, "fresh_fit" if pick == 0 else "warm_fit")
            if pick:  # a path that leaves the chain has a neighbour to leave it for
                around = [f.vertices for f in [kept[i - 1] if i else self.before,
                                               *kept[i + 1:i + 2]] if f is not None]
                kept[i].events.append(
                    "sequence: kept its fit from scratch, on the path of least motion (to "
                    f"the fits kept around it {_moved(kept[i], around)} against the warm "
                    f"fit's {_moved(dropped, around)})")
        if kept:
            self.before = kept[-1]
        return [(frame, fit) for (frame, _, _), fit in zip(pending, kept)]


# What sequence mode's path weighs a frame's two fits by besides motion
# (FitConfig.sequence_path_worse): how the body meets the detector's keypoints and how
# plausible its posture is, not the scene's terms, which a right fit can pay heavily where
# the scan is soft or legs hidden under a table are guessed into it (seed 8's seated
# reacher: warm fits 88 and 67 mm PJE, 3-9 times the fit from scratch's whole objective,
# all but 1.8 times of it penetration).
IMAGE_TERMS = ("data", "joint_limits", "pose_prior")


def _image_cost(result: FitResult) -> float:
    """A fit's terms IMAGE_TERMS, summed."""
    return sum(result.losses.get(term, 0.0) for term in IMAGE_TERMS)


def _leave_off_far_worse(candidates: list[FitResult], ratio: float) -> None:
    """Of a frame's warm-started fit and its fit from scratch (``candidates``), leave off
    the path the one whose :func:`_image_cost` is over ``ratio`` times the other's (0:
    neither), charging its cost to the other, with an event: the two fit the same frame,
    and a chain that carried a wrong posture on sits in a minimum that its smoothness
    cannot pay for (seed 249's sofa sitter after a blurred frame: joints at their limits,
    3-8 times the fit from scratch's cost, 250 mm PJE against 46-75, and on the path for
    its little motion)."""
    if ratio <= 0:
        return
    values = [_image_cost(c) for c in candidates]
    if min(values) <= 0 or max(values) <= ratio * min(values):
        return
    worse = values.index(max(values))
    dropped = candidates.pop(worse)
    names = ("warm-started fit", "fit from scratch")
    candidates[0].events.append(
        f"sequence: its {names[worse]} left off the path of least motion, its keypoints' "
        f"and posture's cost {values[worse]:.0f} over {ratio:g} times its "
        f"{names[1 - worse]}'s {values[1 - worse]:.0f}")
    _discard(candidates[0], dropped, "warm_fit" if worse == 0 else "fresh_fit")


def _moved(fit: FitResult, around: list[torch.Tensor]) -> str:
    """How far a fit's body is from the fits ``around`` it (vertices): mean, in cm."""
    return f"{100 * sum(motion(fit.vertices, v) for v in around) / len(around):.1f} cm"


def _swapped_far(fitter: Fitter, frames: list[Frame], results: list[FitResult],
                 which: set[int]) -> dict[int, float]:
    """Of the frames ``which``, those (-> px off) whose fit takes one of
    ``config.swap_check_parts`` as swapped against the detector and ends over
    ``config.swap_check_px`` from the keypoints as it labelled them: the start choice
    compares labellings two stages in, by objective and scene cost; the finished fits
    tell them apart better (seed 54's kneeler, legs taken as swapped: 11.4 px and 568 mm
    off, as detected 7.0 px and 65 mm)."""
    limit, parts = fitter.config.swap_check_px, set(fitter.config.swap_check_parts)
    if limit <= 0:
        return {}
    errors = {b: _error_px(fitter, results[b], frames[b]) for b in sorted(which)
              if parts & set(results[b].swapped)}
    return {b: error for b, error in errors.items() if error > limit}


def _kept_nearer(fitter: Fitter, frame: Frame, result: FitResult, error: float,
                 as_detected: FitResult) -> FitResult:
    """Of ``result`` (parts taken as swapped, ``error`` px off) and ``frame`` fitted again
    as detected, the fit as detected where it ends under ``config.swap_check_nearer``
    times ``error`` from its keypoints, else ``result``, with an event saying so."""
    other = _error_px(fitter, as_detected, frame)
    nearer = other < fitter.config.swap_check_nearer * error
    kept, dropped = (as_detected, result) if nearer else (result, as_detected)
    kept.events.append(f"{' and '.join(result.swapped)} fitted as swapped, {error:.1f} px "
                       f"off; fitted again as detected, {other:.1f} px; kept the "
                       + ("fit as detected" if kept is as_detected else "swapped fit"))
    _discard(kept, dropped)
    return kept


def _fit_from(fitter: Fitter, frame: Frame, previous: FitResult, anchor: FitResult,
              anchor_px: float, from_scratch: Callable[[Frame], FitResult] | None = None
              ) -> list[FitResult]:
    """Sequence mode: ``frame`` fitted from its neighbour's fit (``previous``), with
    ``config.sequence_anchor_size`` the scale search's size prior centred on the size of
    the ``anchor`` frame's fit (``anchor_px`` from its keypoints). Where that
    lost the keypoints, or one limb's, or keeps overriding the detector's sides
    (:func:`refit_reason`), the frame is fitted again from scratch, and the sequence goes
    on from that fit, with its own shape: a warm start that lost the keypoints may still
    end near them at a wrong depth (a lying body 30 cm near, 13.0 px off against the
    fresh fit's 13.4), which the fresh fit's scale search does not inherit. Where its
    labelling overrides the detector against the frame's own start search, the fit
    nearer the keypoints of it and a fit from scratch goes on (:func:`_checked_labels`).
    Each fit from scratch is ``from_scratch(frame)`` (default: a plain fit of the frame)."""
    from_scratch = from_scratch or (lambda f: fitter.fit([f])[0])
    sized_as = anchor if fitter.config.sequence_anchor_size else previous
    results = fitter.fit([frame], warm_start=previous.params,
                         previous_keypoints=previous.keypoints[None], sized_as=sized_as.params)
    errors = _errors(fitter, results[0], frame)
    error_px = float(errors.nanmean())
    why = refit_reason(fitter.config, error_px, anchor_px,
                       previous.swapped, results[0].swapped, metrics.limb_errors(errors))
    if why:
        fresh = from_scratch(frame)
        fresh.events.append(f"sequence: refitted from scratch, {why}")
        _discard(fresh, results[0])
        return [fresh]
    if fitter.config.sequence_refit and fitter.config.sequence_label_check:
        checked = _checked_labels(fitter, frame, results[0], error_px, from_scratch)
        if checked is not results[0]:
            return [checked]
    if fitter.config.sequence_refit and fitter.config.sequence_floating_refit:
        return _unless_floating(fitter, frame, results, from_scratch)
    return results


def _checked_labels(fitter: Fitter, frame: Frame, warm: FitResult, warm_px: float,
                    from_scratch: Callable[[Frame], FitResult]) -> FitResult:
    """The warm fit (``warm_px`` from its keypoints), unless its labelling, taken from its
    neighbour's fit, overrides the detector's left and right of a part that the frame's own
    start search (``Fitter.start_labelling``, charged to ``warm``; a fit from scratch reuses
    it) keeps as detected: then the frame is fitted again from scratch, and the fit nearer
    its keypoints (each as it labelled them) is returned. A neighbour whose fit missed a
    detector's swap has its legs crossed, and the frames after it, labelled to match, keep
    them crossed, further from their keypoints than a fit from scratch (seed 3's leg-up
    sitter: 10-13 px and five frames 240 mm worse than single frames, fitted from scratch
    4-8 px); where the detector did swap a part and the start search missed it, the fit from
    scratch is the one further off (seed 57's wall: 15.3 px against 5.3)."""
    if not warm.swapped:
        return warm
    t0 = time.perf_counter()
    own = fitter.start_labelling(frame)
    _charge(warm, "label_check", time.perf_counter() - t0, fitter.evaluations)
    disputed = sorted(set(warm.swapped) - set(own))
    if not disputed:
        return warm
    fresh = from_scratch(frame)
    fresh_px = _error_px(fitter, fresh, frame)
    kept, dropped = (fresh, warm) if fresh_px < warm_px else (warm, fresh)
    kept.events.append(
        f"sequence: its neighbour's fit overrode the detector's left and right of the "
        f"{' and '.join(disputed)}, which the frame's own start search keeps; fitted again "
        f"from scratch, {fresh_px:.1f} px off against the warm fit's {warm_px:.1f}; kept "
        + ("the fit from scratch" if kept is fresh else "the warm fit"))
    _discard(kept, dropped)
    return kept


def _unless_floating(fitter: Fitter, frame: Frame, results: list[FitResult],
                     from_scratch: Callable[[Frame], FitResult]) -> list[FitResult]:
    """A warm-started fit whose underside floats over every surface is fitted again from
    scratch, and the fit that floats less is kept (:func:`_less_floating`): the keypoint
    stage lets a frame drift along the camera rays from its neighbour's depth, and the
    contact stage alone cannot pull it back (seed 35's bed, 22 cm up, 576 mm off)."""
    return [_less_floating(fitter, results[0], lambda: from_scratch(frame), None,
                           ("sequence: its neighbour's fit ", "neighbour's",
                            "a fit from scratch", "fit from scratch"))]


def _less_floating(fitter: Fitter, result: FitResult, refit: Callable[[], FitResult],
                   data_share: float | None, words: tuple[str, str, str, str]
                   ) -> FitResult:
    """``result``, unless it floats over every surface (quality.FLOATING): then
    :func:`_kept_less_floating` of it and the fit ``refit()`` gives."""
    check = _floating_check(fitter, result)
    if result.underside_gap <= quality.FLOATING:
        _charge(result, "floating_check", check, 0)
        return result
    return _kept_less_floating(fitter, result, refit(), check, data_share, words)


def _floating_check(fitter: Fitter, result: FitResult) -> float:
    """Set ``result.underside_gap`` (its underside's gap to the nearest surface below);
    returns the seconds that took."""
    t0 = time.perf_counter()
    result.underside_gap = quality.underside_gap(result.vertices, fitter.scene)
    return time.perf_counter() - t0


def _kept_less_floating(fitter: Fitter, result: FitResult, other: FitResult, check: float,
                        data_share: float | None, words: tuple[str, str, str, str]
                        ) -> FitResult:
    """Of a floating ``result`` and a fit ``other`` of its frame made again, ``other`` if
    it floats less and (given ``data_share``) its data term is under ``data_share`` times
    the first's, else ``result``. The fit kept carries an event in ``words`` (what
    floated, the first's name, the refit's, and the refit's name as kept), the dropped
    fit's cost and the floating checks (``check`` seconds so far)."""
    gap = result.underside_gap
    t0 = time.perf_counter()
    other_gap = other.underside_gap = quality.underside_gap(other.vertices, fitter.scene)
    check += time.perf_counter() - t0
    better = other_gap < gap and (
        data_share is None or other.losses["data"] < data_share * result.losses["data"])
    kept, dropped = (other, result) if better else (result, other)
    subject, first, second, second_kept = words
    kept.events.append(
        f"{subject}floated {quality.gap_text(gap)} over any surface (data term "
        f"{result.losses['data']:.0f}), {second} {quality.gap_text(other_gap)} "
        f"({other.losses['data']:.0f}); kept the " + (second_kept if better else first))
    _discard(kept, dropped)
    _charge(kept, "floating_check", check, 0)
    return kept


def _charge_all(result: FitResult, original: FitResult) -> None:
    """Count in ``result``, a copy of ``original`` made at no cost (:meth:`_Paths.lend`),
    the original's cost, stage by stage: the chain kept the copy and the path's fit is the
    original, one fit from scratch."""
    result.seconds += original.seconds
    for step, seconds in original.stage_seconds.items():
        result.stage_seconds[step] = result.stage_seconds.get(step, 0.0) + seconds
    for step, count in original.stage_evaluations.items():
        result.stage_evaluations[step] = result.stage_evaluations.get(step, 0.0) + count


def _discard(kept: FitResult, dropped: FitResult, step: str = "discarded_fit") -> None:
    """Charge ``kept`` with the cost of a fit of its frame that was not kept, as ``step``."""
    _charge(kept, step, dropped.seconds, sum(dropped.stage_evaluations.values()))


def refit_reason(config: FitConfig, error_px: float, anchor_px: float,
                 previous_swapped: list[str], swapped: list[str],
                 limbs: dict[str, float] | None = None) -> str:
    """Why sequence mode fits a frame again from scratch ('' if it keeps the warm fit
    ending ``error_px`` from the keypoints, each limb ``limbs`` px off on average,
    relabelled ``swapped``, whose neighbour was relabelled ``previous_swapped``): the fit
    lost the keypoints (over REFIT_RATIO times the anchor's error and over REFIT_MIN_PX),
    or, with ``sequence_limb_refit``, one limb's of two or more (over LIMB_RATIO times the
    anchor's error, LIMB_MIN_PX and LIMB_STANDOUT times any other limb's), or, with
    ``sequence_side_refit``, the chain overrode the detector's left and right of the same
    part (legs or arms) for the second frame running."""
    if not config.sequence_refit:
        return ""
    if error_px > max(REFIT_RATIO * anchor_px, REFIT_MIN_PX):
        return (f"{error_px:.0f} px off from its neighbour's fit ({anchor_px:.0f} for the "
                "anchor)")
    ranked = sorted((limbs or {}).items(), key=lambda item: item[1], reverse=True)
    if config.sequence_limb_refit and len(ranked) > 1:
        (name, worst), (_, runner_up) = ranked[:2]
        if worst > max(LIMB_RATIO * anchor_px, LIMB_MIN_PX, LIMB_STANDOUT * runner_up):
            return (f"its {name} {worst:.0f} px off from its neighbour's fit (the other "
                    f"limbs at most {runner_up:.0f}, the anchor {anchor_px:.0f})")
    again = sorted(set(previous_swapped) & set(swapped))
    if config.sequence_side_refit and again:
        return (f"its neighbour's fit overrode the detector's left and right of the "
                f"{' and '.join(again)} for the second frame running")
    return ""


def _charge(result: FitResult, step: str, seconds: float, evaluations: float) -> None:
    """Count work done for a frame outside its fit (a discarded fit, the anchor search) in
    its seconds and profile, so that a frame's seconds are what fitting it took."""
    result.seconds += seconds
    result.stage_seconds[step] = seconds
    result.stage_evaluations[step] = evaluations


def _errors(fitter: Fitter, result: FitResult, frame: Frame) -> torch.Tensor:
    """(25,) each body keypoint's pixel distance from the fit (metrics.keypoint_errors)."""
    return metrics.keypoint_errors(result.keypoints, frame.keypoints, fitter.camera,
                                   fitter.body.keypoint_mask, result.swapped)


def _error_px(fitter: Fitter, result: FitResult, frame: Frame) -> float:
    """The fit's reprojection error (metrics.reprojection_error)."""
    return metrics.reprojection_error(result.keypoints, frame.keypoints, fitter.camera,
                                      fitter.body.keypoint_mask, result.swapped)


def _chains(rec: Recording, names: list[str], anchor_seen: float,
            as_detected: Callable[[str], bool] | None) -> list[list[str]]:
    """Sequence mode's order: from the anchor frame forward to the last, then backward
    from the frame before it to the first. The anchor, whose body shape and placement
    every other frame inherits, is the first frame whose body keypoints' summed
    confidence is at least ``anchor_seen`` times the best frame's (FitConfig) and, with
    ``as_detected``, the first such of ANCHOR_TRIES that it accepts (else the first)."""
    seen = [_seen(rec, name) for name in names]
    well_seen = [i for i, s in enumerate(seen) if s >= anchor_seen * max(seen)]
    anchor = next((i for i in well_seen[:ANCHOR_TRIES] if as_detected(names[i])),
                  well_seen[0]) if as_detected else well_seen[0]
    return [names[anchor:], names[:anchor][::-1]]


def _seen(rec: Recording, name: str) -> float:
    """Summed detector confidence of a frame's body keypoints (0 for an unreadable file)."""
    try:
        return float(load_keypoints(rec.keypoint_path(name)).data[BODY, 2].sum())
    except InputError:
        return 0.0


def load_scene(rec: Recording, sdf_dim: int) -> Scene:
    """The recording's scene in its camera frame (its PROX SDF, else the SDF cache)."""
    return Scene.load(*load_scene_mesh(rec.scene_path), load_cam2world(rec.cam2world_path),
                      rec.sdf_paths, dim=sdf_dim)


def _load_frame(rec: Recording, name: str, camera: Camera, config: FitConfig,
                depth_camera: DepthCamera | None = None) -> Frame:
    keypoints = load_keypoints(rec.keypoint_path(name))
    depth = None
    if config.uses("depth"):
        paths = rec.depth_paths(name)
        if paths is None:
            raise InputError(rec.recording_dir / "Depth" / f"{name}.png",
                             f"configuration '{config.name}' needs Depth/ and BodyIndex/ "
                             "frames")
        depth = load_depth_points(*paths, camera, config.flip, config.depth_max_points,
                                  depth_camera=depth_camera)
    return Frame(name, keypoints, depth)


def _write_frame(out: Path, recording: str, frame: Frame, result: FitResult,
                 body: BodyModel, camera, scene: Scene, config: FitConfig,
                 sequence: bool) -> dict:
    scene_stats, flagged = metrics.scene_stats(result.vertices, body, scene)
    error = metrics.reprojection_error(result.keypoints, frame.keypoints, camera,
                                       body.keypoint_mask, result.swapped)
    joints = result.keypoints[BODY]
    stats = {"frame": frame.name, "reprojection_error_px": error, **scene_stats,
             "root_m": [round(float(x), 4) for x in joints[BODY_25.index("mid_hip")]],
             "stature_m": _stature(body, result),
             "seconds": result.seconds,
             "profile": {stage: {"seconds": round(result.stage_seconds.get(stage, 0.0), 4),
                                 "body_evaluations": round(evaluations, 1)}
                         for stage, evaluations in result.stage_evaluations.items()},
             "events": result.events,
             "sides_swapped": result.swapped,
             "flags": quality.frame_flags(scene_stats, result.vertices, joints,
                                          frame.keypoints.confidence, scene,
                                          result.underside_gap)}
    params = body.export(result.params, 0)
    params["camera"] = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                        "k": camera.k, "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                        "translation": [0, 0, 0]}
    json_path, ply_path = frame_paths(out, recording, frame.name)
    write_json(json_path, {
        "frame": frame.name, "config": config.name, "sequence": sequence, **params,
        "losses": result.losses, "stats": stats,
        "vertices_flagged": flagged,
        "timings": {"seconds": result.seconds, "stages": result.stage_seconds},
    })
    atomic_write_bytes(ply_path, ply_bytes(result.vertices.numpy(), body.faces.numpy()))
    prox_result = body.prox_result(result.params, 0)
    if prox_result is not None:
        write_pickle(json_path.with_suffix(".pkl"), prox_result)
    return stats


def _stature(body: BodyModel, result: FitResult) -> float:
    """The fitted person's standing height (m), from the fit's shape alone."""
    with torch.no_grad():
        return round(float(body.stature(result.params)[0]), 4)


def _summarise(recording: str, source: str, config: FitConfig, sequence: bool,
               frames: list[dict], failures: list[tuple[str, str]], scene_seconds: float
               ) -> dict:
    n = len(frames)
    profile = _profile(frames)
    parts = Counter(p for f in frames for p in f["contact_parts"])
    mean = lambda key: sum(f[key] for f in frames) / n if n else None  # noqa: E731
    return {
        "recording": recording, "config": config.name, "sequence": sequence,
        "frames_fitted": n, "frames_failed": len(failures),
        "failures": [{"frame": f, "error": e} for f, e in failures],
        "numerical_events": [{"frame": f["frame"], "event": e} for f in frames
                             for e in f["events"]],
        "penetration": {
            "mean_penetrating_share": mean("penetrating_share"),
            "max_depth_m": max((f["max_depth_m"] for f in frames), default=None),
        },
        "contact": {
            "share_of_frames_with_contact": (sum(bool(f["contact_parts"]) for f in frames) / n
                                             if n else None),
            "parts": {p: c / n for p, c in sorted(parts.items())},
        },
        "flagged_frames": [{"frame": f["frame"], "flags": f["flags"]} for f in frames
                           if f["flags"]],
        "reprojection_error_px": mean("reprojection_error_px"),
        # the person's height, the median of the frames' (one person a recording)
        "stature_m": (statistics.median(f["stature_m"] for f in frames) if n else None),
        "seconds_per_frame": mean("seconds"),
        "body_evaluations_per_frame": (round(sum(stage["body_evaluations"] for stage in
                                                 profile.values()), 1) if n else None),
        "profile": profile,
        "scene_setup_seconds": scene_seconds,
        "threads": torch.get_num_threads(),
        "data": source,
        "frames": frames,
    }


def _profile(frames: list[dict]) -> dict[str, dict[str, float]]:
    """Per stage, in the order they ran, the mean seconds and body evaluations (rows of a
    batch) per frame: where a fit's time goes."""
    stages: dict[str, dict[str, float]] = {}
    for frame in frames:
        for stage, cost in frame["profile"].items():
            total = stages.setdefault(stage, {"seconds": 0.0, "body_evaluations": 0.0})
            for key in total:
                total[key] += cost[key] / len(frames)
    return {stage: {key: round(value, 4 if key == "seconds" else 1)
                    for key, value in total.items()} for stage, total in stages.items()}
