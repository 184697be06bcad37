"""Training the spiral identity decoder as an auto-decoder, and fitting its latent code to a body.

BLSM eq. 17 (H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned
Model of the Human Mesh", European Conference on Computer Vision (ECCV), 2020): the decoder's weights and
one latent code per training body are optimised together (Adam: D. P. Kingma and J. Ba, "Adam: A Method
for Stochastic Optimization", ICLR, 2015) to minimise the mean per-vertex distance to the bodies' identity
offsets. The codes start at the bodies' identity-PCA coefficients (the decoder starts as that PCA), and a
new body's code is found by Levenberg-Marquardt from its PCA projection (:func:`fit_latents`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.models.body.shape_space import PCA, fit_pca
from bodyfit.models.decoders.spiral import Hierarchy, SpiralDecoder, dense


@dataclass(frozen=True)
class TrainConfig:
    """Latent size, wall-clock budget and the optimiser's settings (BLSM section 5.1's rates, except the
    codes', which are in standard deviations here)."""

    d: int = 8
    minutes: float = 14.0
    batch: int = 16
    lr_net: float = 1e-3
    lr_latent: float = 1e-2
    weight_decay: float = 5e-5
    seed: int = 0
    epochs: int | None = None  # stop after this many epochs, if the time budget lasts


@dataclass
class Trained:
    """A trained decoder with its training codes' per-dimension mean and spread (d,) and the run's log."""

    decoder: SpiralDecoder
    latent_mean: np.ndarray
    latent_std: np.ndarray
    history: list[dict[str, float]] = field(default_factory=list)


