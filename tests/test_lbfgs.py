"""Several L-BFGS problems stepped in lockstep: each group of rows as if alone."""
import numpy as np
import torch

from prox_engine import lbfgs


def _rosenbrock(x: torch.Tensor, stiffness: torch.Tensor) -> torch.Tensor:
    """(B,) Rosenbrock functions of rows (B, 2), each with its own stiffness."""
    return (1 - x[:, 0]) ** 2 + stiffness * (x[:, 1] - x[:, 0] ** 2) ** 2


def _lockstep(start: torch.Tensor, stiffness: torch.Tensor, groups: list[slice],
              max_iter: int, max_calls: int = 1) -> torch.Tensor:
    x = start.clone().requires_grad_(True)

    def objective():
        losses = _rosenbrock(x, stiffness)
        return lambda rows: losses[rows].sum()

    lbfgs.minimise([x], objective, groups, max_iter, max_calls, ftol=1e-9)
    return x.detach()


def _torch(start: torch.Tensor, stiffness: torch.Tensor, max_iter: int) -> torch.Tensor:
    """torch.optim.LBFGS over all rows' summed loss (one call)."""
    x = start.clone().requires_grad_(True)
    optimizer = torch.optim.LBFGS([x], lr=1.0, max_iter=max_iter,
                                  line_search_fn="strong_wolfe", tolerance_grad=1e-7,
                                  tolerance_change=1e-10, history_size=20)

    def closure():
        optimizer.zero_grad()
        loss = _rosenbrock(x, stiffness).sum()
        loss.backward()
        return loss

    optimizer.step(closure)
    return x.detach()


START = torch.tensor([[-1.2, 1.0], [3.0, -2.0], [0.5, 2.5]], dtype=torch.float64)
STIFFNESS = torch.tensor([100.0, 1e5, 10.0], dtype=torch.float64)


def test_one_group_follows_torch():
    """A single group takes torch's L-BFGS steps (its two-loop recursion compiled: the
    same steps up to rounding)."""
    for max_iter in (5, 40):
        torch.testing.assert_close(_lockstep(START, STIFFNESS, [slice(0, 3)], max_iter),
                                   _torch(START, STIFFNESS, max_iter), rtol=1e-9, atol=1e-9)


def test_each_group_is_minimised_as_if_alone():
    """Three rows as three groups: each ends where torch's L-BFGS takes it alone (one
    optimizer over the three let the stiff row's line searches cut the others' steps:
    after 5 iterations the first row was elsewhere)."""
    together = _lockstep(START, STIFFNESS, [slice(i, i + 1) for i in range(3)], 5)
    for row in range(3):
        alone = _torch(START[row:row + 1], STIFFNESS[row:row + 1], 5)
        torch.testing.assert_close(together[row], alone[0], rtol=1e-9, atol=1e-9)
    assert not torch.allclose(_torch(START, STIFFNESS, 5)[0], together[0], atol=1e-3)
    done = _lockstep(START, STIFFNESS, [slice(i, i + 1) for i in range(3)], 100, 3)
    assert torch.allclose(done, torch.ones(3, 2, dtype=torch.float64), atol=1e-5)


class _DirectRosenbrock(lbfgs.Direct):
    """:func:`_rosenbrock` with its gradient in closed form, on ``x``'s memory."""

    def __init__(self, x: torch.Tensor, stiffness: torch.Tensor) -> None:
        self.x, self.stiffness = x.detach().numpy(), stiffness.numpy()

    def evaluate(self):
        a, b = self.x[:, 0], self.x[:, 1]
        bend = b - a ** 2
        gradient = np.stack([-2 * (1 - a) - 4 * self.stiffness * bend * a,
                             2 * self.stiffness * bend], 1)
        return (1 - a) ** 2 + self.stiffness * bend ** 2, [gradient]


def test_a_direct_objective_takes_the_autograd_objectives_steps():
    """An objective that works out its own gradient (:class:`lbfgs.Direct`) is minimised
    as the same objective through autograd, group by group."""
    groups = [slice(0, 1), slice(1, 3)]
    x = START.clone().requires_grad_(True)
    lbfgs.minimise([x], _DirectRosenbrock(x, STIFFNESS), groups, 8, 2, ftol=1e-9)
    expected = torch.cat([_lockstep(START[g], STIFFNESS[g], [slice(0, g.stop - g.start)], 8, 2)
                          for g in groups])
    torch.testing.assert_close(x.detach(), expected, rtol=1e-12, atol=1e-12)
    assert not torch.allclose(x.detach(), START)


