"""The annotator's panel: one image with the help / status text beside both cameras' colour images, on which every
mesh's projected outline is drawn (the legacy open3d visualizer draws no text, so the window shows this image).

No window here (testable without a display): `Panel(session, view).image()` draws it from the Session's state
and the Controller's `ViewState`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from annotator.images import (SELECTED_COLOR, STATUS_COLORS, muted_colors, object_colors, outline_overlay,
                               residual_ramp, resize_image, scaled_camera)
from annotator.keys import ViewState, format_score, key_help_lines, object_name
from dsr_bench.errors import UserError

#: Panel layout (pixels): text column width, camera image width, font size.
PANEL_TEXT_WIDTH = 380
PANEL_IMAGE_WIDTH = 480
PANEL_FONT_SIZE = 14
#: The colour legend: (label, RGB 0..1) of the selected object and each status, as meshes and outlines use them.
LEGEND: list[tuple[str, tuple[float, float, float]]] = [("selected", SELECTED_COLOR)] + [
    (name, rgb) for name, rgb in STATUS_COLORS.items()]
#: The residual colour scale's top (m): `Session.residual_colors`' default `max_residual`.
RESIDUAL_SCALE = 0.01
#: Panel-sized colour images kept in memory ((step, camera) pairs).
IMAGE_CACHE = 8
#: Fit scores kept in memory before the cache is emptied.
SCORE_CACHE = 256


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


def panel_image(lines: Sequence[str], images: Sequence[tuple[str, np.ndarray]], *,
                text_width: int = PANEL_TEXT_WIDTH, font_size: int = PANEL_FONT_SIZE, height: int | None = None,
                legend: bool = True) -> np.ndarray:
    """(H, W, 3) uint8: the text lines in a dark column on the left, the titled images stacked on the right.

    A line "keys\tlabel" is drawn in two aligned columns; other lines wrap at the column width. With `legend`, the
    colour legend follows the text: a swatch per mesh colour (`LEGEND`) and the depth-residual scale
    (0 .. `RESIDUAL_SCALE`, `residual_ramp`). H = `height` when given (the window's height: what does not fit is
    cut off at the bottom), else the taller of the text and the images; W = text_width + the widest image.
    """
    from PIL import Image, ImageDraw

    font = _font(font_size)
    line_h = font_size + 5
    title_h = line_h
    tab_x = 8 + 9 * font_size  # second column of "keys\tlabel" lines
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    rows: list[tuple[str, str]] = []
    for line in lines:
        left, _, right = line.partition("\t")
        if right:
            rows.append((left, right))
            continue
        words, current = left.split(" "), ""
        for word in words:  # wrap to the column width
            trial = f"{current} {word}" if current else word
            if current and measure.textlength(trial, font=font) > text_width - 16:
                rows.append((current, ""))
                current = "  " + word
            else:
                current = trial
        rows.append((current, ""))
    img_w = max([im.shape[1] for _, im in images], default=0)
    img_h = sum(im.shape[0] + title_h for _, im in images)
    legend_h = (2 + (len(LEGEND) + 1) // 2) * line_h + 14 if legend else 0
    if height is None:
        height = max(img_h, len(rows) * line_h + 10 + legend_h)
    canvas = Image.new("RGB", (text_width + img_w, int(height)), (24, 24, 28))
    draw = ImageDraw.Draw(canvas)
    for k, (left, right) in enumerate(rows):
        draw.text((8, 5 + k * line_h), left, fill=(235, 235, 235), font=font)
        if right:
            draw.text((tab_x, 5 + k * line_h), right, fill=(200, 220, 255), font=font)
    if legend:
        _draw_legend(draw, font, 8, 5 + len(rows) * line_h + 6, text_width - 16, line_h)
    y = 0
    for title, im in images:
        draw.text((text_width + 6, y + 2), title, fill=(255, 210, 120), font=font)
        canvas.paste(Image.fromarray(np.asarray(im, np.uint8)), (text_width, y + title_h))
        y += im.shape[0] + title_h
    return np.asarray(canvas)


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
    """Draws the panel of a Session and a ViewState, keeping the panel-sized colour images of recent steps."""

    def __init__(self, session, view: ViewState, *, text_width: int = PANEL_TEXT_WIDTH,
                 image_width: int = PANEL_IMAGE_WIDTH, font_size: int = PANEL_FONT_SIZE, height: int | None = None):
        """text_width, image_width, font_size: px; height: the panel window's height (px), None to fit."""
        self.session = session
        self.view = view
        self.text_width, self.image_width, self.font_size, self.height = text_width, image_width, font_size, height
        self._images: dict[tuple[int, str], np.ndarray] = {}  # panel-sized colour images by (step, camera)

    def image(self) -> np.ndarray:
        """The panel image (H, W, 3) uint8: help/status text and the legend beside both cameras' images (muted,
        `muted_colors`) with every mesh's outline."""
        s = self.session
        capture = s.capture
        colors = object_colors(s.status(), s.selected)
        meshes = [capture.mesh(i) for i in range(s.num_objects)]
        overlays = []
        for name, cam in capture.cameras.items():
            small = scaled_camera(cam.camera, self.image_width)
            key = (s.step, name)
            if key not in self._images:
                if len(self._images) >= IMAGE_CACHE:
                    self._images.pop(next(iter(self._images)))
                small_color = resize_image(capture.color(*key), small.width, small.height)
                # muted like the 3D view's cloud: no object's own colour reads as a status colour of an outline
                self._images[key] = np.round(muted_colors(small_color / 255.0) * 255).astype(np.uint8)
            overlays.append((name, outline_overlay(self._images[key], small, meshes, s.poses(), colors=colors,
                                                   selected=s.selected)))
        return panel_image(help_lines(s, self.view), overlays, text_width=self.text_width,
                           font_size=self.font_size, height=self.height)
