"""A small software renderer for triangle meshes: gallery PNGs of bodies with the skeleton inside.

Pure numpy (plus PIL for writing PNGs and drawing their labels); no OpenGL, no matplotlib. Orthographic
camera, flat per-face Lambert shading with the light at the camera, a vectorised z-buffer for opaque meshes
and an "x-ray" composite for translucent ones. :func:`tile` lays renders out in a grid and
:func:`label_grid` titles its columns and rows.

World convention: metres, +Y up, +X forward (the body faces +X), +Z is the body's right. Views:

* ``"front"``: camera on +X looking toward -X; image right = -Z, so the body's right side appears on the
  image left, like a photo of a person facing you.
* ``"side"``: camera on +Z looking toward -Z; image right = +X, so the body faces image right.
* ``"back"``: camera on -X looking toward +X; image right = +Z.

Image up is +Y in every view.

Translucent meshes (``opacity < 1``) are drawn *x-ray style*: each one is rasterised with its own z-buffer
(so only its nearest surface counts) and then alpha-composited, with alpha = opacity, over everything drawn
before it wherever it covers a pixel, **regardless of depth**. Bones inside a translucent skin therefore
stay visible, and so does an opaque object in front of a translucent one (tinted by it). Translucent meshes
are composited after all opaque meshes, in the order given.

Example::

    img = render([RenderMesh(bone_v, bone_f, (0.93, 0.89, 0.80)),
                  RenderMesh(skin_v, skin_f, (0.85, 0.65, 0.55), opacity=0.35)], view="front")
    save_png(img, "gallery/body_front.png")
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bodyfit.models.errors import BodyfitError, NonFiniteError, ShapeError

if TYPE_CHECKING:
    from PIL import ImageDraw

VIEWS = ("front", "side", "back")

# Fraction of the light that is ambient; the rest is Lambert |n·l| with the light at the camera.
_AMBIENT = 0.3
# Margin around the fitted bounding box, as a fraction of the smaller image side.
_MARGIN = 0.04
# Most candidate pixels (triangles x bounding-box pixels) evaluated at once; bounds temporary memory.
_CHUNK_PIXELS = 1 << 21
# Triangles whose doubled screen area (in pixels²) is below this are degenerate and skipped.
_MIN_AREA2 = 1e-12
# Labels: dark grey text, and the blank pixels kept around each label.
_INK = (34, 34, 34)
_LABEL_MARGIN = 8


@dataclass(frozen=True, eq=False)
class RenderMesh:
    """One triangle mesh to draw.

    Attributes:
        vertices: (V, 3) float world positions in metres.
        faces: (F, 3) integer vertex indices in ``[0, V)``; winding does not matter.
        color: (r, g, b), each in 0..1.
        opacity: 1 draws the mesh opaque (z-buffered); below 1 draws it x-ray style (see the module
            docstring); 0 draws nothing.

    Inputs are checked on construction; a ``ValueError`` (``ShapeError``, ``NonFiniteError`` or
    ``BodyfitError``) says what is wrong. Equality is identity (arrays have no single truth value).
    """

    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float]
    opacity: float = 1.0

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ShapeError(f"RenderMesh vertices must have shape (V, 3); got {v.shape}")
        if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
            raise ShapeError(f"RenderMesh vertices must be numbers; got dtype {v.dtype}")
        if not np.isfinite(v).all():
            bad = np.argwhere(~np.isfinite(v))[0].tolist()
            raise NonFiniteError(
                f"RenderMesh vertices contain NaN or infinite values (first at index {bad}); "
                "send finite positions"
            )
        f = np.asarray(self.faces)
        if f.ndim != 2 or f.shape[1] != 3:
            raise ShapeError(f"RenderMesh faces must have shape (F, 3) (triangles); got {f.shape}")
        if f.size and not np.issubdtype(f.dtype, np.integer):
            raise ShapeError(f"RenderMesh faces must be integer vertex indices; got dtype {f.dtype}")
        if f.size and (int(f.min()) < 0 or int(f.max()) >= len(v)):
            raise ShapeError(
                f"RenderMesh face indices must lie in [0, {len(v)}) for {len(v)} vertices; "
                f"got values from {int(f.min())} to {int(f.max())}"
            )
        _check_rgb("RenderMesh color", self.color)
        if not (isinstance(self.opacity, int | float | np.number) and 0.0 <= float(self.opacity) <= 1.0):
            raise BodyfitError(f"RenderMesh opacity must be a number in [0, 1]; got {self.opacity!r}")


def render(
    meshes: Sequence[RenderMesh],
    view: str = "front",
    size: tuple[int, int] = (512, 768),
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Render meshes with an orthographic camera.

    Args:
        meshes: the meshes; opaque ones (opacity 1) are z-buffered together, translucent ones are then
            composited x-ray style in the order given (see the module docstring).
        view: ``"front"``, ``"side"`` or ``"back"`` (see the module docstring for the axes).
        size: (width, height) of the image in pixels.
        background: (r, g, b) in 0..1.
        bounds: (min xyz (3,), max xyz (3,)) world box to fit into the image; default the union bounding box
            of all mesh vertices. Pass the same bounds to several renders to give them one scale.
    Returns:
        (height, width, 3) uint8 RGB image.
    """
    if view not in VIEWS:
        raise BodyfitError(f"unknown view {view!r}; use one of {', '.join(VIEWS)}")
    if (
        len(size) != 2
        or not all(isinstance(s, int | np.integer) and not isinstance(s, bool) for s in size)
        or min(size) < 1
    ):
        raise ShapeError(f"size must be (width, height) as two positive integers; got {size!r}")
    width, height = int(size[0]), int(size[1])
    _check_rgb("background", background)
    for i, m in enumerate(meshes):
        if not isinstance(m, RenderMesh):
            raise BodyfitError(f"meshes[{i}] must be a RenderMesh; got {type(m).__name__}")
    lo, hi = _bounds(meshes, bounds)

    project, toward_camera = _camera(view)
    scale, offset = _fit(project, lo, hi, width, height)

    image = np.empty((height, width, 3), np.float64)
    image[:] = np.asarray(background, np.float64)
    opaque = [m for m in meshes if float(m.opacity) >= 1.0]
    translucent = [m for m in meshes if 0.0 < float(m.opacity) < 1.0]

    if opaque:
        verts = np.concatenate([np.asarray(m.vertices, np.float64) for m in opaque])
        starts = np.cumsum([0] + [len(m.vertices) for m in opaque[:-1]])
        faces = np.concatenate(
            [np.asarray(m.faces, np.int64).reshape(-1, 3) + s for m, s in zip(opaque, starts)]
        )
        colors = np.concatenate([np.tile(np.asarray(m.color, np.float64), (len(m.faces), 1)) for m in opaque])
        pix, face = _rasterise(verts, faces, project, scale, offset, width, height)
        shade = _shade(verts, faces, toward_camera)
        image.reshape(-1, 3)[pix] = colors[face] * shade[face, None]

    for m in translucent:
        verts = np.asarray(m.vertices, np.float64)
        faces = np.asarray(m.faces, np.int64).reshape(-1, 3)
        pix, face = _rasterise(verts, faces, project, scale, offset, width, height)
        shade = _shade(verts, faces, toward_camera)
        layer = np.asarray(m.color, np.float64) * shade[face, None]
        a = float(m.opacity)
        flat = image.reshape(-1, 3)
        flat[pix] = (1.0 - a) * flat[pix] + a * layer

    return np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)


