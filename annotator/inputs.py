"""Checks of `import-capture`'s input files before anything is read or allocated from them (docs/annotator.md, "Real
captures in", "Checks"): JSON values of the right type (a number is a JSON number, not true or "912"), image sizes
within MAX_IMAGE_SIDE, a PNG's size and type from its header (before decoding it: a decoder allocates what the
header declares), and paths that stay inside SRC (no absolute paths, no '..', no link leading out of it).
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

from dsr_bench.errors import UserError

#: Largest image width or height (px) a rig file or a recording may declare: 4K (3840 x 2160) fits; RealSense streams
#: are at most 1920 x 1080. Every step's images are held in memory until the capture is written.
MAX_IMAGE_SIDE = 4096
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: PNG colour types (IHDR) -> channels as decoded.
PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def is_number(value) -> bool:
    """A JSON number (int or float; not true / false, not a string)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def finite(value) -> bool:
    """A JSON number that is finite (an int too large for a float is not)."""
    if not is_number(value):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def numbers(value, shape: tuple[int, ...]) -> bool:
    """Whether `value` is nested JSON lists of finite numbers of exactly `shape` ((5,), (4, 4), ...)."""
    if not shape:
        return finite(value)
    return isinstance(value, list) and len(value) == shape[0] and all(numbers(v, shape[1:]) for v in value)


def image_side(value) -> bool:
    """A JSON integer 1..MAX_IMAGE_SIDE (an image width or height in pixels)."""
    return isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= MAX_IMAGE_SIDE


def inside(src: Path, rel, field: str, where) -> Path:
    """SRC / `rel` (a path from the input's `field`, relative to SRC), checked to stay inside SRC: UserError naming
    `where` and the field when it is not a relative path, is absolute, climbs out with '..', or resolves (through
    links) to somewhere outside SRC."""
    fix = f"copy the file into {src} and give its path relative to it"
    if not isinstance(rel, str) or not rel.strip() or "\0" in rel:
        raise UserError(f"{where}: {field} must be a path relative to {src} (a string), got {str(rel)[:60]!r}; {fix}")
    path = Path(rel)
    if path.is_absolute() or ".." in path.parts:
        how = "an absolute path" if path.is_absolute() else "it climbs out with '..'"
        raise UserError(f"{where}: {field} {rel!r} is not inside {src} ({how}); {fix}")
    return resolved_inside(src, src / path, field, where)


def resolved_inside(src: Path, path: Path, field: str, where) -> Path:
    """`path` (under SRC), checked to resolve inside SRC (a link may point elsewhere in SRC, not out of it)."""
    try:
        real = path.resolve()
    except (OSError, RuntimeError) as exc:  # a link loop
        raise UserError(f"{where}: {field} {str(path)!r} cannot be resolved ({exc}); copy the file into "
                        f"{src}") from None
    if not real.is_relative_to(src.resolve()):
        shown = str(path.relative_to(src)) if path.is_relative_to(src) else str(path)
        raise UserError(f"{where}: {field} {shown!r} leads outside {src} (a link to {real}); copy the file into {src} "
                        "instead of linking it")
    return path


def png_header(path: Path) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from a PNG's IHDR chunk, reading 33 bytes; UserError naming the file
    when it is not a PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(33)
    except OSError as exc:
        raise UserError(f"{path}: unreadable image ({exc.strerror or exc}); re-export it as PNG") from None
    if len(head) < 33 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise UserError(f"{path}: not a PNG file (no PNG signature and header); re-export it as PNG")
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    return width, height, depth, colour


def png_shape(path: Path) -> tuple[tuple[int, ...], str, int, int]:
    """(array shape as decoded, dtype name, bit depth, colour type) that a PNG's header declares, read without
    decoding it."""
    width, height, depth, colour = png_header(path)
    channels = PNG_CHANNELS.get(colour, 0)
    shape = (height, width) if channels == 1 else (height, width, channels)
    return shape, "uint16" if depth == 16 else "uint8", depth, colour
