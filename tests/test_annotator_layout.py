"""The annotator windows' layout on a screen (pure: no display) and the colours the window draws: the legend's
palette against the muted capture colours, and the residual scale against the Session's."""

from __future__ import annotations

import numpy as np
import pytest

from dsr_bench.annotator import images, layout
from dsr_bench.errors import UserError


def _inside(rect, screen) -> bool:
    x, y, w, h = rect
    return x >= 0 and y >= 0 and x + w <= screen[0] and y + h <= screen[1] and w > 0 and h > 0


@pytest.mark.parametrize("screen", [(1920, 1080), (1600, 1000), (1024, 700)])
@pytest.mark.parametrize("aspect", [0.75, 0.5625])
def test_both_windows_fit_the_screen_side_by_side(screen, aspect):
    lay = layout.window_layout(*screen, image_aspect=aspect, max_image_width=1280)
    assert _inside(lay.view, screen) and _inside(lay.panel, screen)
    vx, _, vw, _ = lay.view
    px, _, pw, ph = lay.panel
    assert vx + vw <= px  # side by side, not overlapping
    # the panel's content (text column + image; two images stacked under their titles) fits its window
    assert lay.text_width + lay.image_width == pw
    assert 2 * (lay.image_height + layout.TITLE_HEIGHT) <= ph
    assert lay.image_height == round(lay.image_width * aspect)
    assert vw >= 0.4 * screen[0]  # the 3D view keeps a usable share


def test_larger_screens_get_larger_camera_images():
    sizes = [layout.window_layout(w, h).image_width for w, h in ((1024, 700), (1600, 1000), (1920, 1080))]
    assert sizes == sorted(sizes) and sizes[0] < sizes[-1]
    assert layout.window_layout(1920, 1080).image_width > 480  # the old fixed panel's images were 480 wide
    assert layout.window_layout(1920, 1080, max_image_width=320).image_width == 320  # never above native width


@pytest.mark.parametrize("screen", [(1920, 1080), (1600, 1000), (1024, 700)])
def test_panel_layout_of_a_resized_panel_window(screen):
    lay = layout.window_layout(*screen, image_aspect=0.75, max_image_width=640)
    _, _, pw, ph = lay.panel
    # the window as laid out gives back its own sizes
    assert layout.panel_layout(pw, ph, lay.text_width, max_image_width=640) == (lay.text_width, lay.image_width)
    # taller and wider: larger images (up to the native width), the text column kept; both images fit the height
    text_w, img_w = layout.panel_layout(pw + 300, ph + 300, lay.text_width, max_image_width=640)
    assert text_w == lay.text_width and (img_w > lay.image_width or lay.image_width == 640) and img_w <= 640
    assert 2 * (round(img_w * 0.75) + layout.TITLE_HEIGHT) <= ph + 300 and text_w + img_w <= pw + 300
    # lower: smaller images that fit the new height
    text_w, img_w = layout.panel_layout(pw, ph // 2, lay.text_width, max_image_width=640)
    assert img_w < lay.image_width and 2 * (round(img_w * 0.75) + layout.TITLE_HEIGHT) <= ph // 2
    # narrower than the text column: the column gives way so that images of 64 px still show
    text_w, img_w = layout.panel_layout(300, ph, lay.text_width, max_image_width=640)
    assert img_w == 64 and text_w + img_w <= 300


def test_layout_follows_the_monitor_origin_and_refuses_tiny_screens():
    a, b = layout.window_layout(1600, 1000), layout.window_layout(1600, 1000, origin=(1920, 0))
    assert b.view[0] - a.view[0] == 1920 and b.panel[0] - a.panel[0] == 1920 and b.view[1:] == a.view[1:]
    with pytest.raises(UserError, match="--window-size") as err:
        layout.window_layout(640, 480)
    assert "\n" not in str(err.value)


def test_parse_window_size():
    assert layout.parse_window_size("1600x1000") == (1600, 1000)
    assert layout.parse_window_size(" 1920X1080 ") == (1920, 1080)
    for bad in ("1600", "1600x", "axb", "1600x1000x2", "-5x10"):
        with pytest.raises(UserError, match="WIDTHxHEIGHT"):
            layout.parse_window_size(bad)


def test_screen_size_falls_back_without_a_display(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr(layout.shutil, "which", lambda name: None)  # no xrandr
    assert layout.screen_size() == (*layout.FALLBACK_SCREEN, 0, 0)


def test_screen_size_reads_the_primary_monitor_from_xrandr(monkeypatch):
    out = ("Screen 0: minimum 8 x 8, current 3520 x 1080, maximum 32767 x 32767\n"
           "HDMI-1 connected 1600x900+0+180 (normal left inverted right) 477mm x 268mm\n"
           "DP-1 connected primary 1920x1080+1600+0 (normal left inverted right) 527mm x 296mm\n"
           "DP-2 disconnected (normal left inverted right x axis y axis)\n")

    class Done:
        stdout = out

    monkeypatch.setattr(layout.shutil, "which", lambda name: "/usr/bin/xrandr")
    monkeypatch.setattr(layout.subprocess, "run", lambda *a, **k: Done())
    assert layout.screen_size() == (1920, 1080, 1600, 0)
    Done.stdout = out.replace(" primary", "")
    assert layout.screen_size() == (1600, 900, 0, 180)  # no primary: the first connected monitor


# --- colours -------------------------------------------------------------------------------------------------


def _saturation(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, np.float64).reshape(-1, 3)
    mx, mn = rgb.max(-1), rgb.min(-1)
    return np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-12), 0.0)


