"""Whether a native window can open here: the one check shared by `dsr-bench view`, `dsr-bench annotate` and the
annotator's window (only the standard library, outside `dsr_bench.cli` so that importing it does not assemble the
CLI)."""

from __future__ import annotations

import os
import sys


def no_display() -> bool:
    """True on a Linux machine without an X11 or Wayland display (DISPLAY and WAYLAND_DISPLAY unset or empty),
    where a native window cannot open."""
    return sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