def test_a_failed_call_is_undone_for_its_group_only():
    """A group whose objective raises beyond x = 0.5 (as anny's shape prior rejects
    non-finite parameters) keeps its point from before the call and is reported; the
    other group, evaluated in the same rounds, reaches its minimum."""
    x = torch.zeros(2, 2, dtype=torch.float64, requires_grad=True)
    target = torch.full((2,), 2.0, dtype=torch.float64)

    def objective():
        if bool((x[0].detach() > 0.5).any()):
            raise ValueError("out of the support")
        loss = ((x - target) ** 2).sum(1)
        return lambda rows: loss[rows].sum()

    failed = lbfgs.minimise([x], objective, [slice(0, 1), slice(1, 2)], max_iter=50)
    assert failed == [True, False]
    assert torch.allclose(x[1].detach(), target, atol=1e-6)
    assert torch.equal(x[0].detach(), torch.zeros(2, dtype=torch.float64))


def _two_loop(grad, steps, changes, rho, scale):
    """torch's two-loop recursion, as torch.optim.LBFGS writes it."""
    al = [None] * len(steps)
    q = grad.neg()
    for i in range(len(steps) - 1, -1, -1):
        al[i] = steps[i].dot(q) * rho[i]
        q.add_(changes[i], alpha=-al[i])
    r = q * scale
    for i in range(len(steps)):
        r.add_(steps[i], alpha=al[i] - changes[i].dot(r) * rho[i])
    return r


def test_the_direction_is_the_two_loop_recursion_over_the_last_pairs():
    """Pairs' direction is torch's two-loop recursion over the pairs kept: all of them,
    or the last ``size`` once more were added."""
    torch.manual_seed(0)
    for m in (0, 1, 5, 20, 27):
        steps = [torch.randn(30, dtype=torch.float64) for _ in range(m)]
        changes = [s + 0.3 * torch.randn(30, dtype=torch.float64) for s in steps]
        rho = [1 / float(y.dot(s)) for y, s in zip(changes, steps)]
        pairs = lbfgs.Pairs(20, 30)
        for s, y, r in zip(steps, changes, rho):
            pairs.add(s.numpy(), y.numpy(), r)
        kept = slice(max(0, m - 20), m)
        grad = torch.randn(30, dtype=torch.float64)
        torch.testing.assert_close(
            torch.from_numpy(pairs.direction(grad.numpy(), 0.7)),
            _two_loop(grad, steps[kept], changes[kept], rho[kept], 0.7))


def test_groups_still_running_go_on_over_their_own_rows_alone():
    """With ``narrow``, once a group has ended the others are evaluated on variables of
    their own rows (the ended group's rows are no longer evaluated) and end where they
    end without it; the ended group keeps its point."""
    groups = [slice(0, 1), slice(1, 2), slice(2, 3)]
    evaluated, narrowed = [], []

    def objective_on(x: torch.Tensor, stiffness: torch.Tensor):
        def objective():
            evaluated.append(len(x))
            losses = _rosenbrock(x, stiffness)
            return lambda rows: losses[rows].sum()
        return objective

    def narrow(rows: torch.Tensor):
        narrowed.append(rows.tolist())
        kept = x.detach()[rows].clone().requires_grad_(True)
        return [kept], objective_on(kept, STIFFNESS[rows])

    x = START.clone().requires_grad_(True)
    lbfgs.minimise([x], objective_on(x, STIFFNESS), groups, 40, ftol=1e-9, narrow=narrow)
    plain = _lockstep(START, STIFFNESS, groups, 40)
    torch.testing.assert_close(x.detach(), plain, rtol=1e-9, atol=1e-9)
    assert narrowed and all(len(rows) < 3 for rows in narrowed)
    assert min(evaluated) < 3 and evaluated[-1] == len(narrowed[-1])
    for earlier, later in zip(narrowed, narrowed[1:]):
        assert set(later) < set(earlier)
