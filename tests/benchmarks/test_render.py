"""The software renderer: framing, view orientation, depth test, x-ray translucency, tiling, labels, PNG
output."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from benchmarks.render import RenderMesh, label_grid, render, save_png, tile

RED = (1.0, 0.0, 0.0)
GREEN = (0.0, 1.0, 0.0)
BLUE = (0.0, 0.0, 1.0)

_BOX_FACES = np.array(
    [
        [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x = lo, x = hi
        [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y = lo, y = hi
        [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],  # z = lo, z = hi
    ]
)  # fmt: skip


def box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box: (8, 3) vertices (corner k has bit 2/1/0 = x/y/z at hi) and (12, 3) triangles."""
    corners = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], np.float64)
    v = np.asarray(lo) + corners * (np.asarray(hi) - np.asarray(lo))
    return v, _BOX_FACES.copy()


def box_mesh(
    lo: tuple[float, float, float],
    hi: tuple[float, float, float],
    color: tuple[float, float, float],
    opacity: float = 1.0,
) -> RenderMesh:
    v, f = box(lo, hi)
    return RenderMesh(v, f, color, opacity)


def quad_x(
    x: float, y: tuple[float, float], z: tuple[float, float], color: tuple[float, float, float]
) -> RenderMesh:
    """A rectangle in the plane X = x (facing the front/back cameras)."""
    v = np.array([[x, y[0], z[0]], [x, y[1], z[0]], [x, y[1], z[1]], [x, y[0], z[1]]])
    return RenderMesh(v, np.array([[0, 1, 2], [0, 2, 3]]), color)


def drawn(img: np.ndarray) -> np.ndarray:
    """(H, W) mask of pixels that are not the white background."""
    return np.asarray((img != 255).any(axis=2))


def centroid(img: np.ndarray, color: tuple[int, int, int]) -> tuple[float, float]:
    """(row, column) centroid of the pixels of exactly ``color``."""
    rows, cols = np.nonzero((img == np.array(color, np.uint8)).all(axis=2))
    assert len(rows) > 0, f"no pixel of colour {color}"
    return float(rows.mean()), float(cols.mean())


def test_unit_cube_front_fills_the_margined_square() -> None:
    cube = box_mesh((0, 0, 0), (1, 1, 1), RED)
    img = render([cube], "front", size=(200, 200))
    assert img.shape == (200, 200, 3) and img.dtype == np.uint8
    # Margin 4 % of 200 = 8 px each side: the face-on front face covers exactly 184 x 184 pixel centres,
    # the faces seen edge-on add nothing, and face-on shading gives the full colour.
    mask = drawn(img)
    assert int(mask.sum()) == 184 * 184
    rows, cols = np.nonzero(mask)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (8, 191, 8, 191)
    assert (img[mask] == np.array([255, 0, 0], np.uint8)).all()


def test_aspect_ratio_is_kept_and_the_box_centred() -> None:
    slab = box_mesh((0, 0, 0), (1, 2, 1), GREEN)  # 1 wide, 2 tall in the front view
    img = render([slab], "front", size=(400, 300))
    rows, cols = np.nonzero(drawn(img))
    height, width = rows.max() - rows.min() + 1, cols.max() - cols.min() + 1
    assert height == 300 - 2 * 12  # height limits: margin 4 % of 300 = 12 px
    assert abs(width - height / 2) <= 1
    assert abs((cols.min() + cols.max()) / 2 - 199.5) <= 0.5


def _orientation_scene() -> list[RenderMesh]:
    """Red at the body's right (+Z), blue at its left (-Z), green in front (+X) and up (+Y)."""
    return [
        box_mesh((-0.1, -0.1, 0.4), (0.1, 0.1, 0.6), RED),
        box_mesh((-0.1, -0.1, -0.6), (0.1, 0.1, -0.4), BLUE),
        box_mesh((0.4, 0.4, -0.1), (0.6, 0.6, 0.1), GREEN),
    ]


def test_front_view_shows_the_body_right_on_the_image_left() -> None:
    img = render(_orientation_scene(), "front", size=(128, 128))
    red, blue, green = centroid(img, (255, 0, 0)), centroid(img, (0, 0, 255)), centroid(img, (0, 255, 0))
    assert red[1] < 40 and blue[1] > 88  # +Z (body right) on the image left
    assert green[0] < red[0] - 20  # +Y up
    assert abs(green[1] - 63.5) < 2


def test_back_view_mirrors_the_front_view() -> None:
    img = render(_orientation_scene(), "back", size=(128, 128))
    red, blue = centroid(img, (255, 0, 0)), centroid(img, (0, 0, 255))
    assert red[1] > 88 and blue[1] < 40


