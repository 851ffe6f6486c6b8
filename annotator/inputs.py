"""Checks of `import-capture`'s input files before anything is read or allocated from them (docs/annotator.md, "Real
captures in", "Checks"): JSON values of the right type (a number is a JSON number, not true or "912"), image sizes
within MAX_IMAGE_SIDE, a PNG's size and type from its header (before decoding it: a decoder allocates what the
header declares), a PNG whole to its last byte (every chunk's CRC, IEND at its end: a file cut short), paths that
stay inside SRC (no absolute paths, no '..', no link leading out of it), and names that become part of output paths
and identities (a capture's, an object's: one plain name, no '/', '\\', '..').
"""

from __future__ import annotations

import json
import math
import re
import struct
import zlib
from pathlib import Path

from dsr_bench.errors import UserError

#: Largest image width or height (px) a rig file or a recording may declare: 4K (3840 x 2160) fits; RealSense streams
#: are at most 1920 x 1080. Every step's images are held in memory until the capture is written.
MAX_IMAGE_SIDE = 4096
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: PNG colour types (IHDR) -> channels as decoded.
PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
#: Longest name (characters) of a capture or an object: one file name (255 bytes on common file systems) with room.
MAX_NAME = 128


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


def png_intact(path: Path) -> None:
    """UserError naming the file unless the PNG is whole: every chunk complete and its CRC right, up to IEND. A file
    cut short (a copy or an export that stopped) decodes without error in PIL while only its last 20 bytes (IEND,
    the last IDAT's CRC and zlib checksum) are gone. Streams the file (1 MiB at a time): nothing is held but a
    block."""
    fix = "re-export it, or copy it again from the rig"
    try:
        with open(path, "rb") as f:
            f.seek(len(PNG_SIGNATURE))  # the signature and IHDR were read by png_header
            while True:
                at = f.tell()
                head = f.read(8)
                if len(head) < 8:
                    raise UserError(f"{path}: truncated PNG (it ends at byte {at} without its IEND chunk: the file was "
                                    f"cut short); {fix}")
                length, kind = struct.unpack(">I4s", head)
                name = kind.decode("latin-1")
                crc, left = zlib.crc32(kind), length
                while left:
                    block = f.read(min(left, 1 << 20))
                    if not block:
                        break
                    crc, left = zlib.crc32(block, crc), left - len(block)
                stored = f.read(4)
                if left or len(stored) < 4:
                    raise UserError(f"{path}: truncated PNG (its {name!r} chunk at byte {at} runs past the end of "
                                    f"the file, and no IEND follows: the file was cut short); {fix}")
                if int.from_bytes(stored, "big") != crc:
                    raise UserError(f"{path}: corrupt PNG (its {name!r} chunk at byte {at} fails its CRC); {fix}")
                if kind == b"IEND":
                    return
    except OSError as exc:
        raise UserError(f"{path}: unreadable image ({exc.strerror or exc}); {fix}") from None


def plain_name(value, field: str, where, example: str = "capture_0000") -> str:
    """`value` checked to be one plain name (a capture's or an object's: it becomes part of output paths, file
    names and identities): a non-empty string of at most MAX_NAME characters, not '.' or '..', without '/', '\\',
    NUL or other control characters; UserError naming `where` and the field otherwise, with a name that would do
    (`example` when nothing of `value` is left)."""
    text = value if isinstance(value, str) else ""
    why = ("it is not a string" if not isinstance(value, str) else "it is empty" if not value.strip() else
           f"it is longer than {MAX_NAME} characters" if len(value) > MAX_NAME else
           f"{value.strip()!r} is a path" if value.strip() in (".", "..") else
           "it holds '/' or '\\' (a path)" if "/" in value or "\\" in value else
           "it holds control characters" if any(ord(c) < 32 or ord(c) == 127 for c in value) else None)
    if why is None:
        return value
    suggestion = re.sub(r"[^A-Za-z0-9_-]+", "_", text).strip("_")[:MAX_NAME] or example
    shown = json_text(value)
    raise UserError(f"{where}: {field} {shown} is not a plain name: {why}; it becomes part of output paths and "
                    f"identities, so rename it, e.g. {suggestion!r}")


def json_text(value, limit: int = 60) -> str:
    """`value` as a short one-line JSON text (control characters escaped) for an error message."""
    text = json.dumps(value)
    return text if len(text) <= limit else text[:limit] + "..."
