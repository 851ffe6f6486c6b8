"""The annotator's panel: one image with the help / status text beside both cameras' colour images, on which every
mesh's projected outline is drawn (the legacy open3d visualizer draws no text, so the window shows this image).

No window here (testable without a display): `Panel(session, view).image()` draws it from the Session's state
and the Controller's `ViewState`.

Drawn every frame something changed, so what does not change is kept: each text row and the legend are rendered
once (`_row_image`, `_legend_image`: cached), each camera's panel-sized image once per step, and each object's
outline once per (camera, image width, pose, thickness) (`Panel._outline`): a nudge re-rasterises only the moved
object's outline.
"""

from __future__ import annotations

from collections import OrderedDict
from functools import lru_cache
from typing import Sequence

import numpy as np

from annotator.images import (RESIDUAL_SCALE, SELECTED_COLOR, STATUS_COLORS, mask_boundary, muted_colors,
                               object_colors, residual_ramp, resize_image, scaled_camera, silhouette_masks)
from annotator.keys import ViewState, format_score, key_help_lines, object_name
from dsr_bench.errors import UserError

#: Panel layout (pixels): text column width, camera image width, font size.
PANEL_TEXT_WIDTH = 380
PANEL_IMAGE_WIDTH = 480
PANEL_FONT_SIZE = 14
#: The colour legend: (label, RGB 0..1) of the selected object and each status, as meshes and outlines use them.
LEGEND: list[tuple[str, tuple[float, float, float]]] = [("selected", SELECTED_COLOR)] + [
    (name, rgb) for name, rgb in STATUS_COLORS.items()]
#: Panel-sized colour images kept in memory ((step, camera) pairs).
IMAGE_CACHE = 8
#: Fit scores kept in memory before the cache is emptied.
SCORE_CACHE = 256
#: Object outlines kept in memory ((camera, image width, object, pose, thickness) entries).
OUTLINE_CACHE = 64
#: The panel's background (RGB 0..255).
BACKGROUND = (24, 24, 28)


def cached_score(session, view: ViewState, obj: int):
    """The fit score of object `obj`'s pose at the current step: the one the session recorded with the pose's
    last change (no new fit), else session.score(obj) cached in `view` on (step, obj, pose) (None when it fails)."""
    stored = session.stored_score(obj)
    if stored is not None:
        return stored
    key = (session.step, obj, session.poses()[obj].round(9).tobytes())
    if key not in view.score_cache:
        if len(view.score_cache) > SCORE_CACHE:
            view.score_cache.clear()
        try:
            view.score_cache[key] = session.score(obj)
        except UserError:
            view.score_cache[key] = None
    return view.score_cache[key]


def help_lines(session, view: ViewState | None = None) -> list[str]:
    """The panel's text: status of the step and selected object, nudge settings, then the keys."""
    view = view or ViewState()
    obj, n = session.selected, session.num_objects
    statuses = session.status()
    step_mm = view.translation_step * 1000
    step_deg = np.rad2deg(view.rotation_step)
    lines = [
        f"step {session.step}/{session.num_steps}   object {obj + 1}/{n}: {object_name(session, obj)}",
        f"status: {statuses[obj] if 0 <= obj < len(statuses) else '-'}",
        format_score(cached_score(session, view, obj) if 0 <= obj < n else None),
        f"done here: {sum(s == 'confirmed' for s in statuses)}/{n} confirmed",
        f"nudge: {'coarse' if view.coarse else 'fine'} {step_mm:g} mm / {step_deg:g} deg, {view.frame} axes",
        f"cloud: {'depth residual' if view.residual else 'capture colours'}",
        f"undo {session.undo_depth}   redo {session.redo_depth}",
        f"> {view.message}" if view.message else ">",
        "",
        "keys (mouse: rotate / pan / zoom the view)",
    ]
    return lines + key_help_lines()


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()


def _line_height(font_size: int) -> int:
    return font_size + 5


@lru_cache(maxsize=512)
def _wrap(line: str, text_width: int, font_size: int) -> tuple[tuple[str, str], ...]:
    """The rows (left, right) of one text line: "keys\tlabel" is one row of two columns; other lines wrap at the
    column width (`text_width` px less the margins)."""
    from PIL import Image, ImageDraw

    left, _, right = line.partition("\t")
    if right:
        return ((left, right),)
    font = _font(font_size)
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    rows, words, current = [], left.split(" "), ""
    for word in words:  # wrap to the column width
        trial = f"{current} {word}" if current else word
        if current and measure.textlength(trial, font=font) > text_width - 16:
            rows.append((current, ""))
            current = "  " + word
        else:
            current = trial
    rows.append((current, ""))
    return tuple(rows)


@lru_cache(maxsize=512)
def _row_image(left: str, right: str, text_width: int, font_size: int) -> np.ndarray:
    """One text row (line height x text_width, 3) uint8: `left` at the margin, `right` in the second column."""
    from PIL import Image, ImageDraw

    font = _font(font_size)
    row = Image.new("RGB", (text_width, _line_height(font_size)), BACKGROUND)
    draw = ImageDraw.Draw(row)
    draw.text((8, 0), left, fill=(235, 235, 235), font=font)
    if right:
        draw.text((8 + 9 * font_size, 0), right, fill=(200, 220, 255), font=font)
    out = np.asarray(row)
    out.flags.writeable = False
    return out