def test_side_view_shows_forward_to_the_image_right() -> None:
    img = render(_orientation_scene(), "side", size=(128, 128))
    red, green = centroid(img, (255, 0, 0)), centroid(img, (0, 255, 0))
    assert green[1] > red[1] + 20  # +X (forward) to the image right
    assert green[0] < red[0] - 20  # +Y up
    # The camera sits on +Z, so the red box (at +Z) hides the blue one behind it.
    assert not (img == np.array([0, 0, 255], np.uint8)).all(axis=2).any()


@pytest.mark.parametrize("swap", [False, True])
def test_nearer_opaque_quad_wins_whatever_the_order(swap: bool) -> None:
    near = quad_x(0.5, (0.0, 1.0), (0.0, 1.0), BLUE)  # nearer to the front camera (on +X)
    far = quad_x(0.0, (0.5, 1.5), (0.5, 1.5), RED)
    meshes = [far, near] if swap else [near, far]
    blue, red = np.array([0, 0, 255], np.uint8), np.array([255, 0, 0], np.uint8)
    # The overlap is y, z in [0.5, 1]: a pixel at y = z = 0.75 is blue from the front and red from the back.
    bounds = (np.array([0.0, 0.0, 0.0]), np.array([0.5, 1.5, 1.5]))
    front = render(meshes, "front", size=(120, 120), bounds=bounds)
    back = render(meshes, "back", size=(120, 120), bounds=bounds)
    # y = 0.75 is the image centre row and z = 0.75 the centre column.
    assert (front[60, 60] == blue).all() and (back[60, 60] == red).all()
    # Both colours are still visible where the quads do not overlap.
    assert (front == red).all(axis=2).any() and (back == blue).all(axis=2).any()


def test_depth_test_holds_across_triangle_sizes() -> None:
    # Triangles are batched by screen size; a small near quad must beat a big far one drawn in another batch.
    near = quad_x(0.5, (0.4, 0.6), (0.4, 0.6), BLUE)
    far = quad_x(0.0, (0.0, 1.0), (0.0, 1.0), RED)
    for meshes in ([near, far], [far, near]):
        front = render(meshes, "front", size=(100, 100))
        back = render(meshes, "back", size=(100, 100))
        assert tuple(front[50, 50]) == (0, 0, 255) and tuple(back[50, 50]) == (255, 0, 0)
        assert tuple(front[20, 20]) == (255, 0, 0)


def test_a_single_triangle_covers_half_its_box() -> None:
    # Right triangle with legs along the image's top and left edges (front view: image right = -Z).
    tri = RenderMesh(np.array([[0, 1, 0], [0, 1, -1], [0, 0, 0]], np.float64), np.array([[0, 1, 2]]), RED)
    img = render([tri], "front", size=(200, 200))
    mask = drawn(img)
    assert abs(int(mask.sum()) - 184 * 184 / 2) < 184  # half the square, give or take the diagonal
    assert mask[10, 10] and mask[10, 189] and mask[189, 10]  # near the three corners
    assert not mask[189, 189] and not mask[110, 110]  # beyond the hypotenuse
    rows, cols = np.nonzero(mask)
    assert (cols + rows).max() == 199  # pixel centres on or inside the diagonal x + y = 200


@pytest.mark.parametrize("seed", range(4))
def test_triangle_coverage_matches_a_point_in_triangle_test(seed: int) -> None:
    # Random triangles with no axis-aligned edges, framed by fixed bounds so the pixel mapping is known:
    # front view, u = -z, v = y in [0, 1] -> pixel x = 8 + 184 u, pixel y = 8 + 184 (1 - v).
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0.0, 1.0, (3, 2))
    verts = np.stack([rng.uniform(-1, 1, 3), uv[:, 1], -uv[:, 0]], axis=1)  # x (depth) is irrelevant
    bounds = (np.array([-1.0, 0.0, -1.0]), np.array([1.0, 1.0, 0.0]))
    img = render([RenderMesh(verts, np.array([[0, 1, 2]]), RED)], "front", size=(200, 200), bounds=bounds)
    px = np.stack([8 + 184 * uv[:, 0], 8 + 184 * (1 - uv[:, 1])], axis=1)
    cy, cx = np.mgrid[0:200, 0:200] + 0.5
    sides = []
    for k in range(3):
        (ax, ay), (bx, by) = px[k], px[(k + 1) % 3]
        sides.append((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))
    signs = np.stack(sides)
    expected = (signs >= 0).all(axis=0) | (signs <= 0).all(axis=0)
    assert expected.sum() > 50
    assert (drawn(img) == expected).all()


