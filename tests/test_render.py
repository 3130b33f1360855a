"""Headless renderer: projection, occlusion, PNG output, input validation and speed."""
import time

import numpy as np
import pytest
from PIL import Image

from fluidlab_core.render import VIEWS, Layer, render, view_axes

UNIT_BOX = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
SIZE = (200, 200)  # square image for the unit box: the box fills it minus the margin
RED, BLUE, WHITE = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (255, 255, 255)


def cluster(centre, n=400, half_width=0.04, seed=0):
    """n points uniformly in a cube of the given half-width (m) around centre."""
    rng = np.random.default_rng(seed)
    return np.asarray(centre) + rng.uniform(-half_width, half_width, (n, 3))


def dominates(pixel, channel):
    """The channel clearly outweighs the other two (shading darkens rims and adds a white highlight)."""
    values = [int(c) for c in pixel]
    others = max(v for i, v in enumerate(values) if i != channel)
    return values[channel] - others > 50


def is_red(pixel):
    return dominates(pixel, 0)


def is_blue(pixel):
    return dominates(pixel, 2)


def test_view_axes_match_the_documented_table():
    expected = {  # name: (screen right, screen up, towards camera) in world axes
        "front": ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
        "side": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
        "top": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    }
    for name, axes in expected.items():
        np.testing.assert_allclose(np.array(view_axes(name)), np.array(axes, dtype=float), atol=1e-12)
    assert set(VIEWS) == {"front", "side", "top", "iso"}


def test_top_view_puts_a_cluster_where_x_is_right_and_y_is_up():
    # x = 0.75 (right of centre), y = 0.25 (below centre) in a unit box; the image centre is (100, 100)
    # and the box spans 160-200 px, so the cluster centre lands at column/row 140-150.
    img = render([Layer(cluster((0.75, 0.25, 0.5)), RED)], view="top", bounds=UNIT_BOX, size=SIZE)
    assert img.shape == (SIZE[1], SIZE[0], 3) and img.dtype == np.uint8
    for row in (143, 145, 147):
        for col in (143, 145, 147):
            assert is_red(img[row, col]), (row, col, img[row, col])
    for row, col in ((55, 55), (55, 145), (145, 55), (100, 100)):  # mirrored positions stay empty
        assert tuple(img[row, col]) == WHITE, (row, col, img[row, col])
    for row, col in ((0, 0), (0, SIZE[0] - 1), (SIZE[1] - 1, SIZE[0] - 1), (SIZE[1] - 1, 0)):
        assert tuple(img[row, col]) == WHITE


def test_nearer_layer_covers_farther_one_whatever_the_layer_order():
    far_red = Layer(cluster((0.5, 0.5, 0.2), seed=1), RED, "far")
    near_blue = Layer(cluster((0.5, 0.5, 0.8), seed=2), BLUE, "near")
    for layers in ([far_red, near_blue], [near_blue, far_red]):
        img = render(layers, view="top", bounds=UNIT_BOX, size=SIZE)
        assert is_blue(img[100, 100]), img[100, 100]
        assert not is_red(img[100, 100])
    # from below the order flips: the red layer is nearer
    img = render([far_red, near_blue], view=(-90.0, -90.0), bounds=UNIT_BOX, size=SIZE)
    assert is_red(img[100, 100]), img[100, 100]


def test_png_is_written_atomically_with_the_right_size(tmp_path):
    path = tmp_path / "frames" / "frame_000.png"
    img = render(
        [Layer(cluster((0.5, 0.5, 0.5)), BLUE, "water")], path, view="iso", size=(320, 240), title="t = 0.00 s"
    )
    with Image.open(path) as png:
        assert png.format == "PNG" and png.size == (320, 240)
        np.testing.assert_array_equal(np.asarray(png.convert("RGB")), img)
    assert sorted(p.name for p in path.parent.iterdir()) == ["frame_000.png"]  # no temp file left behind


def test_non_finite_points_raise_and_name_the_layer():
    points = cluster((0.5, 0.5, 0.5))
    points[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"layer 'water'.*not finite"):
        render([Layer(points, BLUE, "water")])


def test_bad_inputs_raise_with_the_reason():
    layer = Layer(cluster((0.5, 0.5, 0.5)), RED)
    with pytest.raises(ValueError, match=r"unknown view 'bottom'.*front, iso, side, top"):
        render([layer], view="bottom")
    with pytest.raises(ValueError, match="shape"):
        Layer(np.zeros((5, 2)), RED, "flat")
    with pytest.raises(ValueError, match="size must be positive"):
        render([layer], size=(0, 100))
    with pytest.raises(ValueError, match="lower < upper"):
        render([layer], bounds=((0, 0, 0), (1, 0, 1)))
    with pytest.raises(ValueError, match=r"color"):
        Layer(np.zeros((1, 3)), (255, 0, 0))


def test_100k_points_render_quickly():
    points = np.random.default_rng(0).random((100_000, 3))
    start = time.perf_counter()
    img = render([Layer(points, BLUE, "water")], view="iso")
    elapsed = time.perf_counter() - start
    assert elapsed < 3.0, f"rendering 100k points took {elapsed:.2f} s"
    assert (img != 255).any(axis=2).mean() > 0.2  # the cube is actually drawn


def test_empty_scene_needs_bounds():
    img = render([], bounds=UNIT_BOX, size=(50, 40), draw_axes=False)
    assert img.shape == (40, 50, 3)
    with pytest.raises(ValueError, match="pass bounds"):
        render([Layer(np.zeros((0, 3)), RED, "empty")])
