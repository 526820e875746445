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
