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

from dsr_bench.annotator.images import (RESIDUAL_SCALE, SELECTED_COLOR, STATUS_COLORS, mask_boundary, mesh_preview,
                                        muted_colors, object_colors, residual_ramp, resize_image, scaled_camera,
                                        silhouette_masks)
from dsr_bench.annotator.keys import ViewState, format_score, key_help_lines, object_name
from dsr_bench.errors import UserError

#: Panel layout (pixels): text column width, camera image width, font size.
PANEL_TEXT_WIDTH = 380
PANEL_IMAGE_WIDTH = 480
PANEL_FONT_SIZE = 14
#: The colour legend: (label, RGB 0..1) of the selected object and each status, as meshes and outlines use them.
LEGEND: list[tuple[str, tuple[float, float, float]]] = [("selected", SELECTED_COLOR)] + [
    (name, rgb) for name, rgb in STATUS_COLORS.items()]
#: Legend swatches to a row.
LEGEND_COLUMNS = 3
#: Panel-sized colour images kept in memory ((step, camera) pairs).
IMAGE_CACHE = 8
#: Fit scores kept in memory before the cache is emptied.
SCORE_CACHE = 256
#: Object outlines kept in memory ((camera, image width, object, pose, thickness) entries).
OUTLINE_CACHE = 64
#: The panel's background (RGB 0..255).
BACKGROUND = (24, 24, 28)
#: Text colours (RGB 0..255): the text, the keys' labels, the "next:" line (what to do now).
TEXT_COLOR = (235, 235, 235)
KEY_COLOR = (200, 220, 255)
HINT_COLOR = (255, 220, 130)
#: The line above the objects' previews and the one above the keys.
OBJECTS_TITLE = "objects (frame: status colour):"
KEYS_TITLE = "keys (mouse: rotate / pan / zoom the view)"
#: Each object's preview in the objects row: at most this size (px), cells at least this wide (px).
PREVIEW_SIZE = 56
PREVIEW_MIN_CELL = 52
#: ... and at least this size (px) where the window is too short for the text at PREVIEW_SIZE.
PREVIEW_MIN_SIZE = 28
#: The preview's background and the grey of an object without a known colour (RGB 0..255, 0..1).
PREVIEW_BACKGROUND = (44, 44, 50)
PREVIEW_GREY = (0.7, 0.7, 0.72)


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
    """The panel's text: status of the step and selected object, nudge settings, the message and what to do next
    (`ViewState.hint`), then the keys."""
    view = view or ViewState()
    obj, n = session.selected, session.num_objects
    statuses = session.status()
    step_mm = view.translation_step * 1000
    step_deg = np.rad2deg(view.rotation_step)
    lines = [
        f"step {session.step}/{session.num_steps}   object {obj + 1}/{n}: {object_name(session, obj)}",
        f"status: {statuses[obj] if 0 <= obj < len(statuses) else '-'}",
        format_score(cached_score(session, view, obj) if 0 <= obj < n else None),
        f"done here: {sum(s == 'confirmed' for s in statuses)}/{n} confirmed   undo {session.undo_depth}   "
        f"redo {session.redo_depth}",
        f"nudge: {'coarse' if view.coarse else 'fine'} {step_mm:g} mm / {step_deg:g} deg, {view.frame} axes",
        f"cloud: {'depth residual' if view.residual else 'capture colours'}",
        f"> {view.message}" if view.message else ">",
    ]
    if view.hint:
        lines.append(view.hint)
    return lines + [KEYS_TITLE] + key_help_lines()


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
def _row_image(left: str, right: str, text_width: int, font_size: int,
               color: tuple[int, int, int] = TEXT_COLOR) -> np.ndarray:
    """One text row (line height x text_width, 3) uint8: `left` at the margin (in `color`), `right` in the second
    column."""
    from PIL import Image, ImageDraw

    font = _font(font_size)
    row = Image.new("RGB", (text_width, _line_height(font_size)), BACKGROUND)
    draw = ImageDraw.Draw(row)
    draw.text((8, 0), left, fill=color, font=font)
    if right:
        draw.text((8 + 9 * font_size, 0), right, fill=KEY_COLOR, font=font)
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


@lru_cache(maxsize=64)
def _label_image(text: str, width: int, font_size: int) -> np.ndarray:
    """A centred label (line height x width, 3) uint8, cut to the width (an ellipsis ends a cut label)."""
    from PIL import Image, ImageDraw

    font = _font(font_size)
    row = Image.new("RGB", (width, _line_height(font_size)), BACKGROUND)
    draw = ImageDraw.Draw(row)
    shown = text
    while len(shown) > 3 and draw.textlength(shown, font=font) > width - 2:
        shown = shown[:-3] + ".."
    draw.text(((width - draw.textlength(shown, font=font)) / 2, 1), shown, fill=TEXT_COLOR, font=font)
    out = np.asarray(row)
    out.flags.writeable = False
    return out


