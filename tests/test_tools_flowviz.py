"""Middlebury colour wheel and flow-video frames (emdflow.tools.flowviz)."""

import numpy as np
import pytest

from emdflow.tools.flowviz import flow_to_color, make_colorwheel, quality_color, render_flow_frame


def test_colorwheel_is_the_middlebury_one():
    wheel = make_colorwheel()
    assert wheel.shape == (55, 3)
    np.testing.assert_array_equal(wheel[0], [255, 0, 0])  # starts at red
    np.testing.assert_array_equal(wheel[15], [255, 255, 0])  # RY = 15 → yellow
    np.testing.assert_array_equal(wheel[21], [0, 255, 0])  # + YG = 6 → green


def test_flow_to_color_conventions():
    u = np.array([[0.0, 1.0, -1.0, 0.0, 0.0, 0.5, np.nan, np.nan, 2.0]])
    v = np.array([[0.0, 0.0, 0.0, 1.0, -1.0, 0.0, np.nan, 1.0, 0.0]])
    rgb = flow_to_color(u, v, max_flow=1.0, unknown_rgb=(1, 2, 3))
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 9, 3)
    np.testing.assert_array_equal(rgb[0, 0], [255, 255, 255])  # zero flow is white
    assert rgb[0, 1, 0] == 255 and rgb[0, 1, 2] < 100  # right: red end of the wheel
    assert rgb[0, 2, 2] > 200 and rgb[0, 2, 0] == 0  # left: cyan / blue
    assert rgb[0, 3, 1] > 200 and rgb[0, 3, 2] < 100  # down: yellow-green
    assert rgb[0, 4, 2] > 200  # up: blue-magenta
    assert rgb[0, 5].min() > 100  # half magnitude is pale
    np.testing.assert_array_equal(rgb[0, 6], [1, 2, 3])  # both unknown
    np.testing.assert_array_equal(rgb[0, 7], rgb[0, 3])  # one known axis: the other is 0
    assert rgb[0, 8].max() <= int(0.75 * 255) + 1  # beyond max_flow: darkened to 75 %


def test_quality_colour_goes_red_to_green():
    assert quality_color(0) == (0, 0, 255)
    assert quality_color(255) == (0, 255, 0)
    b, g, r = quality_color(128)
    assert g > 200 and r > 200


def test_render_flow_frame_size_and_content():
    gray = np.full((40, 50), 100, np.uint8)
    u = np.full((40, 50), np.nan, np.float32)
    v = np.full((40, 50), np.nan, np.float32)
    u[10, 10] = 3.0
    img = render_flow_frame(gray, u, v, 2.0, 0.0, 200, upscale=3, max_flow=6)
    assert img.shape == (120, 150, 3) and img.dtype == np.uint8
    # the detection is drawn in the wheel's colour of (3, 0), BGR
    expected = flow_to_color(np.array([[3.0]]), np.array([[0.0]]), 6.0)[0, 0, ::-1]
    np.testing.assert_array_equal(img[31, 31], expected)
    with pytest.raises(ValueError, match="expected shape"):
        render_flow_frame(gray, u[:5], v, 0, 0, 0)


@pytest.mark.parametrize("thickness", [1, 2])
def test_text_outline_lies_around_its_own_glyphs(thickness):
    """The dark outline hugs the text: drawn as a thicker stroke it advanced further per
    glyph, so a number's outline ran ahead of it and read as ghost digits ("q 2222")."""
    from emdflow.tools.flowviz import _text

    img = np.full((60, 420, 3), 128, np.uint8)
    _text(img, "q 222  12.50 px/frame", (10, 40), 0.8, (255, 255, 255), thickness)
    white = np.flatnonzero((img > 200).all(axis=2).any(axis=0))
    dark = np.flatnonzero((img < 40).all(axis=2).any(axis=0))
    assert white.size and dark.size
    assert white.min() - 3 <= dark.min() and dark.max() <= white.max() + 3
