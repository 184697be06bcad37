"""Whether a subject's bone scales are proportioned like the population's: each segment's scale relative to
the body's typical (median) segment scale, per axis, against the range of those proportions over the shape
space's population (shape coefficients drawn from their prior, a standard normal: the model's coefficients
are in population standard deviations).

A subject whose shape stays within the population prior has proportions within this range by construction;
one the data pulled beyond it (a tibia half again as long as its femur suggests, for instance) is reported
segment by segment. The range is the central :data:`COVERAGE` of :data:`SAMPLES` draws, a Monte Carlo
estimate (N. Metropolis and S. Ulam, "The Monte Carlo Method", Journal of the American Statistical
Association 44(247), 1949).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel

SAMPLES = 20_000
COVERAGE = 0.998  # the central share of the population's proportions taken as its range
MARGIN = 0.01
"""A proportion is outside the range when it lies more than this share beyond it. Where a segment is often
the body's median one its proportion is exactly 1 in much of the population, so the range ends at 1.00 and
a body near the mean sits on that edge, a rounding error inside or outside."""
AXES = "xyz"


@dataclass(frozen=True)
class ProportionRange:
    """low, high (n_seg, 3): the population's range of each segment's proportion per axis; segments: the
    segment names."""

    low: np.ndarray
    high: np.ndarray
    segments: tuple[str, ...]

    @classmethod
    def of(cls, model: BodyModel, seed: int = 0) -> ProportionRange:
        """The range over :data:`SAMPLES` bodies of ``model``'s population (bone coefficients ~ N(0, 1))."""
        decoder = model.decoder(torch.float64)
        mean = decoder.scale_mean.numpy()
        basis = decoder.scale_basis.numpy()
        c = np.random.default_rng(seed).standard_normal((SAMPLES, basis.shape[0]))
        scales = (mean + c @ basis).reshape(SAMPLES, -1, 3)
        ratios = proportions(scales)
        tail = (1.0 - COVERAGE) / 2.0 * 100.0
        low, high = np.percentile(ratios, [tail, 100.0 - tail], axis=0)
        return cls(low, high, tuple(model.skeleton.segments))

    def outliers(self, scales: np.ndarray) -> list[str]:
        """The segments (with axis and value, e.g. "tibia_r y 1.31 (population 1.07-1.25)") whose
        proportion in scales (n_seg, 3) lies outside the range by more than :data:`MARGIN`."""
        ratio = proportions(scales[None])[0]
        out = []
        outside = (ratio < self.low * (1.0 - MARGIN)) | (ratio > self.high * (1.0 + MARGIN))
        for s, a in zip(*np.nonzero(outside), strict=True):
            out.append(
                f"{self.segments[s]} {AXES[a]} {ratio[s, a]:.2f} (population {self.low[s, a]:.2f}-"
                f"{self.high[s, a]:.2f})"
            )
        return out


def proportions(scales: np.ndarray) -> np.ndarray:
    """(B, n_seg, 3) each segment's scale over the median segment scale of its body, per axis."""
    return scales / np.median(scales, axis=1, keepdims=True)
