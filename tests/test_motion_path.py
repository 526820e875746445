"""Sequence mode's path of least motion through each frame's warm-started fit and its fit
from scratch (prox_engine.motion_path)."""
from __future__ import annotations

import pytest
import torch

from prox_engine.motion_path import least_motion_path, medoid, motion

BODY = torch.randn(500, 3, generator=torch.Generator().manual_seed(0)) * 0.3


def at(*x: float) -> list[torch.Tensor]:
    """The body moved to each of ``x`` (m) along the camera's x axis."""
    return [BODY + torch.tensor([v, 0.0, 0.0]) for v in x]


def test_motion_is_the_mean_distance_between_the_fits_vertices():
    assert motion(*at(0.0, 0.03)) == pytest.approx(0.03, abs=1e-6)
    bent = BODY.clone()
    bent[:100] += torch.tensor([0.0, 0.0, 0.5])  # a fifth of the body moved 50 cm
    assert motion(BODY, bent) == pytest.approx(0.1, abs=1e-6)


def test_a_frame_whose_chain_jumps_keeps_its_fit_from_scratch_and_ties_keep_the_chain():
    chain, fresh = at(0.0, 0.0, 0.4, 0.0), at(0.0, 0.0, 0.02, 0.0)
    assert least_motion_path([list(c) for c in zip(chain, fresh)]) == [0, 0, 1, 0]


def test_a_chain_that_moves_together_is_kept_over_scattered_fits_from_scratch():
    chain, fresh = at(0.40, 0.41, 0.42, 0.43), at(0.0, 0.3, 0.0, 0.3)
    assert least_motion_path([list(c) for c in zip(chain, fresh)]) == [0, 0, 0, 0]


def test_the_fit_kept_before_the_window_draws_the_path_and_single_candidates_pass():
    chain, fresh = at(0.4, 0.4, 0.4), at(0.0, 0.0, 0.0)
    pairs = [list(c) for c in zip(chain, fresh)]
    assert least_motion_path(pairs) == [0, 0, 0]  # a tie: the chain
    assert least_motion_path(pairs, before=at(0.0)[0]) == [1, 1, 1]
    assert least_motion_path([at(0.0), *pairs[1:]]) == [0, 1, 1]  # the anchor has one fit
    assert least_motion_path([]) == []


def test_the_medoid_is_the_body_that_moves_least_to_the_others_among_those_allowed():
    bodies = at(0.0, 0.01, 0.02, 0.5, 0.6)
    assert medoid(bodies, list(range(5))) == 2
    assert medoid(bodies, [0, 3, 4]) == 0  # the frames seen well enough
    assert medoid(bodies, [4]) == 4


def _fit(name: str, x: float, seconds: float):
    """A fit of frame ``name``, the body at ``x`` (m), that took ``seconds`` in its final
    stage over 10 body evaluations."""
    from prox_engine.fitting import FitResult

    return FitResult(name, {}, at(x)[0], torch.zeros(118, 3), {}, seconds, {"final": seconds},
                     {"final": 10.0})


@pytest.mark.parametrize("chain_keeps, warm_at, kept", [
    ("fresh", 0.4, "fresh"), ("warm", 0.4, "fresh"), ("warm", 0.0, "warm")])
def test_a_fit_from_scratch_lent_to_the_chain_is_made_once_and_counted_once(
        chain_keeps, warm_at, kept):
    """The chain falls back on the path's fit from scratch of frame b (made ahead): it is
    lent a copy that costs nothing and keeps it or its warm fit (which, as the chain's
    checks do, counts the other's cost); the path then weighs the chain's fit against its
    own fit from scratch (one fit, where the chain kept the copy of it), nothing is fitted
    again, and whichever fit is kept counts the warm fit and the fit from scratch once."""
    from prox_engine.fitting import Frame
    from prox_engine.pipeline import _discard, _Paths

    paths = _Paths(None, window=2)  # no fitter: nothing may be fitted here
    anchor, fresh, warm = _fit("a", 0.0, 1.0), _fit("b", 0.0, 1.0), _fit("b", warm_at, 0.25)
    paths.ahead["b"] = fresh
    lent = paths.lend(Frame("b", None))
    assert lent is not fresh and lent.seconds == 0 and paths.lend(Frame("b", None)) is lent
    assert torch.equal(lent.vertices, fresh.vertices)
    chain = lent if chain_keeps == "fresh" else warm
    _discard(chain, warm if chain is lent else lent)
    assert paths.add([(Frame("a", None), anchor)], True) == []
    (_, first), (_, second) = paths.add([(Frame("b", None), chain)], False)
    assert first is anchor
    assert second is {"fresh": lent if chain is lent else fresh, "warm": warm}[kept]
    assert second.seconds == pytest.approx(1.25)
    assert sum(second.stage_evaluations.values()) == pytest.approx(20.0)
    assert not paths.ahead and not paths.lent


