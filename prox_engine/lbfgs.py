"""torch's L-BFGS with strong Wolfe line search, for several independent problems at once.

One ``torch.optim.LBFGS`` over a batch minimises the batch's summed loss as a single
problem: one line search sets one step for every frame, one history mixes their
curvatures, and a frame's fit depends on which frames it is batched with (``prox fit
--batch 8`` on tuning seed 0: 131 mm PJE against 82 one frame at a time). Here each group
of rows (a frame's candidate bodies) runs torch's algorithm as a coroutine of its own, and
the groups advance in lockstep: every round poses the points all groups ask for in one
batched evaluation. A group follows the iterations it follows alone, up to the rounding
of batched arithmetic; a group fitted alone follows ``torch.optim.LBFGS`` up to rounding.

The algorithm's own arithmetic (points, line searches) is numpy's in float64 on vectors
of a few hundred values, where each torch operation cost 1-5 us: a third of a keypoint
evaluation's time went into the optimiser around it; its directions are compiled
(:func:`_two_loop`).
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from itertools import accumulate
from typing import Callable, Generator

import numba
import numpy as np
import torch

# Evaluates the model at the variables' current values and returns each group's loss.
Objective = Callable[[], Callable[[slice], torch.Tensor]]
# A coroutine yields the flat point (float64) it wants evaluated and is sent (loss,
# gradient) there, or None when the evaluation failed (a non-finite point some term
# rejects).
Evaluation = tuple[float, np.ndarray] | None
Search = Generator[np.ndarray, Evaluation, tuple]
# Given the rows (ascending) of the groups still running, variables of their own over just
# those rows, holding the values there, and the objective on them.
Narrow = Callable[[torch.Tensor], tuple[list[torch.Tensor], "Objective | Direct"]]


class Direct(ABC):
    """An objective that works out its gradient itself, without autograd."""

    @abstractmethod
    def evaluate(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """At the variables' current values: each row's loss (B,) and the gradient of
        their sum in each variable (its shape)."""


class _Failed(Exception):
    """The evaluation of a point this group asked for failed."""


def row_groups(rows: int, groups: int) -> list[slice]:
    """``rows`` split into ``groups`` consecutive groups of as many rows (a frame's)."""
    return sized_groups([rows // groups] * groups)


def sized_groups(sizes: list[int]) -> list[slice]:
    """Consecutive groups of rows of the given ``sizes`` (each frame's candidates)."""
    return [slice(end - size, end) for size, end in zip(sizes, accumulate(sizes))]


def packed(groups: list[slice]) -> tuple[torch.Tensor, list[slice]]:
    """The rows of ``groups`` (indices, in order) and where each group's lie among them."""
    rows = torch.cat([torch.arange(group.start, group.stop) for group in groups])
    return rows, sized_groups([group.stop - group.start for group in groups])


def minimise(variables: list[torch.Tensor], objective: Objective | Direct,
             groups: list[slice], max_iter: int, max_calls: int = 1,
             ftol: float | None = None, history: int = 20, narrow: Narrow | None = None
             ) -> list[bool]:
    """Minimise each group's loss, ``objective()(rows)`` (a :class:`Direct` one: its rows'
    sum of ``objective.evaluate()``), over its ``rows`` of
    ``variables`` (leaf tensors (B, ...); a group's loss must depend on its rows only), in
    place.

    Per group, up to ``max_calls`` calls of torch's L-BFGS step (``max_iter`` iterations,
    strong Wolfe, history ``history``), stopped early once a call changes the group's loss
    by at most ``ftol`` times itself (at least 1). A call that fails or ends on non-finite
    values is undone and ends the group's minimisation. Returns, per group, whether that
    happened. With ``narrow``, each time groups end the others go on over their own rows
    alone (``narrow(rows)``), so that a group that has ended stops costing."""
    values = [v.detach().numpy() for v in variables]
    coroutines = [_calls(_flat(values, rows), max_iter, max_calls, ftol, history)
                  for rows in groups]
    asked = {i: next(c) for i, c in enumerate(coroutines)}
    resting = dict(asked)  # each group's rows hold a point evaluated without failing
    failed = [False] * len(groups)
    running = (variables, objective, groups)  # what the running groups are evaluated on
    held = len(groups)  # how many groups' rows ``running`` holds
    while asked:
        if narrow is not None and len(asked) < held:
            running, held = _narrowed(variables, groups, asked, resting, narrow), len(asked)
        answers = _evaluate(*running, asked, resting)
        for i, answer in answers.items():
            try:
                asked[i] = coroutines[i].send(answer)
            except StopIteration as stop:
                point, failed[i] = stop.value
                _assign(variables, groups[i], point)
                del asked[i]
    return failed


def _narrowed(variables: list[torch.Tensor], groups: list[slice],
              asked: dict[int, np.ndarray], resting: dict[int, np.ndarray], narrow: Narrow
              ) -> tuple[list[torch.Tensor], Objective | Direct, list[slice | None]]:
    """The variables and objective of the ``asked`` groups' rows alone (``narrow``),
    their rows first set to where they rest, and each such group's rows in them (None for
    the groups that have ended)."""
    kept = sorted(asked)
    for i in kept:
        _assign(variables, groups[i], resting[i])
    rows, packed_groups = packed([groups[i] for i in kept])
    narrowed, objective = narrow(rows)
    placed: list[slice | None] = [None] * len(groups)
    for i, rows_now in zip(kept, packed_groups):
        placed[i] = rows_now
    return narrowed, objective, placed


def _evaluate(variables: list[torch.Tensor], objective: Objective | Direct,
              groups: list[slice | None], asked: dict[int, np.ndarray],
              resting: dict[int, np.ndarray]) -> dict[int, Evaluation]:
    """Each asking group's loss and flat gradient at its point, in one evaluation; its rows
    then rest there (``resting``: every running group asks each round, so no group's rows
    need putting back). A group whose point is not finite gets None, and so does one whose
    point makes the objective raise (found by evaluating the groups one by one from their
    resting points, which only happens then)."""
    finite = {i: x for i, x in asked.items() if np.isfinite(x).all()}
    answers: dict[int, Evaluation] = {i: None for i in asked if i not in finite}
    try:
        answers.update(_answers(variables, objective, groups, finite, resting))
    except (IndexError, ValueError):
        for i, x in finite.items():
            try:
                answers.update(_answers(variables, objective, groups, {i: x}, resting))
            except (IndexError, ValueError):
                answers[i] = None
    return answers


def _answers(variables: list[torch.Tensor], objective: Objective | Direct,
             groups: list[slice | None], points: dict[int, np.ndarray],
             resting: dict[int, np.ndarray]) -> dict[int, tuple[float, np.ndarray]]:
    """Loss and flat gradient of the groups at ``points``, where their rows then rest;
    if the evaluation raises, they are put back to their ``resting`` points first."""
    if not points:
        return {}
    for i, x in points.items():
        _assign(variables, groups[i], x)
    try:
        if isinstance(objective, Direct):
            rows, grads = objective.evaluate()
            losses = {i: float(rows[groups[i]].sum()) for i in points}
        else:
            with torch.enable_grad():
                loss_of = objective()
                found = {i: loss_of(groups[i]) for i in points}
                grads = torch.autograd.grad(sum(found.values()), variables, allow_unused=True)
            losses = {i: float(loss.detach()) for i, loss in found.items()}
            grads = [np.zeros(v.shape, np.float32) if g is None else g.numpy()
                     for g, v in zip(grads, variables)]
    except BaseException:
        for i in points:
            _assign(variables, groups[i], resting[i])
        raise
    resting.update(points)
    return {i: (loss, _flat(grads, groups[i])) for i, loss in losses.items()}


def _flat(arrays: list[np.ndarray], rows: slice) -> np.ndarray:
    """A group's rows of ``arrays`` (its parameters or their gradients) as torch's L-BFGS
    flattens them, variable by variable, in float64."""
    return np.concatenate([a[rows].reshape(-1) for a in arrays]).astype(np.float64)


def _assign(variables: list[torch.Tensor], rows: slice, point: np.ndarray) -> None:
    """The variables' ``rows`` set to the flat ``point`` (in their own dtype), through
    numpy views of their memory (a torch index and copy per variable cost 5 us). No
    graph reads them meanwhile: each evaluation's graph is built after its points are set
    and spent before the next are."""
    offset = 0
    for v in variables:
        part = v.detach().numpy()[rows]
        part[...] = point[offset:offset + part.size].reshape(part.shape)
        offset += part.size


def _calls(x: np.ndarray, max_iter: int, max_calls: int, ftol: float | None,
           history: int) -> Search:
    """A group's minimisation: up to ``max_calls`` calls of torch's step, each undone if
    it fails, the loss compared before and after each. Returns the final point and whether
    a call was undone."""
    state: dict = {"n_iter": 0, "pairs": Pairs(history, len(x)), "H_diag": 1}
    answer = yield x
    for call in range(max_calls):
        backup = x
        try:
            if answer is None:
                raise _Failed
            x, loss = yield from _step(x, answer, state, max_iter, history)
        except (_Failed, IndexError, ValueError):
            loss = math.nan
        if not (math.isfinite(loss) and np.isfinite(x).all()):
            return backup, True
        if call + 1 == max_calls:
            break
        answer = yield x  # where the call ended: the settling test and the next call
        if ftol is not None and answer is not None and (
                abs(loss - answer[0]) <= ftol * max(1.0, abs(answer[0]))):
            break
    return x, False


def _step(x: np.ndarray, answer: tuple[float, np.ndarray], state: dict, max_iter: int,
          history: int, tolerance_grad: float = 1e-7, tolerance_change: float = 1e-10
          ) -> Generator[np.ndarray, Evaluation, tuple[np.ndarray, float]]:
    """``torch.optim.LBFGS.step`` (lr 1, strong Wolfe) from ``x`` where the loss and flat
    gradient are ``answer``; returns the new point and the loss at the call's start."""
    max_eval = max_iter * 5 // 4
    orig_loss, flat_grad = answer
    loss, current_evals = orig_loss, 1
    if np.abs(flat_grad).max() <= tolerance_grad:
        return x, orig_loss
    d, t = state.get("d"), state.get("t")
    pairs = state["pairs"]
    prev_flat_grad, prev_loss = state.get("prev_flat_grad"), state.get("prev_loss")
    n_iter = 0
    while n_iter < max_iter:
        n_iter += 1
        state["n_iter"] += 1
        if state["n_iter"] == 1:
            d = -flat_grad
        else:
            y = flat_grad - prev_flat_grad
            s = d * t
            ys = float(y @ s)
            if ys > 1e-10:
                pairs.add(s, y, 1.0 / ys)
                state["H_diag"] = ys / float(y @ y)
            d = pairs.direction(flat_grad, state["H_diag"])
        prev_flat_grad, prev_loss = flat_grad, loss
        t = min(1.0, 1.0 / float(np.abs(flat_grad).sum())) if state["n_iter"] == 1 else 1.0
        gtd = float(flat_grad @ d)
        if gtd > -tolerance_change:
            break
        loss, flat_grad, t, ls_func_evals = yield from _strong_wolfe(
            x, t, d, loss, flat_grad, gtd, max_ls=max_eval - current_evals)
        x = x + t * d
        opt_cond = np.abs(flat_grad).max() <= tolerance_grad
        current_evals += ls_func_evals
        if (n_iter == max_iter or current_evals >= max_eval or opt_cond
                or np.abs(d * t).max() <= tolerance_change
                or abs(loss - prev_loss) < tolerance_change):
            break
    state.update(d=d, t=t, prev_flat_grad=prev_flat_grad, prev_loss=prev_loss)
    return x, orig_loss


class Pairs:
    """L-BFGS's last ``size`` pairs of steps s_i and gradient changes y_i of ``n``
    variables (float64), with rho_i = 1 / (y_i . s_i), in a ring of slots kept from step
    to step, and the direction they give (:func:`_two_loop`)."""

    def __init__(self, size: int, n: int) -> None:
        self.size, self.count, self.start = size, 0, 0
        self.pairs = np.zeros((2 * size, n))  # the steps' slots, then the changes'
        self.rho = np.zeros(size)

    def add(self, s: np.ndarray, y: np.ndarray, rho: float) -> None:
        size = self.size
        if self.count == size:  # full: the oldest pair goes, its slot the new one's
            slot, self.start = self.start, (self.start + 1) % size
        else:
            slot, self.count = self.count, self.count + 1
        self.pairs[slot], self.pairs[size + slot], self.rho[slot] = s, y, rho

    def direction(self, grad: np.ndarray, scale: float) -> np.ndarray:
        """-H grad for the inverse Hessian H of the pairs with H_0 = ``scale`` I."""
        return _two_loop(self.pairs, self.start, self.count, self.rho, grad, scale)


def compile_directions() -> None:
    """Compile :func:`_two_loop` now, or load it from numba's cache (0.3 s, once a
    process): ``prox setup`` fills the cache, and a worker calls this before it forks, so
    that no job pays for it."""
    pairs = Pairs(1, 1)
    pairs.add(np.ones(1), np.ones(1), 1.0)
    pairs.direction(np.ones(1), 1.0)


@numba.njit(cache=True)
def _two_loop(pairs: np.ndarray, start: int, m: int, rho: np.ndarray, grad: np.ndarray,
              scale: float) -> np.ndarray:
    """torch's two-loop recursion, compiled: -H ``grad`` for the inverse Hessian H of the
    ``m`` pairs in the ring of slots of ``pairs`` (steps, then changes), the oldest at
    slot ``start``, with H_0 = ``scale`` I. As numpy and torch operations (4m products
    and updates of the variables, or two triangular systems in their inner products) a
    step cost 110-130 us in a fit, 35 ms of a frame."""
    size, n = pairs.shape[0] // 2, len(grad)
    direction = -grad
    alpha = np.empty(m)
    for back in range(m - 1, -1, -1):  # newest first: a_i = rho_i s_i . q, q -= a_i y_i
        i = (start + back) % size
        a = 0.0
        for j in range(n):
            a += pairs[i, j] * direction[j]
        alpha[back] = a * rho[i]
        for j in range(n):
            direction[j] -= alpha[back] * pairs[size + i, j]
    direction *= scale
    for k in range(m):  # oldest first: r += s_i (a_i - rho_i y_i . r)
        i = (start + k) % size
        b = 0.0
        for j in range(n):
            b += pairs[size + i, j] * direction[j]
        b = alpha[k] - b * rho[i]
        for j in range(n):
            direction[j] += b * pairs[i, j]
    return direction


def _cubic_interpolate(x1: float, f1: float, g1: float, x2: float, f2: float, g2: float,
                       bounds: tuple[float, float] | None = None) -> float:
    """torch's ``_cubic_interpolate`` on floats: the minimiser of the cubic through two
    points with their values and slopes, within ``bounds``."""
    xmin_bound, xmax_bound = bounds if bounds is not None else (min(x1, x2), max(x1, x2))
    d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
    d2_square = d1 ** 2 - g1 * g2
    if d2_square < 0:
        return (xmin_bound + xmax_bound) / 2.0
    d2 = math.sqrt(d2_square)
    if x1 <= x2:
        min_pos = x2 - (x2 - x1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
    else:
        min_pos = x1 - (x1 - x2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
    return min(max(min_pos, xmin_bound), xmax_bound)


def _strong_wolfe(x, t, d, f, g, gtd, c1=1e-4, c2=0.9, tolerance_change=1e-9, max_ls=25):
    """torch's ``_strong_wolfe``, asking for the points it evaluates instead of calling,
    on float64 arrays and floats (no array is changed in place, so none is copied)."""

    def evaluate(step):
        answer = yield x + step * d
        if answer is None:
            raise _Failed
        return answer

    d_norm = np.abs(d).max()
    f_new, g_new = yield from evaluate(t)
    ls_func_evals = 1
    gtd_new = float(g_new @ d)
    t_prev, f_prev, g_prev, gtd_prev = 0, f, g, gtd
    done = False
    ls_iter = 0
    while ls_iter < max_ls:
        if f_new > (f + c1 * t * gtd) or (ls_iter > 1 and f_new >= f_prev):
            bracket, bracket_f = [t_prev, t], [f_prev, f_new]
            bracket_g = [g_prev, g_new]
            bracket_gtd = [gtd_prev, gtd_new]
            break
        if abs(gtd_new) <= -c2 * gtd:
            bracket, bracket_f, bracket_g = [t], [f_new], [g_new]
            done = True
            break
        if gtd_new >= 0:
            bracket, bracket_f = [t_prev, t], [f_prev, f_new]
            bracket_g = [g_prev, g_new]
            bracket_gtd = [gtd_prev, gtd_new]
            break
        min_step = t + 0.01 * (t - t_prev)
        max_step = t * 10
        tmp = t
        t = _cubic_interpolate(t_prev, f_prev, gtd_prev, t, f_new, gtd_new,
                               bounds=(min_step, max_step))
        t_prev, f_prev = tmp, f_new
        g_prev = g_new
        gtd_prev = gtd_new
        f_new, g_new = yield from evaluate(t)
        ls_func_evals += 1
        gtd_new = float(g_new @ d)
        ls_iter += 1
    if ls_iter == max_ls:
        bracket, bracket_f, bracket_g = [0, t], [f, f_new], [g, g_new]
    insuf_progress = False
    low_pos, high_pos = (0, 1) if bracket_f[0] <= bracket_f[-1] else (1, 0)
    while not done and ls_iter < max_ls:
        if abs(bracket[1] - bracket[0]) * d_norm < tolerance_change:
            break
        t = _cubic_interpolate(bracket[0], bracket_f[0], bracket_gtd[0],
                               bracket[1], bracket_f[1], bracket_gtd[1])
        eps = 0.1 * (max(bracket) - min(bracket))
        if min(max(bracket) - t, t - min(bracket)) < eps:
            if insuf_progress or t >= max(bracket) or t <= min(bracket):
                if abs(t - max(bracket)) < abs(t - min(bracket)):
                    t = max(bracket) - eps
                else:
                    t = min(bracket) + eps
                insuf_progress = False
            else:
                insuf_progress = True
        else:
            insuf_progress = False
        f_new, g_new = yield from evaluate(t)
        ls_func_evals += 1
        gtd_new = float(g_new @ d)
        ls_iter += 1
        if f_new > (f + c1 * t * gtd) or f_new >= bracket_f[low_pos]:
            bracket[high_pos] = t
            bracket_f[high_pos] = f_new
            bracket_g[high_pos] = g_new
            bracket_gtd[high_pos] = gtd_new
            low_pos, high_pos = (0, 1) if bracket_f[0] <= bracket_f[1] else (1, 0)
        else:
            if abs(gtd_new) <= -c2 * gtd:
                done = True
            elif gtd_new * (bracket[high_pos] - bracket[low_pos]) >= 0:
                bracket[high_pos] = bracket[low_pos]
                bracket_f[high_pos] = bracket_f[low_pos]
                bracket_g[high_pos] = bracket_g[low_pos]
                bracket_gtd[high_pos] = bracket_gtd[low_pos]
            bracket[low_pos] = t
            bracket_f[low_pos] = f_new
            bracket_g[low_pos] = g_new
            bracket_gtd[low_pos] = gtd_new
    t = bracket[low_pos]
    f_new = bracket_f[low_pos]
    g_new = bracket_g[low_pos]
    return f_new, g_new, t, ls_func_evals