def test_xray_translucent_skin_shows_the_opaque_core() -> None:
    skin = box_mesh((-1, -1, -1), (1, 1, 1), BLUE, opacity=0.4)
    core = box_mesh((-0.3, -0.3, -0.3), (0.3, 0.3, 0.3), RED)
    img = render([skin, core], "front", size=(100, 100))
    # The core is inside the skin, yet shows through: 0.6 * red + 0.4 * blue at full (face-on) shading.
    assert tuple(img[50, 50]) == (153, 0, 102)
    # Skin only: 0.6 * white background + 0.4 * blue; not red.
    assert tuple(img[50, 10]) == (153, 153, 255)
    # Outside the skin: background.
    assert tuple(img[50, 1]) == (255, 255, 255)


def test_fully_opaque_and_zero_opacity_meshes() -> None:
    core = box_mesh((-0.3, -0.3, -0.3), (0.3, 0.3, 0.3), RED)
    hidden = render([box_mesh((-1, -1, -1), (1, 1, 1), BLUE), core], "front", size=(100, 100))
    assert tuple(hidden[50, 50]) == (0, 0, 255)  # an opaque skin hides the core
    invisible = render([box_mesh((-1, -1, -1), (1, 1, 1), BLUE, opacity=0.0), core], "front", size=(100, 100))
    assert tuple(invisible[50, 50]) == (255, 0, 0) and tuple(invisible[50, 10]) == (255, 255, 255)


def test_lambert_shading_ignores_winding_and_darkens_oblique_faces() -> None:
    flat = quad_x(0.0, (0.0, 1.0), (0.0, 1.0), (1.0, 1.0, 1.0))
    flipped = RenderMesh(flat.vertices, flat.faces[:, ::-1].copy(), flat.color)
    a = render([flat], "front", size=(64, 64), background=(0.0, 0.0, 0.0))
    b = render([flipped], "front", size=(64, 64), background=(0.0, 0.0, 0.0))
    assert (a == b).all() and tuple(a[32, 32]) == (255, 255, 255)
    # Tilted 60° away from the camera: |n·l| = 0.5, so intensity = 0.3 + 0.7 * 0.5 = 0.65.
    c, s = np.cos(np.radians(60)), np.sin(np.radians(60))
    tilted = RenderMesh(
        np.array([[0, 0, 0], [0, 1, 0], [s, 1, c], [s, 0, c]], np.float64), flat.faces, (1.0, 1.0, 1.0)
    )
    img = render([tilted], "front", size=(64, 64), background=(0.0, 0.0, 0.0))
    assert tuple(img[32, 32]) == (166, 166, 166)


def test_shared_bounds_give_renders_one_scale() -> None:
    bounds = (np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0]))
    big = render([box_mesh((-1, -1, -1), (1, 1, 1), RED)], "front", size=(200, 200), bounds=bounds)
    small = render(
        [box_mesh((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), RED)], "front", size=(200, 200), bounds=bounds
    )
    assert int(drawn(big).sum()) == 184 * 184
    assert int(drawn(small).sum()) == 92 * 92
    # A mesh larger than the bounds is clipped at the image edge, not an error.
    huge = render([box_mesh((-3, -3, -3), (3, 3, 3), RED)], "front", size=(50, 50), bounds=bounds)
    assert drawn(huge).all()


def test_degenerate_and_empty_meshes_draw_nothing() -> None:
    line = RenderMesh(np.array([[0, 0, 0], [0, 1, 0], [0, 2, 0]], np.float64), np.array([[0, 1, 2]]), RED)
    no_faces = RenderMesh(np.zeros((4, 3)), np.zeros((0, 3), np.int64), RED)
    img = render([line, no_faces], "front", size=(32, 32))
    assert not drawn(img).any()
    background = render([], size=(8, 4), background=(0.0, 0.5, 1.0), bounds=(np.zeros(3), np.ones(3)))
    assert background.shape == (4, 8, 3) and (background == np.array([0, 128, 255], np.uint8)).all()


