"""The annotator's panel: one image with the help / status text beside both cameras' colour images, on which every
mesh's projected outline is drawn (the legacy open3d visualizer draws no text, so the window shows this image).

No window here (testable without a display): `Panel(session, view).image()` draws it from the Session's state
and the Controller's `ViewState`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from annotator.images import object_colors, outline_overlay, resize_image, scaled_camera
from annotator.keys import ViewState, format_score, key_help_lines, object_name
from dsr_bench.errors import UserError

#: Panel layout (pixels): text column width, camera image width, font size.
PANEL_TEXT_WIDTH = 380
PANEL_IMAGE_WIDTH = 480
PANEL_FONT_SIZE = 14
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
                text_width: int = PANEL_TEXT_WIDTH, font_size: int = PANEL_FONT_SIZE) -> np.ndarray:
    """(H, W, 3) uint8: the text lines in a dark column on the left, the titled images stacked on the right.

    A line "keys\tlabel" is drawn in two aligned columns; other lines wrap at the column width. H fits
    the taller of the text and the images; W = text_width + the widest image.
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
    height = max(img_h, len(rows) * line_h + 10)
    canvas = Image.new("RGB", (text_width + img_w, height), (24, 24, 28))
    draw = ImageDraw.Draw(canvas)
    for k, (left, right) in enumerate(rows):
        draw.text((8, 5 + k * line_h), left, fill=(235, 235, 235), font=font)
        if right:
            draw.text((tab_x, 5 + k * line_h), right, fill=(200, 220, 255), font=font)
    y = 0
    for title, im in images:
        draw.text((text_width + 6, y + 2), title, fill=(255, 210, 120), font=font)
        canvas.paste(Image.fromarray(np.asarray(im, np.uint8)), (text_width, y + title_h))
        y += im.shape[0] + title_h
    return np.asarray(canvas)


class Panel:
    """Draws the panel of a Session and a ViewState, keeping the panel-sized colour images of recent steps."""

    def __init__(self, session, view: ViewState):
        self.session = session
        self.view = view
        self._images: dict[tuple[int, str], np.ndarray] = {}  # panel-sized colour images by (step, camera)

    def image(self) -> np.ndarray:
        """The panel image (H, W, 3) uint8: help/status text beside both cameras' outline overlays."""
        s = self.session
        capture = s.capture
        colors = object_colors(s.status(), s.selected)
        meshes = [capture.mesh(i) for i in range(s.num_objects)]
        overlays = []
        for name, cam in capture.cameras.items():
            small = scaled_camera(cam.camera, PANEL_IMAGE_WIDTH)
            key = (s.step, name)
            if key not in self._images:
                if len(self._images) >= IMAGE_CACHE:
                    self._images.pop(next(iter(self._images)))
                self._images[key] = resize_image(capture.color(*key), small.width, small.height)
            overlays.append((name, outline_overlay(self._images[key], small, meshes, s.poses(), colors=colors,
                                                   selected=s.selected)))
        return panel_image(help_lines(s, self.view), overlays)
