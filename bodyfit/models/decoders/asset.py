"""The spiral decoder asset (``spiral_d<d>.npz``): writing it, and loading it only for the body model it was
trained on.

The file holds the pooling hierarchy and spirals of the template, the decoder's weights, the training
codes' mean and spread, and the sha256 of the ``body.npz`` whose bone-corrected template it adds to. A
mismatch with the installed body model (another template, other bone correctives) is refused at load.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.models.assets import read_manifest, verified_asset, write_manifest
from bodyfit.models.body.model import ANATOMICAL_JOINTS, BODY_ASSET, BodyModel, BodyOutput
from bodyfit.models.decoders.export import SpiralBody, bone_only_decoder
from bodyfit.models.decoders.spiral import Hierarchy, SpiralDecoder
from bodyfit.models.decoders.train import Trained
from bodyfit.models.errors import AssetError, ShapeError
from bodyfit.models.skeleton.model import check_finite

FORMAT = "bodyfit-spiral-identity-1"
RETRAIN_HINT = "retrain it with `bodyfit decoders train` (or restore assets/ with `git checkout assets/`)"
# Identity codes further than this from the training codes' mean (in their standard deviations) are refused.
MAX_CODE_SD = 5.0


def asset_name(d: int) -> str:
    return f"spiral_d{d}.npz"


def save_asset(trained: Trained, hierarchy: Hierarchy, folder: Path, metrics: dict[str, Any]) -> Path:
    """Write ``spiral_d<d>.npz`` into ``folder`` for the body model there, and its manifest entry (sha256,
    d, the body model's sha256, ``metrics``)."""
    body_sha = read_manifest(folder)["files"][BODY_ASSET]["sha256"]
    d = trained.decoder.d
    weights = {f"w/{k}": v.detach().float().numpy() for k, v in trained.decoder.state_dict().items()
               if k in dict(trained.decoder.named_parameters())}  # fmt: skip
    path = folder / asset_name(d)
    arrays: dict[str, Any] = {
        "format": np.asarray(FORMAT),
        "body_sha256": np.asarray(body_sha),
        "d": np.asarray(d),
        "latent_mean": trained.latent_mean.astype(np.float32),
        "latent_std": trained.latent_std.astype(np.float32),
        **hierarchy.arrays(),
        **weights,
    }
    np.savez_compressed(path, **arrays)
    write_manifest(
        folder, {path.name: {"d": d, "format": FORMAT, "body_sha256": body_sha, "metrics": metrics}}, {}
    )
    return path


@dataclass(frozen=True)
class SpiralAsset:
    """A loaded asset: the decoder and the training codes' mean and spread (d,)."""

    decoder: SpiralDecoder
    latent_mean: np.ndarray
    latent_std: np.ndarray


def load_asset(d: int = 8, folder: Path | None = None) -> SpiralAsset:
    """Load ``spiral_d<d>.npz`` after checking its hash against the manifest and its body model against the
    installed ``body.npz``.

    Raises:
        AssetError: missing, corrupted, of another format, or trained for another body model.
    """
    path = verified_asset(asset_name(d), folder)
    body_sha = read_manifest(folder)["files"][BODY_ASSET]["sha256"]
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise AssetError(f"cannot read {path}: {exc}; {RETRAIN_HINT}") from exc
    if str(data.get("format")) != FORMAT:
        raise AssetError(f"{path} is not a {FORMAT} asset (format {data.get('format')!s}); {RETRAIN_HINT}")
    if str(data["body_sha256"]) != body_sha:
        raise AssetError(
            f"{path} was trained for the body model {str(data['body_sha256'])[:12]}..., but the installed "
            f"{BODY_ASSET} is {body_sha[:12]}...: its offsets would sit on another template; {RETRAIN_HINT}"
        )
    decoder = SpiralDecoder(Hierarchy.from_arrays(data), int(data["d"]))
    state = {k[2:]: torch.as_tensor(v) for k, v in data.items() if k.startswith("w/")}
    missing = set(dict(decoder.named_parameters())) - set(state)
    if missing:
        raise AssetError(f"{path} lacks the decoder weights {sorted(missing)}; {RETRAIN_HINT}")
    decoder.load_state_dict(state, strict=False)
    return SpiralAsset(decoder.eval(), data["latent_mean"], data["latent_std"])


class SpiralBodyModel:
    """The body model with the spiral identity decoder: validated forward, like :class:`BodyModel`.

    Shape coefficients are [bone coefficients (n_bone), identity code (d)], both in standard deviations.
    """

    def __init__(self, body: BodyModel, asset: SpiralAsset) -> None:
        self.body, self.asset = body, asset
        self.n_bone, self.d = body.n_bone, asset.decoder.d
        self.joint_names = [name for name, _, _ in ANATOMICAL_JOINTS]
        decoder = bone_only_decoder(body.skeleton, body.data, torch.float32)
        self.module = SpiralBody(decoder, asset.decoder, asset.latent_mean, asset.latent_std)

    @classmethod
    def load(cls, d: int = 8, folder: Path | None = None) -> SpiralBodyModel:
        return cls(BodyModel.load(folder), load_asset(d, folder))

    @property
    def n_shape(self) -> int:
        return self.n_bone + self.d

    def validate_shape(self, shape: torch.Tensor | np.ndarray | None, batch: int) -> torch.Tensor:
        """(B, n_bone + d) float32 coefficients; None is the mean body. Refuses a wrong size, NaN, and
        identity codes beyond :data:`MAX_CODE_SD` standard deviations."""
        if shape is None:
            return torch.zeros(batch, self.n_shape)
        t = torch.as_tensor(np.asarray(shape) if isinstance(shape, np.ndarray) else shape).float()
        if t.ndim != 2 or t.shape != (batch, self.n_shape):
            raise ShapeError(
                f"shape coefficients must have shape ({batch}, {self.n_shape}): {self.n_bone} bone "
                f"coefficients then a {self.d}-dimensional spiral identity code; got {tuple(t.shape)}"
            )
        check_finite("shape coefficients", t)
        far = t[:, self.n_bone :].abs() > MAX_CODE_SD
        if bool(far.any()):
            b, k = (int(i) for i in torch.nonzero(far)[0])
            raise ShapeError(
                f"identity code {k} of body {b} is {float(t[b, self.n_bone + k]):.2f} standard deviations "
                f"from the training bodies' mean; the spiral decoder accepts codes within +-{MAX_CODE_SD:g}"
            )
        return t

    def forward(
        self,
        shape: torch.Tensor | np.ndarray | None = None,
        coordinates: torch.Tensor | np.ndarray | None = None,
        root: torch.Tensor | np.ndarray | None = None,
    ) -> BodyOutput:
        """Validated forward (float32): vertices (B, V, 3) and joints (B, J, 3); see :meth:`BodyModel.forward`
        for the coordinates and root."""
        if coordinates is None:
            batch = 1 if shape is None else int(np.shape(shape)[0])
            coordinates = np.zeros((batch, self.body.skeleton.n_dof))
        q, r, _ = self.body.skeleton.validate(coordinates, root, dtype=torch.float32)
        c = self.validate_shape(shape, q.shape[0])
        r = torch.zeros(q.shape[0], 3) if r is None else r
        with torch.no_grad():
            vertices, joints = self.module(c, q, r)
            scales, _ = self.module.body._shape_terms(c[:, : self.n_bone])
            frames = self.module.body.fk(q, r, scales).frames
        return BodyOutput(vertices, joints, frames, scales)
