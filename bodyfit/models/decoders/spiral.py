"""BLSM's spiral mesh-convolution identity decoder: a latent code (B, d) -> identity offsets (B, V, 3).

The decoder of H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned
Model of the Human Mesh", European Conference on Computer Vision (ECCV), 2020 (eq. 9-11, section 5.1): a
fully connected layer to the coarsest mesh of a decimation hierarchy, then blocks of spiral convolution,
ELU and barycentric up-sampling to the finer level, and a last linear spiral convolution to 3 channels on
the template. Spiral convolution is that of G. Bouritsas, S. Bokhnyak, S. Ploumpis, M. Bronstein and
S. Zafeiriou, "Neural 3D Morphable Models: Spiral Convolutional Networks for 3D Shape Representation Learning
and Generation", ICCV, 2019 (fixed length as in S. Gong, L. Chen, M. Bronstein and S. Zafeiriou,
"SpiralNet++: A Fast and Highly Efficient Mesh Convolution Operator", ICCV Workshops, 2019). The
hierarchy and spirals come from :mod:`mesh_hierarchy`.

Two choices of ours: the decoder's output is added to a linear map of the same latent (initialised with
the identity PCA, so training starts from the linear model and the convolutions learn what it misses), and
there is no batch normalisation (a body is decoded alone at inference; the learned scale sits in the weights).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from bodyfit.models.decoders import mesh_hierarchy as mh

# BLSM section 5.1: filters per convolution, coarse to fine, and the up-sampling factor after each.
CHANNELS = (48, 32, 32, 16)
FACTORS = (2, 2, 2, 4)
SPIRAL_LENGTH = 9
# The convolutions output millimetres: unit-sized activations for the millimetres the linear term misses.
OUTPUT_SCALE = 0.001


@dataclass(frozen=True)
class Hierarchy:
    """Meshes finest first: spirals[i] (V_i, L) at level i; up[i] = (index (V_i, 3), weight (V_i, 3)) carrying
    level i + 1 onto level i."""

    spirals: list[np.ndarray]
    up: list[tuple[np.ndarray, np.ndarray]]

    @property
    def sizes(self) -> list[int]:
        return [len(s) for s in self.spirals]

    def arrays(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for i, s in enumerate(self.spirals):
            out[f"spiral_{i}"] = s.astype(np.int32)
        for i, (idx, w) in enumerate(self.up):
            out[f"up_index_{i}"], out[f"up_weight_{i}"] = idx.astype(np.int32), w.astype(np.float32)
        return out

    @classmethod
    def from_arrays(cls, data: dict[str, np.ndarray]) -> Hierarchy:
        n = sum(1 for k in data if k.startswith("spiral_"))
        spirals = [np.asarray(data[f"spiral_{i}"], np.int64) for i in range(n)]
        up = [
            (np.asarray(data[f"up_index_{i}"], np.int64), np.asarray(data[f"up_weight_{i}"], np.float64))
            for i in range(n - 1)
        ]
        return cls(spirals, up)


def build_hierarchy(
    vertices: np.ndarray, faces: np.ndarray, factors: tuple[int, ...] = FACTORS, length: int = SPIRAL_LENGTH
) -> Hierarchy:
    """Decimate the template (V, 3), (F, 3) by ``factors`` applied from the finest level (the last of BLSM's
    up-sampling factors is the first decimation) and compute every level's spirals and up-sampling."""
    levels = [
        mh.Level(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), np.arange(len(vertices)))
    ]
    for f in reversed(factors):
        levels.append(mh.decimate(levels[-1].vertices, levels[-1].faces, len(levels[-1].vertices) // f))
    spirals = [mh.spirals(lv.vertices, lv.faces, length) for lv in levels]
    up = [mh.upsampling(levels[i].vertices, levels[i + 1]) for i in range(len(levels) - 1)]
    return Hierarchy(spirals, up)


class Gather(nn.Module):
    """y_v = sum_k w_vk x_index(v,k) over rows of x (N, F) -> (V, F): a fixed sparse (V, N) matrix.

    With ``sparse`` (the default) float32 inputs are multiplied by the sparse matrix (its backward is one
    more sparse product, far cheaper than scattering a gather's gradient); otherwise, and for ONNX export
    (:func:`dense`), one gather of the K V rows, weighted, and summed over k by a (1, K) GEMV: few graph
    nodes, and no ReduceSum, which ONNX Runtime runs slowly on these shapes.
    """

    index: torch.Tensor
    weight: torch.Tensor
    ones: torch.Tensor

    def __init__(self, index: np.ndarray, weight: np.ndarray, n_rows: int) -> None:
        """index, weight (V, K); n_rows the N of the x it takes."""
        super().__init__()
        V, K = index.shape
        self.shape, self.n_rows, self.sparse = (V, K), n_rows, True
        self.unit = bool(np.all(weight == 1.0))
        self.register_buffer("index", torch.as_tensor(np.ascontiguousarray(index.T), dtype=torch.long))
        self.register_buffer(
            "weight", torch.as_tensor(np.ascontiguousarray(weight.T), dtype=torch.float32)[..., None]
        )
        self._matrix: torch.Tensor | None = None
        self.register_buffer("ones", torch.ones(1, K), persistent=False)

    def matrix(self) -> torch.Tensor:
        """The (V, N) float32 CSR matrix, built on first use."""
        if self._matrix is None:
            V, K = self.shape
            rows = torch.arange(V, device=self.index.device).repeat(K)
            coo = torch.sparse_coo_tensor(
                torch.stack([rows, self.index.reshape(-1)]),
                self.weight.reshape(-1),
                (V, self.n_rows),
                check_invariants=True,
            )
            self._matrix = coo.coalesce().to_sparse_csr()
        return self._matrix

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.sparse and x.dtype == torch.float32:
            return self.matrix() @ x
        V, K = self.shape
        g = x.index_select(0, self.index.reshape(-1)).reshape(K, V, x.shape[1])
        g = g if self.unit else g * self.weight.to(x.dtype)
        return (self.ones.to(x.dtype) @ g.reshape(K, -1)).reshape(V, x.shape[1])


def dense(module: nn.Module) -> nn.Module:
    """Switch every :class:`Gather` in ``module`` to gather-and-sum (what ONNX export traces); returns it."""
    for m in module.modules():
        if isinstance(m, Gather):
            m.sparse = False
    return module


class SpiralConv(nn.Module):
    """y_v = W [x_s(v,1), ..., x_s(v,L)] + b over each vertex's spiral s(v, .) (Bouritsas et al. 2019).

    Computed as products then a gather, y_v = sum_l (x W_l)_s(v,l), the same sum: the gather then moves
    c_out numbers per spiral entry, fewer than c_in where the channels narrow, on the finest levels.
    Training stacks the L products, (L, V, B, c_out), for the sparse matrix of :class:`Gather`; inference
    and ONNX (:func:`dense`) make them one GEMM, (V B, c_in) @ (c_in, L c_out), and gather its rows.
    Activations are vertex-major, (V, B, C).
    """

    rows: torch.Tensor
    ones: torch.Tensor

    def __init__(self, spiral: np.ndarray, c_in: int, c_out: int) -> None:
        """spiral (V, L) vertex indices."""
        super().__init__()
        V, L = spiral.shape
        self.c_in, self.c_out, self.length = c_in, c_out, L
        self.linear = nn.Linear(L * c_in, c_out)
        # Row of (position l, vertex s(v, l)) in the stacked (L * V) products.
        flat = np.arange(L)[None] * V + spiral
        self.gather = Gather(flat, np.ones(flat.shape), V * L)
        # Row of (vertex s(v, l), position l) in the dense path's (V * L) products.
        rows = spiral * L + np.arange(L)[None]
        self.register_buffer("rows", torch.as_tensor(np.ascontiguousarray(rows.T), dtype=torch.long))
        self.register_buffer("ones", torch.ones(1, L), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (V, B, c_in) -> (V, B, c_out)."""
        V, B, L = x.shape[0], x.shape[1], self.length
        if not (self.gather.sparse and x.dtype == torch.float32):
            return self._gathered(x)
        W = self.linear.weight.reshape(self.c_out, L, self.c_in).permute(1, 2, 0)  # (L, c_in, c_out)
        table = torch.matmul(x.reshape(1, V * B, self.c_in), W)  # (L, V * B, c_out)
        return self.gather(table.reshape(L * V, B * self.c_out)).reshape(V, B, self.c_out) + self.linear.bias

    def _gathered(self, x: torch.Tensor) -> torch.Tensor:
        """The dense path: products (V, L, B, c_out) from one GEMM, one gather of L V fixed rows, summed
        over l by a GEMV (as in :class:`Gather`)."""
        V, B, L = x.shape[0], x.shape[1], self.length
        W = self.linear.weight.reshape(self.c_out, L, self.c_in).permute(2, 1, 0).reshape(self.c_in, -1)
        table = (x.reshape(V * B, self.c_in) @ W.to(x.dtype)).reshape(V, B, L, self.c_out)
        table = table.transpose(1, 2).reshape(V * L, B * self.c_out)
        gathered = table.index_select(0, self.rows.reshape(-1)).reshape(L, V * B * self.c_out)
        summed = self.ones.to(x.dtype) @ gathered
        return summed.reshape(V, B, self.c_out) + self.linear.bias.to(x.dtype)


class Upsample(nn.Module):
    """Barycentric up-sampling: each fine vertex a weighted sum of three coarse ones (Ranjan et al. 2018)."""

    def __init__(self, index: np.ndarray, weight: np.ndarray, n_coarse: int) -> None:
        """index, weight (V_fine, 3)."""
        super().__init__()
        self.gather = Gather(index, weight, n_coarse)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (V_coarse, B, C) -> (V_fine, B, C)."""
        return self.gather(x.reshape(x.shape[0], -1)).reshape(-1, x.shape[1], x.shape[2])


class SpiralDecoder(nn.Module):
    """Latent z (B, d) -> identity offsets (B, V, 3) metres: linear(z) + spiral_net(z)."""

    def __init__(
        self,
        hierarchy: Hierarchy,
        d: int,
        linear_basis: np.ndarray | None = None,
        mean: np.ndarray | None = None,
    ) -> None:
        """``linear_basis`` (d, V, 3) and ``mean`` (V, 3) initialise the linear term (the identity PCA's
        first d rows and its mean); the convolutions' last layer starts at zero, so the untrained decoder is
        that linear model."""
        super().__init__()
        sizes = hierarchy.sizes
        n = len(sizes)
        self.d, self.n_vertices = d, sizes[0]
        self.fc = nn.Linear(d, sizes[-1] * CHANNELS[0])
        convs, ups = [], []
        widths = [CHANNELS[0], *CHANNELS]  # the fully connected layer's features, then each convolution's
        for k in range(n - 1):  # coarsest level n - 1 up to level 1
            level = n - 1 - k
            convs.append(SpiralConv(hierarchy.spirals[level], widths[k], widths[k + 1]))
            ups.append(Upsample(*hierarchy.up[level - 1], sizes[level]))
        self.convs, self.ups = nn.ModuleList(convs), nn.ModuleList(ups)
        self.out = SpiralConv(hierarchy.spirals[0], widths[n - 1], 3)
        nn.init.zeros_(self.out.linear.weight)
        nn.init.zeros_(self.out.linear.bias)
        basis = np.zeros((d, sizes[0], 3)) if linear_basis is None else linear_basis
        self.linear = nn.Parameter(torch.as_tensor(basis.reshape(d, -1), dtype=torch.float32))
        mean = np.zeros(sizes[0] * 3) if mean is None else mean
        self.mean = nn.Parameter(torch.as_tensor(mean.reshape(-1), dtype=torch.float32))
        self.act = nn.ELU()

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """z (B, d) -> offsets (B, V, 3)."""
        B = z.shape[0]
        x = self.fc(z).reshape(B, -1, CHANNELS[0]).transpose(0, 1)
        for conv, up in zip(self.convs, self.ups, strict=True):
            x = up(self.act(conv(x)))
        conv = OUTPUT_SCALE * self.out(x).transpose(0, 1)
        return conv + (self.mean + z @ self.linear).reshape(B, self.n_vertices, 3)