def save_png(image: np.ndarray, path: str | os.PathLike[str]) -> None:
    """Write an (H, W, 3) uint8 RGB image as a PNG, creating parent folders."""
    from PIL import Image

    img = _check_image("image", image)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img, mode="RGB").save(out, format="PNG")


def tile(
    images: Sequence[np.ndarray],
    columns: int,
    pad: int = 4,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> np.ndarray:
    """Arrange equal-size images in a grid, row by row.

    Args:
        images: (H, W, 3) uint8 images, all the same size.
        columns: images per row (>= 1); the last row may be short.
        pad: pixels of ``background`` between tiles and around the edge (>= 0).
        background: (r, g, b) in 0..1 for the padding and empty cells.
    Returns:
        (rows * (H + pad) + pad, columns * (W + pad) + pad, 3) uint8 image, where
        rows = ceil(len(images) / columns).
    """
    if len(images) == 0:
        raise ShapeError("tile needs at least one image; got none")
    if not isinstance(columns, int) or isinstance(columns, bool) or columns < 1:
        raise BodyfitError(f"columns must be a positive integer; got {columns!r}")
    if not isinstance(pad, int) or isinstance(pad, bool) or pad < 0:
        raise BodyfitError(f"pad must be a non-negative integer; got {pad!r}")
    _check_rgb("background", background)
    imgs = [_check_image(f"images[{i}]", im) for i, im in enumerate(images)]
    h, w = imgs[0].shape[:2]
    for i, im in enumerate(imgs):
        if im.shape[:2] != (h, w):
            raise ShapeError(
                f"tile needs equal-size images; images[0] is {h}x{w} (H x W) but images[{i}] is "
                f"{im.shape[0]}x{im.shape[1]}; render them with the same size"
            )
    rows = math.ceil(len(imgs) / columns)
    bg = np.clip(np.rint(np.asarray(background, np.float64) * 255.0), 0, 255).astype(np.uint8)
    out = np.empty((rows * (h + pad) + pad, columns * (w + pad) + pad, 3), np.uint8)
    out[:] = bg
    for k, im in enumerate(imgs):
        r, c = divmod(k, columns)
        y, x = pad + r * (h + pad), pad + c * (w + pad)
        out[y : y + h, x : x + w] = im
    return out


def label_grid(
    image: np.ndarray,
    column_titles: Sequence[Sequence[str]],
    row_titles: Sequence[str],
    caption: str = "",
    pad: int = 4,
    font_size: int = 18,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> np.ndarray:
    """Label a grid made by :func:`tile`: titles above its columns, a label left of each row, a caption below.

    Args:
        image: (H, W, 3) uint8 grid from ``tile(images, C, pad)`` with R rows, where R = len(row_titles) and
            C = len(column_titles[0]).
        column_titles: ``[titles]``, one list of C titles drawn in a band above the grid, or R such lists,
            each drawn in a band above its own row (for grids whose columns show different things in
            different rows). Titles are centred over their column and wrapped to its width; a newline
            starts a new line; "" leaves the place blank.
        row_titles: R labels, each centred beside its row in a band left of the grid; a newline starts a
            new line (row labels are not wrapped: the band grows to the widest line).
        caption: text under the grid, wrapped to the labelled image's width (say what the colours mean);
            "" for none.
        pad: the ``pad`` the grid was tiled with.
        font_size: text height in pixels (Pillow's default font: FreeType's Aileron when Pillow has
            FreeType, else a small fixed bitmap font).
        background: (r, g, b) in 0..1 for the bands.
    Returns:
        (B * T + H + K, L + W, 3) uint8 image: the grid unchanged, shifted right by the row-label band's
        width L and down by the title bands above it, where T is a title band's height, B the number of
        title bands (1 or R) and K the caption band's height (0 without a caption).
    """
    from PIL import Image, ImageDraw

    img = _check_image("image", image)
    rows, columns = _check_titles(column_titles, row_titles)
    _check_count("pad", pad, 0)
    _check_count("font_size", font_size, 1)
    _check_rgb("background", background)
    cell_h, cell_w = _cell_size(img.shape[:2], rows, columns, pad)
    pen = _Pen(font_size)
    titles = [[pen.wrap(t, cell_w - _LABEL_MARGIN) for t in line] for line in column_titles]
    band_h = max(pen.size(t)[1] for line in titles for t in line) + 2 * _LABEL_MARGIN
    band_w = max(pen.size(t)[0] for t in row_titles) + 2 * _LABEL_MARGIN
    text = pen.wrap(caption, band_w + img.shape[1] - 2 * _LABEL_MARGIN)
    caption_h = pen.size(text)[1] + 2 * _LABEL_MARGIN if text else 0
    per_row = len(titles) > 1
    height = band_h * (rows if per_row else 1) + img.shape[0] + caption_h
    bg = tuple(round(255 * float(x)) for x in background)
    out = Image.new("RGB", (band_w + img.shape[1], height), bg)
    draw = ImageDraw.Draw(out)
    pitch_y, pitch_x = cell_h + pad, cell_w + pad
    y = 0
    for r in range(rows):
        if r == 0 or per_row:
            for c, title in enumerate(titles[r if per_row else 0]):
                pen.centred(draw, title, band_w + pad + c * pitch_x + cell_w / 2, y + band_h / 2)
            y += band_h
        out.paste(Image.fromarray(img[r * pitch_y : (r + 1) * pitch_y]), (band_w, y))
        pen.centred(draw, row_titles[r], band_w / 2, y + pad + cell_h / 2)
        y += pitch_y
    if pad:
        out.paste(Image.fromarray(img[rows * pitch_y :]), (band_w, y))  # the bottom pad
    if text:
        pen.left(draw, text, _LABEL_MARGIN, y + pad + _LABEL_MARGIN)
    return np.asarray(out)


# -- internals ------------------------------------------------------------------------------------------


def _check_rgb(what: str, rgb: Sequence[float]) -> None:
    try:
        arr = np.asarray(rgb, np.float64)
    except (TypeError, ValueError):
        raise BodyfitError(f"{what} must be (r, g, b) numbers in 0..1; got {rgb!r}") from None
    if arr.shape != (3,) or not np.isfinite(arr).all() or arr.min() < 0.0 or arr.max() > 1.0:
        raise BodyfitError(f"{what} must be (r, g, b) numbers in 0..1; got {rgb!r}")


def _check_image(what: str, image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ShapeError(
            f"{what} must be an (H, W, 3) uint8 RGB array such as render() returns; "
            f"got shape {img.shape}, dtype {img.dtype}"
        )
    return np.ascontiguousarray(img)


def _check_titles(column_titles: Sequence[Sequence[str]], row_titles: Sequence[str]) -> tuple[int, int]:
    """The grid's (rows, columns) from its titles, which must be strings in a consistent number."""
    if isinstance(row_titles, str) or not all(isinstance(t, str) for t in row_titles) or not row_titles:
        raise BodyfitError(f"row_titles must be a list of one string per row; got {row_titles!r}")
    rows = len(row_titles)
    lines = list(column_titles)
    if (
        isinstance(column_titles, str)
        or not lines
        or any(isinstance(line, str) or not all(isinstance(t, str) for t in line) for line in lines)
    ):
        raise BodyfitError(
            f"column_titles must be [[title, ...]] (one list) or one list of titles per row; "
            f"got {column_titles!r}"
        )
    columns = len(lines[0])
    if columns < 1 or any(len(line) != columns for line in lines) or len(lines) not in (1, rows):
        raise ShapeError(
            f"column_titles must hold one list of titles, or {rows} (one per row), all of the same length "
            f">= 1; got lists of lengths {[len(line) for line in lines]}"
        )
    return rows, columns


def _cell_size(shape: tuple[int, ...], rows: int, columns: int, pad: int) -> tuple[int, int]:
    """The (height, width) of one cell of a grid of ``shape`` (H, W) tiled with ``rows`` x ``columns``."""
    cell_h, rest_h = divmod(shape[0] - pad, rows)
    cell_w, rest_w = divmod(shape[1] - pad, columns)
    if rest_h or rest_w or cell_h <= pad or cell_w <= pad:
        raise ShapeError(
            f"a {shape[0]}x{shape[1]} (H x W) image is not a grid of {rows} x {columns} tiles with "
            f"pad {pad}; "
            "give as many row titles as rows, as many column titles as columns, and tile()'s pad"
        )
    return cell_h - pad, cell_w - pad


def _check_count(what: str, value: int, least: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < least:
        raise BodyfitError(f"{what} must be an integer >= {least}; got {value!r}")


class _Pen:
    """Pillow's default font at one size: measures, wraps and draws multi-line text in ``_INK``."""

    def __init__(self, font_size: int) -> None:
        from PIL import Image, ImageDraw, ImageFont

        self.font = ImageFont.load_default(size=font_size)
        self.spacing = max(font_size // 4, 1)
        self._measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))

    def _box(self, text: str) -> tuple[float, float, float, float]:
        return self._measure.multiline_textbbox(
            (0, 0), text, font=self.font, spacing=self.spacing, align="center"
        )

    def size(self, text: str) -> tuple[int, int]:
        """(width, height) in pixels of ``text``'s ink."""
        x0, y0, x1, y1 = self._box(text)
        return math.ceil(x1 - x0), math.ceil(y1 - y0)

    def wrap(self, text: str, width: float) -> str:
        """``text`` with its lines broken at spaces so each fits ``width`` pixels where it can."""
        lines = []
        for paragraph in text.split("\n"):
            line = ""
            for word in paragraph.split(" "):
                candidate = f"{line} {word}" if line else word
                if line and self.font.getlength(candidate) > width:
                    lines.append(line)
                    line = word
                else:
                    line = candidate
            lines.append(line)
        return "\n".join(lines)

    def centred(self, draw: ImageDraw.ImageDraw, text: str, cx: float, cy: float) -> None:
        """Draw ``text``, its lines centred, with its ink's box centred on pixel (cx, cy)."""
        x0, y0, x1, y1 = self._box(text)
        xy = (cx - (x0 + x1) / 2, cy - (y0 + y1) / 2)
        draw.multiline_text(xy, text, fill=_INK, font=self.font, spacing=self.spacing, align="center")

    def left(self, draw: ImageDraw.ImageDraw, text: str, x: float, y: float) -> None:
        """Draw ``text`` left-aligned, its first line's top-left at pixel (x, y)."""
        draw.multiline_text((x, y), text, fill=_INK, font=self.font, spacing=self.spacing)


def _bounds(
    meshes: Sequence[RenderMesh], bounds: tuple[np.ndarray, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray]:
    """The (3,) min and max corners to fit: ``bounds`` checked, else the union box of all vertices."""
    if bounds is not None:
        if len(bounds) != 2:
            raise ShapeError(f"bounds must be (min xyz, max xyz); got a sequence of length {len(bounds)}")
        lo, hi = (np.asarray(b, np.float64) for b in bounds)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ShapeError(
                f"bounds must be two (3,) arrays (min xyz, max xyz); got shapes {lo.shape}, {hi.shape}"
            )
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise NonFiniteError("bounds contain NaN or infinite values; send finite corners")
        if (hi < lo).any():
            raise BodyfitError(f"bounds must be (min xyz, max xyz) with min <= max; got {lo} and {hi}")
        return lo, hi
    nonempty = [np.asarray(m.vertices, np.float64) for m in meshes if len(m.vertices)]
    if not nonempty:
        raise ShapeError("nothing to frame: no mesh has vertices; pass meshes with vertices or give bounds")
    lo = np.min([v.min(axis=0) for v in nonempty], axis=0)
    hi = np.max([v.max(axis=0) for v in nonempty], axis=0)
    return lo, hi


def _camera(view: str) -> tuple[np.ndarray, np.ndarray]:
    """(3, 3) world -> (right, up, toward-camera) rotation rows, and the (3,) unit vector to the camera."""
    x, y, z = np.eye(3)
    right = {"front": -z, "side": x, "back": z}[view]
    toward = np.cross(right, y)  # right-handed camera: right x up = toward the viewer
    return np.stack([right, y, toward]), toward


def _fit(
    project: np.ndarray, lo: np.ndarray, hi: np.ndarray, width: int, height: int
) -> tuple[float, np.ndarray]:
    """Pixels per metre and the (2,) pixel offset mapping the projected box centre to the image centre."""
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    uv = corners @ project[:2].T
    umin, vmin = uv.min(axis=0)
    umax, vmax = uv.max(axis=0)
    margin = _MARGIN * min(width, height)
    avail_w, avail_h = max(width - 2 * margin, 1.0), max(height - 2 * margin, 1.0)
    du, dv = umax - umin, vmax - vmin
    candidates = [avail_w / du if du > 0 else math.inf, avail_h / dv if dv > 0 else math.inf]
    scale = min(candidates)
    if not math.isfinite(scale):
        scale = 1.0  # a single point: any scale will do
    # pixel x = scale * u + ox, pixel y (down) = -scale * v + oy
    offset = np.array([width / 2 - scale * (umin + umax) / 2, height / 2 + scale * (vmin + vmax) / 2])
    return float(scale), offset


def _shade(verts: np.ndarray, faces: np.ndarray, toward_camera: np.ndarray) -> np.ndarray:
    """(F,) flat Lambert intensity: ambient + (1 - ambient) |n·l| with the light at the camera."""
    if len(faces) == 0:
        return np.zeros(0)
    tri = verts[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    cos = np.abs(n @ toward_camera) / np.where(norm > 0, norm, 1.0)
    return np.asarray(_AMBIENT + (1.0 - _AMBIENT) * cos)


def _rasterise(
    verts: np.ndarray,
    faces: np.ndarray,
    project: np.ndarray,
    scale: float,
    offset: np.ndarray,
    width: int,
    height: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer triangles; a pixel is covered when its centre lies inside a triangle (edges inclusive).

    Triangles are grouped by the size of their clipped pixel bounding box, and each group is evaluated as one
    (n, h, w) block of barycentric tests, so the Python loop runs over sizes, not triangles.

    Args:
        verts: (V, 3) world positions; faces: (F, 3) indices.
        project: (3, 3) camera rotation from :func:`_camera`; scale, offset: from :func:`_fit`.
    Returns:
        flat pixel indices (N,) into an (height * width) image, and the (N,) nearest face drawn at each.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(faces) == 0:
        return empty
    cam = verts @ project.T
    sx = cam[:, 0] * scale + offset[0]
    sy = -cam[:, 1] * scale + offset[1]
    depth = -cam[:, 2]  # smaller is nearer
    tx, ty, tz = sx[faces], sy[faces], depth[faces]  # (F, 3) each

    # Pixel (i, j) has its centre at (j + 0.5, i + 0.5); covered columns satisfy min_x <= j + 0.5 <= max_x.
    x0 = np.maximum(np.ceil(tx.min(axis=1) - 0.5), 0).astype(np.int64)
    x1 = np.minimum(np.floor(tx.max(axis=1) - 0.5), width - 1).astype(np.int64)
    y0 = np.maximum(np.ceil(ty.min(axis=1) - 0.5), 0).astype(np.int64)
    y1 = np.minimum(np.floor(ty.max(axis=1) - 0.5), height - 1).astype(np.int64)
    area2 = (tx[:, 1] - tx[:, 0]) * (ty[:, 2] - ty[:, 0]) - (tx[:, 2] - tx[:, 0]) * (ty[:, 1] - ty[:, 0])
    keep = np.flatnonzero((x1 >= x0) & (y1 >= y0) & (np.abs(area2) > _MIN_AREA2))
    if len(keep) == 0:
        return empty
    bw, bh = x1[keep] - x0[keep] + 1, y1[keep] - y0[keep] + 1

    zbuf = np.full(width * height, np.inf)
    fbuf = np.full(width * height, -1, np.int64)
    sizes, group = np.unique(np.stack([bh, bw], axis=1), axis=0, return_inverse=True)
    group = group.reshape(-1)
    order = np.argsort(group, kind="stable")
    bounds_ = np.searchsorted(group[order], np.arange(len(sizes) + 1))
    for g, (h, w) in enumerate(sizes.tolist()):
        members = keep[order[bounds_[g] : bounds_[g + 1]]]
        step = max(1, _CHUNK_PIXELS // (h * w))
        for s in range(0, len(members), step):
            idx = members[s : s + step]
            _fill(idx, h, w, x0[idx], y0[idx], tx[idx], ty[idx], tz[idx], area2[idx], width, zbuf, fbuf)
    pix = np.flatnonzero(fbuf >= 0)
    return pix, fbuf[pix]


def _fill(
    idx: np.ndarray,
    h: int,
    w: int,
    x0: np.ndarray,
    y0: np.ndarray,
    tx: np.ndarray,
    ty: np.ndarray,
    tz: np.ndarray,
    area2: np.ndarray,
    width: int,
    zbuf: np.ndarray,
    fbuf: np.ndarray,
) -> None:
    """Barycentric-test n triangles over their (h, w) pixel boxes and merge the hits into the z-buffer.

    ``zbuf`` / ``fbuf`` are this render's own (height * width,) buffers, updated in place.
    """
    px = (x0[:, None, None] + np.arange(w)[None, None, :] + 0.5).astype(np.float64)  # (n, 1, w)
    py = (y0[:, None, None] + np.arange(h)[None, :, None] + 0.5).astype(np.float64)  # (n, h, 1)
    xa, xb, xc = (tx[:, k, None, None] for k in range(3))
    ya, yb, yc = (ty[:, k, None, None] for k in range(3))
    inv = 1.0 / area2[:, None, None]
    # Barycentric weights of a, b, c (each normalised by the signed area, so either winding works).
    wa = ((xb - px) * (yc - py) - (xc - px) * (yb - py)) * inv
    wb = ((xc - px) * (ya - py) - (xa - px) * (yc - py)) * inv
    wc = 1.0 - wa - wb
    inside = (wa >= 0) & (wb >= 0) & (wc >= 0)
    n_i, r_i, c_i = np.nonzero(inside)
    if len(n_i) == 0:
        return
    z = wa[n_i, r_i, c_i] * tz[n_i, 0] + wb[n_i, r_i, c_i] * tz[n_i, 1] + wc[n_i, r_i, c_i] * tz[n_i, 2]
    pix = (y0[n_i] + r_i) * width + (x0[n_i] + c_i)
    # Nearest fragment per pixel within this chunk, then merge with the buffer.
    srt = np.lexsort((z, pix))
    pix, z, tri = pix[srt], z[srt], idx[n_i[srt]]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    pix, z, tri = pix[first], z[first], tri[first]
    nearer = z < zbuf[pix]
    zbuf[pix[nearer]] = z[nearer]
    fbuf[pix[nearer]] = tri[nearer]