def test_ninety_thousand_triangles_render_without_holes() -> None:
    # A body-sized ellipsoid of 2 * 150 * 300 = 90,000 triangles.
    n_lat, n_lon = 151, 300
    theta = np.linspace(0, np.pi, n_lat)[:, None]
    phi = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)[None, :]
    v = np.stack(
        [
            0.15 * np.sin(theta) * np.cos(phi),
            0.9 * np.cos(theta) + 0 * phi,
            0.25 * np.sin(theta) * np.sin(phi),
        ],
        -1,
    ).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_lat - 1), np.arange(n_lon), indexing="ij")
    a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
    c, d = a + n_lon, b + n_lon
    faces = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    assert len(faces) == 90_000
    mesh = RenderMesh(v, faces, (0.8, 0.6, 0.5))
    img = render([mesh], "front")  # (how long it takes is benchmarks' business, not a test's)
    # The ellipse 0.5 m wide by 1.8 m tall fills pi/4 of its box with no holes along the middle.
    mask = drawn(img)
    rows, cols = np.nonzero(mask)
    box_area = (rows.max() - rows.min() + 1) * (cols.max() - cols.min() + 1)
    assert abs(mask.sum() / box_area - np.pi / 4) < 0.01
    assert mask[rows.min() + 5 : rows.max() - 5, 256].all()


def test_tile_lays_images_out_in_rows() -> None:
    images = [np.full((3, 2, 3), k * 40, np.uint8) for k in range(1, 6)]
    grid = tile(images, columns=2, pad=1, background=(1.0, 1.0, 1.0))
    assert grid.shape == (3 * 4 + 1, 2 * 3 + 1, 3)
    assert (grid[1:4, 1:3] == 40).all() and (grid[1:4, 4:6] == 80).all()
    assert (grid[5:8, 1:3] == 120).all() and (grid[9:12, 1:3] == 200).all()
    assert (grid[9:12, 4:6] == 255).all()  # the empty last cell is background
    assert (grid[0] == 255).all() and (grid[:, 3] == 255).all()
    with pytest.raises(ValueError, match="equal-size"):
        tile([images[0], np.zeros((4, 2, 3), np.uint8)], columns=2)
    with pytest.raises(ValueError, match="columns"):
        tile(images, columns=0)


# A 2 x 3 grid of 60 x 41 (H x W) grey tiles, pad 4: a cell pitch of 64 rows and 45 columns, 132 x 139
# pixels in all (which 2 columns, or 3 rows, would not divide evenly).
_CELL_H, _CELL_W, _PAD = 60, 41, 4


def _grid() -> np.ndarray:
    return tile([np.full((_CELL_H, _CELL_W, 3), 60 + 20 * k, np.uint8) for k in range(6)], columns=3)


def ink(region: np.ndarray) -> bool:
    """Whether ``region`` holds dark text pixels (the bands are white and the ink is near black)."""
    return bool((region.max(axis=2) < 128).any())


def _find(out: np.ndarray, grid: np.ndarray) -> tuple[int, int]:
    """(top, left) at which ``grid`` appears unchanged in ``out``, flush with its right edge."""
    left = out.shape[1] - grid.shape[1]
    tops = [
        t for t in range(out.shape[0] - grid.shape[0] + 1) if (out[t : t + len(grid), left:] == grid).all()
    ]
    assert len(tops) == 1, f"the grid appears at rows {tops}"
    return tops[0], left


def test_label_grid_adds_bands_and_draws_every_label() -> None:
    grid = _grid()
    out = label_grid(grid, [["input", "truth", "fit"]], ["man", "woman"], caption="Blue: the ground truth.")
    assert out.dtype == np.uint8 and out.shape[2] == 3
    top, left = _find(out, grid)
    bottom = top + len(grid)
    assert top > 0 and left > 0 and bottom < len(out)  # a title band, a row-label band, a caption band
    for c in range(3):
        x = left + _PAD + c * (_CELL_W + _PAD)
        assert ink(out[:top, x : x + _CELL_W]), f"no title above column {c}"
    for r in range(2):
        y = top + _PAD + r * (_CELL_H + _PAD)
        assert ink(out[y : y + _CELL_H, :left]), f"no label beside row {r}"
    assert ink(out[bottom:])
    assert not ink(out[:top, :left])  # the corner above the row labels stays blank


def test_blank_titles_leave_their_place_blank() -> None:
    grid = _grid()
    out = label_grid(grid, [["", "truth", ""]], ["", ""])
    top, left = _find(out, grid)
    assert top + len(grid) == len(out)  # no caption, no caption band
    columns = [left + _PAD + c * (_CELL_W + _PAD) for c in range(3)]
    assert [ink(out[:top, x : x + _CELL_W]) for x in columns] == [False, True, False]
    assert not ink(out[:, :left])


def test_long_titles_wrap_within_their_column() -> None:
    grid = _grid()
    short = label_grid(grid, [["to", "", ""]], ["r", "s"])
    wrapped = label_grid(grid, [["to be or not to be", "", ""]], ["r", "s"])
    top_short, _ = _find(short, grid)
    top, left = _find(wrapped, grid)
    assert top > top_short + 30  # several lines, so a taller band
    # every ink pixel of the title band lies over the first column (x from 4 to 45)
    cols = np.nonzero((wrapped[:top, left:].max(axis=2) < 128).any(axis=0))[0]
    assert cols.min() >= _PAD and cols.max() < _PAD + _CELL_W


