"""Where the annotator's two windows go on the screen: the 3D view on the left, the panel (text column and both
cameras' images, stacked) on the right, both within the screen. Pure (`window_layout`), plus the screen size read
from the X display (`screen_size`) and the `--window-size WxH` parser.

Sizes in pixels, (width, height) order unless named; positions are the windows' top-left corners (x right, y down).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass

from dsr_bench.errors import UserError

#: The screen assumed when none can be read (width, height px).
FALLBACK_SCREEN = (1600, 1000)
#: Room left for the window manager: title bars above each window, a task bar below, the screen's edges (px).
TOP_MARGIN = 40
BOTTOM_MARGIN = 50
SIDE_MARGIN = 10
GAP = 10
#: The panel takes at most this share of the usable width; the 3D view the rest.
PANEL_MAX_SHARE = 0.55
#: Height of each camera image's title row in the panel (px).
TITLE_HEIGHT = 19
#: The smallest screen laid out (px); smaller ones are refused in one line.
MIN_SCREEN = (800, 600)


@dataclass(frozen=True)
class Layout:
    """Window rectangles (x, y, width, height) px of the 3D view and the panel, and the panel's inner layout: its
    text column width, each camera image's width and height (stacked, each under a title row), its font size."""

    view: tuple[int, int, int, int]
    panel: tuple[int, int, int, int]
    text_width: int
    image_width: int
    image_height: int
    font_size: int


def _width_for_height(height: int, image_aspect: float) -> int:
    """The widest image (px) two of which, `image_aspect` x as high (rounded) and each under a title row, fit
    `height` px."""
    return int(((height - 2 * TITLE_HEIGHT) / 2 - 0.5) / image_aspect)


def window_layout(screen_width: int, screen_height: int, *, image_aspect: float = 0.75,
                  max_image_width: int = 960, origin: tuple[int, int] = (0, 0)) -> Layout:
    """Both windows side by side within a screen of `screen_width` x `screen_height` px whose top-left corner is
    at `origin` (x, y px; a monitor's position on a larger X screen).

    The panel stacks the two camera images (height = `image_aspect` x width, each under a title row) beside its
    text column, as large as the usable height allows, but takes at most `PANEL_MAX_SHARE` of the usable width
    (the 3D view gets the rest) and images at most `max_image_width` px wide (their native width). Both windows
    span the usable height (screen less the margins for title bars and a task bar).
    """
    if screen_width < MIN_SCREEN[0] or screen_height < MIN_SCREEN[1]:
        raise UserError(f"screen {screen_width}x{screen_height} is too small for the annotator windows (at least "
                        f"{MIN_SCREEN[0]}x{MIN_SCREEN[1]}); give a larger one with --window-size WxH")
    usable_w = screen_width - 2 * SIDE_MARGIN - GAP
    usable_h = screen_height - TOP_MARGIN - BOTTOM_MARGIN
    text_width = 340 if screen_width >= 1400 else 300
    font_size = 14 if usable_h >= 800 else 12
    by_height = _width_for_height(usable_h, image_aspect)
    by_width = int(PANEL_MAX_SHARE * usable_w) - text_width
    image_width = max(64, min(by_height, by_width, int(max_image_width)))
    image_height = int(round(image_width * image_aspect))
    panel_w = text_width + image_width
    view_w = usable_w - panel_w
    x0, y0 = origin[0] + SIDE_MARGIN, origin[1] + TOP_MARGIN
    return Layout(view=(x0, y0, view_w, usable_h), panel=(x0 + view_w + GAP, y0, panel_w, usable_h),
                  text_width=text_width, image_width=image_width, image_height=image_height, font_size=font_size)


def panel_layout(width: int, height: int, text_width: int, *, image_aspect: float = 0.75,
                 max_image_width: int = 960) -> tuple[int, int]:
    """(text column width, camera image width) px for a panel window of `width` x `height` px (after the user or
    the window manager resized it): the text column keeps `text_width` (narrowed to leave the images 64 px when the
    window is narrower), and the two stacked images (height = `image_aspect` x width, each under a title row) get
    the largest width that fits the window's height and the width beside the text, at most `max_image_width`.
    The panel `window_layout` lays out gives back its own sizes."""
    text_width = max(1, min(int(text_width), int(width) - 64))
    by_height = _width_for_height(int(height), image_aspect)
    image_width = max(64, min(by_height, int(width) - text_width, int(max_image_width)))
    return text_width, image_width


def parse_window_size(text: str) -> tuple[int, int]:
    """'WxH' (e.g. '1600x1000') -> (width, height) px; anything else is a one-line UserError."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
    if not m:
        raise UserError(f"--window-size {text!r} is not WIDTHxHEIGHT in pixels; give e.g. --window-size 1600x1000")
    return int(m.group(1)), int(m.group(2))


def _xrandr_monitor() -> tuple[int, int, int, int] | None:
    """(width, height, x, y) px of the primary (else first) connected monitor from `xrandr --current`, or None."""
    if shutil.which("xrandr") is None:
        return None
    try:
        out = subprocess.run(["xrandr", "--current"], capture_output=True, text=True, timeout=5).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    found = re.findall(r" connected( primary)? (\d+)x(\d+)\+(\d+)\+(\d+)", out)
    if not found:
        return None
    primary, w, h, x, y = next((f for f in found if f[0]), found[0])
    return int(w), int(h), int(x), int(y)


def _xlib_screen() -> tuple[int, int] | None:
    """(width, height) px of the X display's default screen (libX11 through ctypes), or None."""
    import ctypes
    import ctypes.util
    import os

    display = os.environ.get("DISPLAY")
    if not display:
        return None
    try:
        xlib = ctypes.CDLL(ctypes.util.find_library("X11") or "libX11.so.6")
    except OSError:
        return None
    xlib.XOpenDisplay.restype = ctypes.c_void_p
    xlib.XOpenDisplay.argtypes = [ctypes.c_char_p]
    xlib.XCloseDisplay.argtypes = [ctypes.c_void_p]
    for name in ("XDefaultScreen", "XDisplayWidth", "XDisplayHeight"):
        getattr(xlib, name).restype = ctypes.c_int
    xlib.XDefaultScreen.argtypes = [ctypes.c_void_p]
    xlib.XDisplayWidth.argtypes = xlib.XDisplayHeight.argtypes = [ctypes.c_void_p, ctypes.c_int]
    handle = xlib.XOpenDisplay(display.encode())
    if not handle:
        return None
    try:
        screen = xlib.XDefaultScreen(handle)
        return int(xlib.XDisplayWidth(handle, screen)), int(xlib.XDisplayHeight(handle, screen))
    finally:
        xlib.XCloseDisplay(handle)


def screen_size() -> tuple[int, int, int, int]:
    """(width, height, x, y) px of the screen to lay the windows out on: the primary monitor (xrandr), else the X
    display's screen (libX11), else `FALLBACK_SCREEN` at (0, 0)."""
    monitor = _xrandr_monitor()
    if monitor is not None:
        return monitor
    screen = _xlib_screen()
    if screen is not None:
        return screen[0], screen[1], 0, 0
    return FALLBACK_SCREEN[0], FALLBACK_SCREEN[1], 0, 0
