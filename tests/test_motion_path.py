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


@pytest.mark.parametrize("warm_at, fresh_at, kept", [(0.4, 0.0, "fresh"), (0.0, 0.4, "warm")])
def test_a_fit_from_scratch_lent_to_the_chain_is_weighed_by_the_path_and_counted_once(
        warm_at, fresh_at, kept):
    """The chain fell back on the path's fit from scratch of a frame (a label or floating
    check) and kept its warm fit, which carries the fit from scratch's cost: the path weighs
    the two without fitting the frame from scratch again, and whichever it keeps counts
    both fits once."""
    from prox_engine.fitting import FitResult, Frame
    from prox_engine.pipeline import _discard, _Paths

    def fit(name: str, x: float, seconds: float) -> FitResult:
        return FitResult(name, {}, at(x)[0], torch.zeros(118, 3), {}, seconds,
                         {"final": seconds}, {"final": 10.0})

    paths = _Paths(None, window=2)  # no fitter: nothing may be fitted here
    anchor, fresh = fit("a", 0.0, 1.0), fit("b", fresh_at, 1.0)
    paths.ahead["b"] = fresh
    assert paths.lend(Frame("b", None)) is fresh
    warm = fit("b", warm_at, 0.25)
    _discard(warm, fresh)  # as the chain's checks do when they keep the warm fit
    assert paths.add([(Frame("a", None), anchor)], True) == []
    (_, first), (_, second) = paths.add([(Frame("b", None), warm)], False)
    assert first is anchor and second is (fresh if kept == "fresh" else warm)
    assert second.seconds == pytest.approx(1.25)
    assert sum(second.stage_evaluations.values()) == pytest.approx(20.0)
    assert not paths.ahead and not paths.lent