def test_the_chain_is_lent_the_first_fit_from_scratch_where_a_refit_replaced_it():
    """Where a refit (a floating restart, a swap check) replaced a frame's first fit from
    scratch, the chain falls back on the first fit, as it would make it alone, while the
    path weighs the refit, which counts both fits' cost."""
    from prox_engine.fitting import Frame
    from prox_engine.pipeline import _discard, _Paths

    paths = _Paths(None, window=1)
    first, refit = _fit("b", 0.3, 1.0), _fit("b", 0.0, 1.0)
    _discard(refit, first)
    paths.ahead["b"], paths.first["b"] = refit, first
    lent = paths.lend(Frame("b", None))
    assert torch.equal(lent.vertices, first.vertices) and lent.seconds == 0
    paths.before = _fit("a", 0.3, 1.0)
    ((_, kept),) = paths.add([(Frame("b", None), lent)], False)
    assert kept is lent and kept.seconds == pytest.approx(2.0)
    assert not paths.first and not paths.lent


def _paths(worse: float, chain_objective: list[float], fresh_objective: list[float],
           chain_penetration: float = 900.0):
    """Which fit (warm-started: True) sequence mode's path (pipeline._Paths, with
    ``sequence_path_worse`` = ``worse``) keeps of each frame of a window, and the fit: the
    chain's fits one body moving together (0.40 m on), the frames' fits from scratch
    scattered (0.0 and 0.3 m), with the keypoints' and posture's costs given, the scene's
    penetration 900 (the chain's ``chain_penetration``), the warm fits' temporal term 50."""
    from prox_engine.fitting import FitResult, Frame
    from prox_engine.pipeline import _Paths

    def fit(name: str, x: float, objective: float, warm: bool) -> FitResult:
        losses = {"data": objective - 10.0, "pose_prior": 10.0,
                  "penetration": chain_penetration if warm else 900.0,
                  **({"temporal": 50.0} if warm else {})}
        return FitResult(name, {}, at(x)[0], torch.zeros(118, 3), losses, 0.25,
                         {"final": 0.25}, {"final": 40.0})

    paths = _Paths(None, window=len(chain_objective), worse=worse)  # nothing fitted here
    names = [f"f{i}" for i in range(len(chain_objective))]
    paths.ahead = {name: fit(name, 0.3 * (i % 2), objective, False)
                   for i, (name, objective) in enumerate(zip(names, fresh_objective))}
    kept = paths.add([(Frame(name, None), fit(name, 0.40 + 0.01 * i, objective, True))
                      for i, (name, objective) in enumerate(zip(names, chain_objective))],
                     fresh=False)
    return [("temporal" in fit.losses, fit) for _, fit in kept]


def test_the_path_leaves_off_a_fit_far_worse_at_the_keypoints_and_posture_than_its_other():
    """A chain that carried a wrong posture on moves least, and the path kept it; its fit
    of the second frame, at 10 times the keypoints' and posture's cost of the frame's fit
    from scratch, is left off, its cost charged to the fit kept. Under 3 times, with the
    rule off (`prox-path-motion-only`), or 10 times as deep in the scene, the chain stands;
    a fit from scratch far worse than the chain's is left off alike."""
    kept = _paths(3.0, [400.0, 4000.0, 400.0], [300.0, 400.0, 300.0])
    assert [warm for warm, _ in kept] == [True, False, True]
    second = kept[1][1]
    assert any("warm-started fit left off the path" in e and "4000" in e
               for e in second.events), second.events
    assert second.stage_seconds["warm_fit"] == 0.25 and second.seconds == 0.5
    assert second.stage_evaluations["warm_fit"] == 40.0
    for worse, chain in ((3.0, [400.0, 1100.0, 400.0]), (0.0, [400.0, 4000.0, 400.0])):
        assert [warm for warm, _ in _paths(worse, chain, [300.0, 400.0, 300.0])] == [True] * 3
    kept = _paths(3.0, [400.0, 400.0, 400.0], [300.0, 400.0, 300.0], chain_penetration=9000.0)
    assert all(warm and not fit.events for warm, fit in kept)
    kept = _paths(3.0, [400.0, 400.0, 400.0], [300.0, 1300.0, 300.0])
    assert all(warm for warm, _ in kept)
    assert any("fit from scratch left off" in e for e in kept[1][1].events)
    assert kept[1][1].stage_seconds["fresh_fit"] == 0.25