def _hue(rgb: np.ndarray) -> np.ndarray:
    import colorsys

    return np.array([colorsys.rgb_to_hsv(*c)[0] for c in np.asarray(rgb, np.float64).reshape(-1, 3)])


def test_muted_capture_colours_never_read_as_status_colours():
    grid = np.stack(np.meshgrid(*[np.linspace(0, 1, 18)] * 3, indexing="ij"), -1).reshape(-1, 3)
    muted = images.muted_colors(grid)
    drawn = [images.SELECTED_COLOR] + [c for name, c in images.STATUS_COLORS.items() if name != "unset"]
    # every status colour drawn in 3D is saturated, every muted capture colour is not: the palettes do not meet
    assert _saturation(drawn).min() >= images.STATUS_MIN_SATURATION
    assert _saturation(muted).max() <= images.MUTED_SATURATION + 1e-9
    assert images.MUTED_SATURATION < images.STATUS_MIN_SATURATION
    dist = np.linalg.norm(muted[:, None] - np.asarray(drawn)[None], axis=-1)
    assert dist.min() > 0.2
    # the status colours differ from each other in hue (orange, blue, cyan, green)
    hues = np.sort(_hue(drawn))
    assert np.diff(np.r_[hues, hues[0] + 1]).min() > 0.05
    # muting keeps hue and brightness
    keep = _saturation(grid) > 0.2
    assert np.allclose(_hue(muted[keep]), _hue(grid[keep]), atol=1e-9)
    assert np.allclose(muted.max(-1), grid.max(-1))


@pytest.mark.parametrize("value, says", [("big", "WIDTHxHEIGHT"), ("640x480", "smaller than 800x600")])
def test_cli_refuses_a_bad_window_size_in_one_line(tmp_path, capsys, value, says):
    from dsr_bench.cli import main

    # refused before the capture is even looked for
    assert main(["annotate", str(tmp_path / "none"), "--window-size", value]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "--window-size" in err and len(err.splitlines()) == 1, err


# --- picking -------------------------------------------------------------------------------------------------


def test_project_is_the_pinhole_model():
    from dsr_bench.annotator.picking import project

    k = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    ext = np.eye(4)
    ext[:3, 3] = [0.0, 0.0, 1.0]  # the world origin 1 m in front of the camera
    uv, z = project(np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 1.0], [0.0, 0.0, -2.0]]), k, ext)
    assert np.allclose(uv[0], [320, 240]) and np.allclose(uv[1], [320 + 25, 240 - 50]) and np.allclose(z, [1, 2, -1])


def test_a_click_between_samples_picks_the_nearest_within_the_tolerance():
    from dsr_bench.annotator.picking import nearest_pick

    uv = np.array([[100.0, 100.0], [110.0, 100.0], [100.0, 130.0]])
    z = np.array([1.0, 1.0, 1.0])
    assert nearest_pick(uv, z, (104.0, 101.0)) == 0  # between samples 0 and 1, nearer 0
    assert nearest_pick(uv, z, (107.0, 99.0)) == 1
    assert nearest_pick(uv, z, (100.0, 118.0), tolerance=12) == 2  # 12 px from sample 2, 18 from sample 0
    assert nearest_pick(uv, z, (100.0, 118.0), tolerance=11) is None  # nothing within 11 px: no pick
    assert nearest_pick(uv, z, (300.0, 300.0)) is None
    assert nearest_pick(uv, np.array([-1.0, 1.0, 1.0]), (101.0, 100.0)) == 1  # behind the camera: never


def test_a_click_never_picks_a_hidden_point():
    from dsr_bench.annotator.picking import nearest_pick

    # a can seen from above: its bottom sample (z 1.10) projects next to the click, its top sample (z 1.00) a bit
    # further; the drawn depth there is the top's
    uv = np.array([[50.0, 50.0], [53.0, 50.0]])
    z = np.array([1.10, 1.00])
    buffer = np.full((100, 100), 1.0)
    assert nearest_pick(uv, z, (50.0, 50.0)) == 0  # without depth: the nearest in pixels
    assert nearest_pick(uv, z, (50.0, 50.0), depth_buffer=buffer) == 1  # the bottom is hidden by the top
    assert nearest_pick(uv, z, (50.0, 50.0), depth_buffer=np.zeros((100, 100))) == 0  # nothing drawn: not hidden
    assert nearest_pick(np.array([[50.0, 50.0], [50.0, 50.0]]), np.array([1.2, 1.1]), (50, 50)) == 1  # tie: nearer
    assert nearest_pick(np.array([[150.0, 50.0]]), np.array([1.0]), (145.0, 50.0), depth_buffer=buffer) is None


def test_screenshot_composes_the_windows_at_their_layout_positions():
    pytest.importorskip("PIL")
    from dsr_bench.annotator.screenshot import compose

    view = np.full((50, 80, 3), 200, np.uint8)
    panel = np.full((40, 30, 3), 90, np.uint8)
    out = compose((200, 120), [((10, 30), "3D", view), ((100, 30), "panel", panel)], title_height=20)
    assert out.shape == (120, 200, 3)
    assert np.all(out[30:80, 10:90] == 200) and np.all(out[30:70, 100:130] == 90)
    assert not np.all(out[10:30, 10:90] == out[0, 0])  # a title bar above each window
