"""anny's shape prior, -log p(phenotype | adult age) under its calibrated age-conditioned
Beta distributions, with its gradient worked out alongside, in numpy.

The scene stages free the shape, and each of their evaluations pays the prior: about forty
operations on (B, 8) tensors, 0.5 ms in torch (0.2 of it the lgamma and digamma calls), an
eighth of a scene evaluation. The same arithmetic in numpy float64 on arrays this small
costs a fifth of that."""
from __future__ import annotations

import numpy as np
import torch
from scipy.special import expit, gammaln, psi

AGE_SPREAD = 0.05  # the age held at the adult's: a Gaussian of this spread (anny's units)
CLAMP = 1e-3  # phenotypes are read within [CLAMP, 1 - CLAMP]


class PhenotypePrior:
    """The prior of shape logits (B, 6) (gender, age, then phenotypes; the columns
    ``columns`` are those with Beta distributions) for the boys' then the girls' Beta
    parameters ``alpha``, ``beta`` (anchors, 2 * len(columns)) tabulated at the ages
    ``anchors`` (piecewise linear between them, as anny interpolates them), at the
    ``adult`` age. With p = sigmoid(logits) clamped, gender g = p_0 and age p_1:

        prior = ((age - adult) / 0.05)^2 / 2 - sum_sex share * log Beta(x; a, b),

    share = 1 - g for the boys' and g for the girls', x the phenotype; d log Beta / dx =
    (a - 1) / x - (b - 1) / (1 - x), d / da = log x + psi(a + b) - psi(a), d / db =
    log(1 - x) + psi(a + b) - psi(b)."""

    def __init__(self, anchors: torch.Tensor, alpha: torch.Tensor, beta: torch.Tensor,
                 columns: list[int], adult: float) -> None:
        self.anchors = anchors.double().numpy()
        self.alpha, self.beta = alpha.double().numpy(), beta.double().numpy()
        self.columns, self.adult = np.asarray(columns), float(adult)

    def __call__(self, shape: torch.Tensor) -> torch.Tensor:
        """The prior (B,) of shape logits (B, 6), differentiable in them."""
        return _Prior.apply(shape, self)

    def parameters(self, age: np.ndarray) -> tuple[np.ndarray, ...]:
        """Beta parameters a, b (B, 2 * columns) at anny ages (B,) (clamped to the
        anchors' range) and their slopes in age (0 outside that range)."""
        anchors, alpha, beta = self.anchors, self.alpha, self.beta
        low, high = anchors[0], anchors[-1]
        held = np.clip(age, low, high)
        upper = np.clip(np.searchsorted(anchors, held), 1, len(anchors) - 1)
        width = anchors[upper] - anchors[upper - 1]
        along = ((held - anchors[upper - 1]) / width)[:, None]
        within = np.where((age >= low) & (age <= high), 1 / width, 0.0)[:, None]
        return ((1 - along) * alpha[upper - 1] + along * alpha[upper],
                (1 - along) * beta[upper - 1] + along * beta[upper],
                (alpha[upper] - alpha[upper - 1]) * within,
                (beta[upper] - beta[upper - 1]) * within)

    def value_and_gradient(self, logits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The prior (B,) of logits (B, 6) and its gradient in them (B, 6)."""
        logistic = expit(logits)
        p = np.clip(logistic, CLAMP, 1 - CLAMP)
        gender, age = p[:, 0:1], p[:, 1]
        a, b, a_slope, b_slope = self.parameters(age)
        x = np.tile(p[:, self.columns], 2)
        log_x, log_rest = np.log(x), np.log1p(-x)
        log_prob = ((a - 1) * log_x + (b - 1) * log_rest + gammaln(a + b) - gammaln(a)
                    - gammaln(b))
        half = len(self.columns)
        share = np.concatenate([np.repeat(1 - gender, half, 1), np.repeat(gender, half, 1)], 1)
        off = age - self.adult
        value = (off / AGE_SPREAD) ** 2 / 2 - (share * log_prob).sum(1)
        both = psi(a + b)
        by_age = ((log_x + both - psi(a)) * a_slope + (log_rest + both - psi(b)) * b_slope)
        by_x = -share * ((a - 1) / x - (b - 1) / (1 - x))
        gradient = np.zeros_like(p)
        gradient[:, self.columns] = by_x[:, :half] + by_x[:, half:]
        gradient[:, 0] = (log_prob[:, :half] - log_prob[:, half:]).sum(1)
        gradient[:, 1] = off / AGE_SPREAD ** 2 - (share * by_age).sum(1)
        clamped = (logistic < CLAMP) | (logistic > 1 - CLAMP)
        return value, gradient * logistic * (1 - logistic) * ~clamped


class _Prior(torch.autograd.Function):
    @staticmethod
    def forward(ctx, shape: torch.Tensor, prior: PhenotypePrior) -> torch.Tensor:
        value, gradient = prior.value_and_gradient(shape.detach().double().numpy())
        ctx.save_for_backward(torch.from_numpy(gradient).to(shape.dtype))
        return torch.from_numpy(value).to(shape.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        (gradient,) = ctx.saved_tensors
        return grad[:, None] * gradient, None