@lru_cache(maxsize=16)
def _title_image(title: str, width: int, font_size: int) -> np.ndarray:
    """A camera image's title row (line height x width, 3) uint8."""
    from PIL import Image, ImageDraw

    row = Image.new("RGB", (width, _line_height(font_size)), BACKGROUND)
    ImageDraw.Draw(row).text((6, 2), title, fill=(255, 210, 120), font=_font(font_size))
    out = np.asarray(row)
    out.flags.writeable = False
    return out


def _legend_height(font_size: int) -> int:
    return (2 + (len(LEGEND) + 1) // 2) * _line_height(font_size) + 14


@lru_cache(maxsize=16)
def _legend_image(text_width: int, font_size: int) -> np.ndarray:
    """The colour legend (`_draw_legend`) as an image (legend height x text_width, 3) uint8."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (text_width, _legend_height(font_size)), BACKGROUND)
    _draw_legend(ImageDraw.Draw(img), _font(font_size), 8, 6, text_width - 16, _line_height(font_size))
    out = np.asarray(img)
    out.flags.writeable = False
    return out


def _paste(canvas: np.ndarray, image: np.ndarray, y: int, x: int) -> None:
    """Copy `image` into `canvas` with its top-left corner at (y, x) px, cut at the canvas's edges."""
    h = max(0, min(image.shape[0], canvas.shape[0] - y))
    w = max(0, min(image.shape[1], canvas.shape[1] - x))
    if h and w:
        canvas[y:y + h, x:x + w] = image[:h, :w]


def panel_image(lines: Sequence[str], images: Sequence[tuple[str, np.ndarray]], *,
                text_width: int = PANEL_TEXT_WIDTH, font_size: int = PANEL_FONT_SIZE, height: int | None = None,
                legend: bool = True, width: int | None = None) -> np.ndarray:
    """(H, W, 3) uint8: the text lines in a dark column on the left, the titled images stacked on the right.

    A line "keys\tlabel" is drawn in two aligned columns; other lines wrap at the column width. With `legend`, the
    colour legend follows the text: a swatch per mesh colour (`LEGEND`) and the depth-residual scale
    (0 .. `RESIDUAL_SCALE`, `residual_ramp`). H = `height` when given (the window's height: what does not fit is
    cut off at the bottom), else the taller of the text and the images; W = `width` when given (the window's width:
    the images cut off at the right if wider), else text_width + the widest image. Text rows, titles and the legend
    are rendered once and kept (`_row_image`, `_legend_image`).
    """
    line_h = _line_height(font_size)
    rows = [row for line in lines for row in _wrap(line, int(text_width), int(font_size))]
    img_w = max([im.shape[1] for _, im in images], default=0)
    img_h = sum(im.shape[0] + line_h for _, im in images)
    legend_h = _legend_height(font_size) if legend else 0
    if height is None:
        height = max(img_h, len(rows) * line_h + 10 + legend_h)
    width = int(text_width + img_w if width is None else width)
    canvas = np.empty((int(height), width, 3), np.uint8)
    canvas[...] = BACKGROUND
    for k, (left, right) in enumerate(rows):
        _paste(canvas, _row_image(left, right, int(text_width), int(font_size)), 5 + k * line_h, 0)
    if legend:
        _paste(canvas, _legend_image(int(text_width), int(font_size)), 5 + len(rows) * line_h, 0)
    y = 0
    for title, im in images:
        _paste(canvas, _title_image(title, im.shape[1], int(font_size)), y, int(text_width))
        _paste(canvas, np.asarray(im, np.uint8), y + line_h, int(text_width))
        y += im.shape[0] + line_h
    return canvas


def _draw_legend(draw, font, x: int, y: int, width: int, line_h: int) -> None:
    """The colour legend at (x, y) px, `width` px wide: mesh colours two to a row, then the residual scale."""
    def rgb(c) -> tuple[int, int, int]:
        r, g, b = (int(round(255 * float(v))) for v in c)
        return r, g, b

    draw.text((x, y), "colours (meshes, outlines):", fill=(235, 235, 235), font=font)
    box = line_h - 6
    for k, (label, color) in enumerate(LEGEND):
        cx, cy = x + (k % 2) * (width // 2), y + (1 + k // 2) * line_h
        draw.rectangle([cx, cy + 2, cx + box, cy + 2 + box], fill=rgb(color))
        draw.text((cx + box + 6, cy), label, fill=(235, 235, 235), font=font)
    y += (1 + (len(LEGEND) + 1) // 2) * line_h + 4
    label = f"residual (R): 0 .. {RESIDUAL_SCALE * 1000:g}+ mm"
    draw.text((x, y), label, fill=(235, 235, 235), font=font)
    bar_x = x + int(draw.textlength(label, font=font)) + 8
    bar_w = max(20, x + width - bar_x)
    ramp = residual_ramp(np.linspace(0.0, 1.0, bar_w))
    for i, color in enumerate(ramp):
        draw.line([bar_x + i, y + 2, bar_x + i, y + 2 + box], fill=rgb(color))


class Panel:
    """Draws the panel of a Session and a ViewState, keeping what does not change between frames: the panel-sized
    colour images of recent steps and the outline of each object at each pose drawn lately."""

    def __init__(self, session, view: ViewState, *, text_width: int = PANEL_TEXT_WIDTH,
                 image_width: int = PANEL_IMAGE_WIDTH, font_size: int = PANEL_FONT_SIZE, height: int | None = None,
                 width: int | None = None):
        """text_width, image_width, font_size: px; height, width: the panel window's size (px), None to fit."""
        self.session = session
        self.view = view
        self.text_width, self.image_width, self.font_size = text_width, image_width, font_size
        self.height, self.width = height, width
        self._images: dict[tuple[int, str, int], np.ndarray] = {}  # panel-sized images by (step, camera, width)
        self._outlines: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._meshes: list[tuple[np.ndarray, np.ndarray]] | None = None

    def resize(self, text_width: int, image_width: int, width: int | None, height: int | None) -> None:
        """Draw from now on at another size (px): the text column's and camera images' widths, the window's."""
        self.text_width, self.image_width, self.width, self.height = text_width, image_width, width, height

    def _outline(self, name: str, camera, obj: int, pose: np.ndarray, thickness: int) -> np.ndarray:
        """Flat pixel indices (K,) of object `obj`'s outline at `pose` (7,) in `camera` (a panel-sized camera
        named `name`), `thickness` px wide: the inner boundary of its amodal silhouette (`silhouette_masks`,
        `mask_boundary`, taken within the silhouette's bounding box); kept for the next frames."""
        key = (name, camera.width, obj, np.asarray(pose, np.float64).tobytes(), thickness)
        found = self._outlines.get(key)
        if found is not None:
            self._outlines.move_to_end(key)
            return found
        if self._meshes is None:
            self._meshes = [self.session.capture.mesh(i) for i in range(self.session.num_objects)]
        mask = silhouette_masks(camera, [self._meshes[obj]], np.asarray(pose, np.float64)[None])[0]
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        out = np.zeros(0, np.int64)
        if len(rows):
            pad = thickness + 1  # zeros around the box, or the image's edge: the erosion sees what it saw before
            r0, r1 = max(0, rows[0] - pad), min(mask.shape[0], rows[-1] + 1 + pad)
            c0, c1 = max(0, cols[0] - pad), min(mask.shape[1], cols[-1] + 1 + pad)
            edge = np.argwhere(mask_boundary(mask[r0:r1, c0:c1], thickness)) + [r0, c0]
            out = edge[:, 0] * mask.shape[1] + edge[:, 1]
        self._outlines[key] = out
        while len(self._outlines) > OUTLINE_CACHE:
            self._outlines.popitem(last=False)
        return out

    def overlay(self, name: str, camera, base: np.ndarray, poses: np.ndarray, colors: np.ndarray,
                selected: int | None) -> np.ndarray:
        """A copy of a panel-sized image `base` (H, W, 3) uint8 with each posed object's outline (1 px, the selected
        one's 2 px and drawn last, on top) in its colour (N, 3) RGB 0..1: what `images.outline_overlay` draws."""
        out = np.array(base, np.uint8, copy=True)
        flat = out.reshape(-1, 3)
        rgb = np.round(np.clip(np.asarray(colors, np.float64), 0, 1) * 255).astype(np.uint8)
        n = len(poses)
        order = [i for i in range(n) if i != selected] + ([selected] if selected is not None and 0 <= selected < n
                                                          else [])
        for i in order:
            if np.all(np.isfinite(poses[i])):
                flat[self._outline(name, camera, i, poses[i], 1 + (i == selected))] = rgb[i]
        return out

    def image(self) -> np.ndarray:
        """The panel image (H, W, 3) uint8: help/status text and the legend beside both cameras' images (muted,
        `muted_colors`) with every mesh's outline."""
        s = self.session
        capture = s.capture
        colors = object_colors(s.status(), s.selected)
        poses = s.poses()
        overlays = []
        for name, cam in capture.cameras.items():
            small = scaled_camera(cam.camera, self.image_width)
            key = (s.step, name, small.width)
            if key not in self._images:
                if len(self._images) >= IMAGE_CACHE:
                    self._images.pop(next(iter(self._images)))
                small_color = resize_image(capture.color(s.step, name), small.width, small.height)
                # muted like the 3D view's cloud: no object's own colour reads as a status colour of an outline
                self._images[key] = np.round(muted_colors(small_color / 255.0) * 255).astype(np.uint8)
            overlays.append((name, self.overlay(name, small, self._images[key], poses, colors, s.selected)))
        return panel_image(help_lines(s, self.view), overlays, text_width=self.text_width,
                           font_size=self.font_size, height=self.height, width=self.width)