def test_titles_per_row_get_a_band_above_each_row() -> None:
    grid = _grid()
    pitch = _CELL_H + _PAD
    out = label_grid(grid, [["points", "camera", "ahead"], ["d", "e", "f"]], ["kinect", "man"])
    band = (len(out) - len(grid)) // 2
    assert len(out) == 2 * band + len(grid) and band > 0
    assert (out[band : band + pitch, -grid.shape[1] :] == grid[:pitch]).all()
    assert (out[2 * band + pitch :, -grid.shape[1] :] == grid[pitch:]).all()
    left = out.shape[1] - grid.shape[1]
    for top in (0, band + pitch):
        for c in range(3):
            x = left + _PAD + c * (_CELL_W + _PAD)
            assert ink(out[top : top + band, x : x + _CELL_W]), f"no title above column {c} at row {top}"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"column_titles": ["a", "b", "c"]}, "one list"),
        ({"column_titles": [["a", "b"]]}, "not a grid of 2 x 2"),
        ({"column_titles": [["a", "b", "c"], ["d", "e"]]}, "same length"),
        ({"column_titles": [["a", "b", "c"]] * 3}, "one per row"),
        ({"row_titles": "rows"}, "row_titles"),
        ({"row_titles": ["a", "b", "c"]}, "not a grid of 3 x 3"),
        ({"pad": -1}, "pad"),
        ({"font_size": 0}, "font_size"),
        ({"image": np.zeros((10, 10), np.uint8)}, "uint8 RGB"),
    ],
)
def test_bad_labels_are_refused(kwargs: dict[str, Any], match: str) -> None:
    args: dict[str, Any] = {"image": _grid(), "column_titles": [["a", "b", "c"]], "row_titles": ["r", "s"]}
    with pytest.raises(ValueError, match=match):
        label_grid(**{**args, **kwargs})


def test_save_png_round_trips_and_creates_folders(tmp_path: Path) -> None:
    img = render([box_mesh((0, 0, 0), (1, 1, 1), RED)], "side", size=(40, 60))
    path = tmp_path / "a" / "b" / "cube.png"
    save_png(img, path)
    back = np.asarray(Image.open(path).convert("RGB"))
    assert (back == img).all()
    with pytest.raises(ValueError, match="uint8"):
        save_png(img.astype(np.float32), tmp_path / "bad.png")


_V, _F = box((0, 0, 0), (1, 1, 1))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"vertices": _V[:, :2]}, r"vertices must have shape \(V, 3\)"),
        ({"vertices": np.where(np.arange(24).reshape(8, 3) == 5, np.nan, _V)}, "NaN or infinite"),
        ({"faces": _F[:, :2]}, r"faces must have shape \(F, 3\)"),
        ({"faces": _F.astype(np.float64)}, "integer"),
        ({"faces": np.where(_F == 7, 8, _F)}, r"\[0, 8\)"),
        ({"faces": np.where(_F == 7, -1, _F)}, r"\[0, 8\)"),
        ({"color": (1.0, 0.0)}, "color"),
        ({"color": (2.0, 0.0, 0.0)}, "color"),
        ({"opacity": 1.5}, "opacity"),
    ],
)
def test_bad_meshes_are_refused(kwargs: dict[str, Any], match: str) -> None:
    args: dict[str, Any] = {"vertices": _V, "faces": _F, "color": RED, **kwargs}
    with pytest.raises(ValueError, match=match):
        RenderMesh(**args)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"view": "top"}, "unknown view 'top'; use one of front, side, back"),
        ({"size": (0, 10)}, "size"),
        ({"background": (0.0, 0.0, 0.0, 1.0)}, "background"),
        ({"bounds": (np.zeros(2), np.ones(2))}, r"\(3,\)"),
        ({"bounds": (np.ones(3), np.zeros(3))}, "min <= max"),
        ({"bounds": (np.zeros(3), np.full(3, np.inf))}, "NaN or infinite"),
    ],
)
def test_bad_render_arguments_are_refused(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        render([RenderMesh(_V, _F, RED)], **kwargs)


def test_nothing_to_frame_is_refused() -> None:
    with pytest.raises(ValueError, match="give bounds"):
        render([])
    with pytest.raises(ValueError, match="RenderMesh"):
        render([(_V, _F)])  # type: ignore[list-item]