def _legend_rows() -> int:
    """Rows of mesh-colour swatches in the legend (LEGEND_COLUMNS to a row)."""
    return -(-len(LEGEND) // LEGEND_COLUMNS)


def _legend_height(font_size: int) -> int:
    return (1 + _legend_rows()) * _line_height(font_size) + 10


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


def panel_image(lines: Sequence[str | np.ndarray], images: Sequence[tuple[str, np.ndarray]], *,
                text_width: int = PANEL_TEXT_WIDTH, font_size: int = PANEL_FONT_SIZE, height: int | None = None,
                legend: bool = True, width: int | None = None) -> np.ndarray:
    """(H, W, 3) uint8: the text lines in a dark column on the left, the titled images stacked on the right.

    A line "keys\tlabel" is drawn in two aligned columns; other lines wrap at the column width; a "next:" line (what
    to do now) is drawn in HINT_COLOR; an item that is an image (h, w, 3) uint8 (the objects' previews) is pasted
    as it is, between the rows. With `legend`, the colour legend follows the text: a swatch per mesh colour
    (`LEGEND`) and the depth-residual scale (0 .. `RESIDUAL_SCALE`, `residual_ramp`). H = `height` when given (the
    window's height: what does not fit is cut off at the bottom), else the taller of the text and the images;
    W = `width` when given (the window's width: the images cut off at the right if wider), else text_width + the
    widest image. Text rows, titles and the legend are rendered once and kept (`_row_image`, `_legend_image`).
    """
    line_h = _line_height(font_size)
    blocks: list[np.ndarray] = []
    for line in lines:
        if isinstance(line, np.ndarray):
            blocks.append(np.asarray(line, np.uint8))
            continue
        color = HINT_COLOR if line.startswith("next:") else TEXT_COLOR
        blocks += [_row_image(left, right, int(text_width), int(font_size), color)
                   for left, right in _wrap(line, int(text_width), int(font_size))]
    text_h = sum(b.shape[0] for b in blocks)
    img_w = max([im.shape[1] for _, im in images], default=0)
    img_h = sum(im.shape[0] + line_h for _, im in images)
    legend_h = _legend_height(font_size) if legend else 0
    if height is None:
        height = max(img_h, text_h + 10 + legend_h)
    width = int(text_width + img_w if width is None else width)
    canvas = np.empty((int(height), width, 3), np.uint8)
    canvas[...] = BACKGROUND
    y = 5
    for block in blocks:
        _paste(canvas, block, y, 0)
        y += block.shape[0]
    if legend:
        _paste(canvas, _legend_image(int(text_width), int(font_size)), y, 0)
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

    box = line_h - 6
    for k, (label, color) in enumerate(LEGEND):
        cx, cy = x + (k % LEGEND_COLUMNS) * (width // LEGEND_COLUMNS), y + (k // LEGEND_COLUMNS) * line_h
        draw.rectangle([cx, cy + 2, cx + box, cy + 2 + box], fill=rgb(color))
        draw.text((cx + box + 4, cy), label, fill=(235, 235, 235), font=font)
    y += _legend_rows() * line_h + 4
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
        self._previews: dict[tuple[int, int], np.ndarray] = {}  # each object's mesh preview by (object, size)

    def _preview(self, obj: int, size: int) -> np.ndarray:
        """Object `obj`'s mesh preview (`images.mesh_preview`), size x size px, in its colour as the muted views show
        it (its identity's `color`, a simulated capture's; grey without one), all objects at one scale; kept."""
        key = (obj, size)
        if key not in self._previews:
            if self._meshes is None:
                self._meshes = [self.session.capture.mesh(i) for i in range(self.session.num_objects)]
            extent = max(float(np.linalg.norm(np.ptp(v, axis=0))) for v, _ in self._meshes if len(v))
            identity = self.session.capture.objects[obj].identity
            color = identity.get("color") if isinstance(identity, dict) else None
            try:
                rgb = muted_colors(np.asarray(color, np.float64).reshape(3))
            except (TypeError, ValueError):
                rgb = np.asarray(PREVIEW_GREY)
            self._previews[key] = mesh_preview(*self._meshes[obj], size, extent, rgb, PREVIEW_BACKGROUND)
        return self._previews[key]

    def objects_row(self, width: int | None = None, size: int = PREVIEW_SIZE) -> np.ndarray:
        """The objects' previews (h, width, 3) uint8 (default width: the text column's), in object order, as many
        to a row as fit: each framed in its mesh colour (the selected one orange, the others by status) over its
        number and name, so that an object not placed yet (no outline, no mesh in 3D) can be found by its shape
        and colour. `size`: the previews' largest size (px)."""
        s = self.session
        n, font_size = s.num_objects, int(self.font_size)
        width = int(self.text_width if width is None else width)
        per_row = max(1, min(n, (width - 8) // PREVIEW_MIN_CELL))
        cell = (width - 8) // per_row
        thumb = max(8, min(int(size), cell - 8))
        line_h = _line_height(font_size)
        cell_h = thumb + 4 + line_h
        out = np.empty((-(-n // per_row) * cell_h + 4, width, 3), np.uint8)
        out[...] = BACKGROUND
        frames = np.round(object_colors(s.status(), s.selected) * 255).astype(np.uint8)
        for i in range(n):
            r, c = divmod(i, per_row)
            x, y = 8 + c * cell + (cell - thumb - 4) // 2, r * cell_h + 2
            out[y:y + thumb + 4, x:x + thumb + 4] = frames[i]
            out[y + 2:y + 2 + thumb, x + 2:x + 2 + thumb] = self._preview(i, thumb)
            _paste(out, _label_image(f"{i + 1} {s.capture.objects[i].name}", cell, font_size), y + thumb + 4,
                   8 + c * cell)
        return out

    def label(self, name: str, camera, image: np.ndarray, poses: np.ndarray, colors: np.ndarray,
              selected: int | None) -> np.ndarray:
        """`image` (an `overlay`) with each posed object's number beside its outline (above its top-left corner),
        in its colour on a dark box, drawn without anti-aliasing (exactly the outline's colour)."""
        from PIL import Image, ImageDraw

        out = Image.fromarray(np.asarray(image, np.uint8))
        draw = ImageDraw.Draw(out)
        draw.fontmode = "1"
        font = _font(self.font_size)
        rgb = np.round(np.clip(np.asarray(colors, np.float64), 0, 1) * 255).astype(np.uint8)
        for i, pose in enumerate(np.asarray(poses, np.float64)):
            if not np.all(np.isfinite(pose)):
                continue
            edge = self._outline(name, camera, i, pose, 1 + (i == selected))
            if len(edge) == 0:
                continue
            top, left = int(edge.min() // camera.width), int((edge % camera.width).min())
            text = str(i + 1)
            w, h = int(draw.textlength(text, font=font)) + 4, _line_height(self.font_size)
            x, y = min(max(0, left), camera.width - w), max(0, top - h - 1)
            draw.rectangle([x, y, x + w - 1, y + h - 2], fill=(16, 16, 18))
            draw.text((x + 2, y), text, fill=tuple(int(c) for c in rgb[i]), font=font)
        return np.asarray(out)

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
        """The panel image (H, W, 3) uint8: help/status text, the objects' previews (`objects_row`) and the legend
        beside both cameras' images (muted, `muted_colors`) with every mesh's outline and number (`label`)."""
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
            drawn = self.overlay(name, small, self._images[key], poses, colors, s.selected)
            overlays.append((name, self.label(name, small, drawn, poses, colors, s.selected)))
        lines: list[str | np.ndarray] = list(help_lines(s, self.view))
        # the objects' previews under the camera images where the window leaves them room (a narrow screen),
        # else in the text column above the keys
        below = self.objects_row(self.image_width)
        free = None if self.height is None else self.height - sum(im.shape[0] + _line_height(self.font_size)
                                                                  for _, im in overlays)
        if free is not None and free >= below.shape[0] + _line_height(self.font_size):
            overlays.append((OBJECTS_TITLE, below))
        else:  # smaller previews when a long message would push the legend out of the window
            line_h = _line_height(self.font_size)
            text_h = 15 + line_h + _legend_height(self.font_size) + sum(
                len(_wrap(line, int(self.text_width), int(self.font_size))) * line_h for line in lines
                if isinstance(line, str))
            row = self.objects_row()
            if self.height is not None and text_h + row.shape[0] > self.height:
                row = self.objects_row(size=max(PREVIEW_MIN_SIZE, PREVIEW_SIZE - (text_h + row.shape[0] - self.height)))
            at = lines.index(KEYS_TITLE)
            lines[at:at] = [OBJECTS_TITLE, row]
        return panel_image(lines, overlays, text_width=self.text_width, font_size=self.font_size, height=self.height,
                           width=self.width)