def vertex_distance(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean per-vertex Euclidean distance of (B, V, 3) tensors (metres); smooth at zero."""
    return torch.sqrt(((pred - target) ** 2).sum(-1) + 1e-14).mean()


def pca_of(offsets: np.ndarray, d: int) -> PCA:
    """Identity PCA with d components of offsets (N, V, 3) (:func:`shape_space.fit_pca`)."""
    return fit_pca(offsets.reshape(len(offsets), -1).astype(np.float64), d)


def pca_codes(pca: PCA, offsets: np.ndarray) -> np.ndarray:
    """Coefficients (N, d) of offsets (N, V, 3), in standard deviations."""
    return pca.project(offsets.reshape(len(offsets), -1).astype(np.float64))


def _optimisers(
    decoder: SpiralDecoder, codes: torch.nn.Embedding, config: TrainConfig
) -> list[torch.optim.Optimizer]:
    """Adam with decoupled weight decay (I. Loshchilov and F. Hutter, "Decoupled Weight Decay
    Regularization", ICLR, 2019: a decay added to gradients this small would be all Adam sees) on the
    convolutions and the fully connected layer; sparse Adam on the codes, so that a code moves only when its
    body is in the batch. The linear term stays the PCA's: for a squared loss no other
    d-dimensional linear map does better, and the convolutions learn what it leaves."""
    net = [p for n, p in decoder.named_parameters() if n not in ("linear", "mean")]
    return [
        torch.optim.AdamW(net, lr=config.lr_net, weight_decay=config.weight_decay),
        torch.optim.SparseAdam(list(codes.parameters()), lr=config.lr_latent),
    ]


def train_spiral(
    hierarchy: Hierarchy,
    offsets: np.ndarray,
    config: TrainConfig,
    checkpoint: Path | None = None,
    log: Callable[[str], None] = print,
    device: str = "cpu",
) -> Trained:
    """Train on identity offsets (N, V, 3) metres for ``config.minutes`` (whole epochs, cosine-decayed rates),
    saving a checkpoint after each epoch. On a GPU ``device`` the gathers run dense (:func:`dense`)."""
    torch.manual_seed(config.seed)
    pca = pca_of(offsets, config.d)
    decoder = SpiralDecoder(hierarchy, config.d, pca.basis.reshape(config.d, -1, 3), pca.mean).to(device)
    if device != "cpu":
        dense(decoder)
    decoder.linear.requires_grad_(False)
    decoder.mean.requires_grad_(False)
    init = torch.as_tensor(pca_codes(pca, offsets), dtype=torch.float32, device=device)
    codes = torch.nn.Embedding.from_pretrained(init, freeze=False, sparse=True)
    target = torch.as_tensor(offsets, dtype=torch.float32, device=device)
    opts = _optimisers(decoder, codes, config)
    base = [opt.param_groups[0]["lr"] for opt in opts]
    clock = _Clock(config.minutes * 60.0, config.epochs)
    history: list[dict[str, float]] = []
    while clock.another(len(history)):
        scale = 0.5 * (1.0 + math.cos(math.pi * min(clock.progress(len(history)), 1.0)))
        for opt, lr in zip(opts, base, strict=True):
            opt.param_groups[0]["lr"] = lr * max(scale, 0.02)
        losses = []
        for batch in torch.randperm(len(target), device=device).split(config.batch):
            loss = 1e3 * vertex_distance(decoder(codes(batch)), target[batch])  # mm
            for opt in opts:
                opt.zero_grad()
            loss.backward()
            for opt in opts:
                opt.step()
            losses.append(float(loss.detach()))
        history.append(
            {"epoch": len(history) + 1, "train_mm": float(np.mean(losses)), "seconds": clock.seconds()}
        )
        log(f"spiral d={config.d} epoch {len(history)}: train {history[-1]['train_mm']:.3f} mm "
            f"({history[-1]['seconds']:.0f} s)")  # fmt: skip
        trained = _finish(decoder, codes, history)
        if checkpoint is not None:
            save_checkpoint(trained, hierarchy, config, checkpoint)
    return trained


class _Clock:
    """The training run's budget: seconds, and optionally a number of epochs."""

    def __init__(self, budget: float, epochs: int | None) -> None:
        self.budget, self.epochs, self.t0 = budget, epochs, time.perf_counter()

    def seconds(self) -> float:
        return round(time.perf_counter() - self.t0, 1)

    def progress(self, epoch: int) -> float:
        """Fraction of the run done: of the time budget, or of the epochs when that comes first."""
        done = (time.perf_counter() - self.t0) / self.budget
        return max(done, epoch / self.epochs) if self.epochs else done

    def another(self, epoch: int) -> bool:
        """Whole epochs: none that would likely overrun the budget, none past the epochs asked for."""
        if epoch == 0:
            return True
        in_time = (time.perf_counter() - self.t0) * (epoch + 1) / epoch <= self.budget
        return in_time and (self.epochs is None or epoch < self.epochs)


def _finish(decoder: SpiralDecoder, codes: torch.nn.Embedding, history: list[dict[str, float]]) -> Trained:
    z = codes.weight.detach().cpu().double().numpy()
    return Trained(decoder, z.mean(axis=0), z.std(axis=0), list(history))


def save_checkpoint(trained: Trained, hierarchy: Hierarchy, config: TrainConfig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "state": {k: v.cpu() for k, v in trained.decoder.state_dict().items()},
            "latent_mean": trained.latent_mean,
            "latent_std": trained.latent_std,
            "history": trained.history,
            "config": asdict(config),
            "hierarchy": hierarchy.arrays(),
        },
        path,
    )


def load_checkpoint(path: Path) -> tuple[Trained, Hierarchy, TrainConfig]:
    ck: dict[str, Any] = torch.load(path, weights_only=False)
    hierarchy = Hierarchy.from_arrays(ck["hierarchy"])
    config = TrainConfig(**ck["config"])
    decoder = SpiralDecoder(hierarchy, config.d)
    decoder.load_state_dict(ck["state"])
    return Trained(decoder, ck["latent_mean"], ck["latent_std"], ck["history"]), hierarchy, config


def fit_latents(
    decoder: SpiralDecoder,
    offsets: np.ndarray,
    init: np.ndarray,
    iterations: int = 8,
    step: float = 1e-2,
) -> np.ndarray:
    """Codes (N, d) whose decoding is nearest (least squares) to offsets (N, V, 3), from ``init`` (N, d).

    Levenberg-Marquardt (K. Levenberg, "A Method for the Solution of Certain Non-Linear Problems in Least
    Squares", Quarterly of Applied Mathematics 2(2), 1944; D. W. Marquardt, "An Algorithm for Least-Squares
    Estimation of Nonlinear Parameters", SIAM Journal on Applied Mathematics 11(2), 1963) with a
    forward-difference Jacobian (d + 1 decodings per iteration; ``step`` in code units) and a step kept
    only where it lowers a body's error.
    """
    out = np.array(init, np.float64)
    dev = decoder.mean.device
    batch = max(1, 400 // out.shape[1])  # the Jacobians of a batch: about 1 GB in float64
    with torch.no_grad():
        for start in range(0, len(out), batch):
            sl = slice(start, start + batch)
            target = torch.as_tensor(offsets[sl], dtype=torch.float32, device=dev)
            out[sl] = (
                _lm(decoder, target, torch.as_tensor(out[sl], device=dev), iterations, step).cpu().numpy()
            )
    return out


def _lm(
    decoder: SpiralDecoder, target: torch.Tensor, z: torch.Tensor, iterations: int, h: float
) -> torch.Tensor:
    """Batched Levenberg-Marquardt on codes z (B, d) float64 against target (B, V, 3)."""
    B, d = z.shape
    eye = torch.eye(d, dtype=torch.float64, device=z.device)
    damping = torch.full((B,), 1e-3, dtype=torch.float64, device=z.device)

    def residual(zz: torch.Tensor) -> torch.Tensor:
        return (decoder(zz.float()) - target).reshape(B, -1).double()

    r = residual(z)
    cost = (r**2).sum(1)
    for _ in range(iterations):
        J = torch.stack([(residual(z + h * eye[k]) - r) / h for k in range(d)], dim=2)  # (B, 3V, d)
        JtJ = J.transpose(1, 2) @ J
        g = (J.transpose(1, 2) @ r.unsqueeze(2)).squeeze(2)
        A = JtJ + damping[:, None, None] * torch.diag_embed(torch.diagonal(JtJ, dim1=1, dim2=2) + 1e-12)
        z_new = z - torch.linalg.solve(A, g)
        r_new = residual(z_new)
        cost_new = (r_new**2).sum(1)
        better = cost_new < cost
        z = torch.where(better[:, None], z_new, z)
        r = torch.where(better[:, None], r_new, r)
        cost = torch.where(better, cost_new, cost)
        damping = torch.where(better, damping * 0.3, damping * 10.0)
    return z


def reconstruction_mm(decoded: np.ndarray, offsets: np.ndarray) -> tuple[float, float]:
    """Mean and max per-vertex distance (mm) between (N, V, 3) arrays in metres."""
    e = np.linalg.norm(decoded - offsets, axis=-1) * 1e3
    return float(e.mean()), float(e.max())


def decode(decoder: SpiralDecoder, codes: np.ndarray, batch: int = 50) -> np.ndarray:
    """Offsets (N, V, 3) of codes (N, d)."""
    dev = decoder.mean.device
    with torch.no_grad():
        parts = [decoder(torch.as_tensor(c, dtype=torch.float32, device=dev)).cpu().double().numpy()
                 for c in np.array_split(codes, max(1, math.ceil(len(codes) / batch)))]  # fmt: skip
    return np.concatenate(parts)


def compare(trained: Trained, pca: PCA, offsets: np.ndarray, iterations: int = 8) -> dict[str, float]:
    """Held-out comparison on offsets (N, V, 3): the spiral decoder with codes fitted by
    :func:`fit_latents` from the PCA projection, against the projection on the d-component PCA fitted on
    the same training bodies (the best the linear space can do). Mean and max mm."""
    init = pca_codes(pca, offsets)
    pca_rec = pca.reconstruct(init).reshape(offsets.shape)
    codes = fit_latents(trained.decoder, offsets, init, iterations)
    spiral_rec = decode(trained.decoder, codes)
    s, p = reconstruction_mm(spiral_rec, offsets), reconstruction_mm(pca_rec, offsets)
    return {
        "spiral_mm": s[0],
        "spiral_max_mm": s[1],
        "pca_mm": p[0],
        "pca_max_mm": p[1],
        "ratio": s[0] / p[0],
    }
