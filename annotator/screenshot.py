"""A picture of the annotator's windows as they are laid out on a screen, for the docs.

Run under a display of that size, e.g.
`xvfb-run -a -s "-screen 0 1600x1000x24" python -m annotator.screenshot CAPTURE docs/annotator-window.png`.
The capture must be simulated (its true poses place the objects); the annotation state goes to a temporary
folder, the capture is not changed. The picture is composed from the two windows' own images (open3d's) at their
layout positions (`annotator.layout`) on a dark desktop, with a title bar drawn above each; saved as a
palette PNG.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from dsr_bench.annotator.layout import parse_window_size
from dsr_bench.errors import UserError
from dsr_bench.geometry import pose_to_matrix


def _place(session) -> None:
    """Every object at its true step-0 pose (through the pick API); objects 1-2 snapped, 3 confirmed, the rest
    left initialised, so that the picture shows each status colour; object 1 selected."""
    truth = session.capture.truth_poses()
    if truth is None:
        raise UserError("the capture has no true poses (truth.json): give a simulated capture "
                        "(dsr-bench generate-captures --out caps -n 1)")
    for obj in range(session.num_objects):
        v, _ = session.capture.mesh(obj)
        m = pose_to_matrix(truth[0][obj])
        picks = v[np.linspace(0, len(v) - 1, 8).astype(int)]
        session.init_from_picks(obj, picks, picks @ m[:3, :3].T + m[:3, 3])
    for obj in range(min(3, session.num_objects)):
        session.snap(obj)
    if session.num_objects > 2:
        session.confirm(2)
    session.select(0)


def compose(desktop: tuple[int, int], windows: list[tuple[tuple[int, int], str, np.ndarray]],
            title_height: int = 24) -> np.ndarray:
    """(H, W, 3) uint8: a dark desktop (width, height px) with each window's image (H_i, W_i, 3) pasted at its
    top-left corner (x, y px) under a title bar of `title_height` px showing its title."""
    from PIL import Image, ImageDraw

    from dsr_bench.annotator.panel import _font

    canvas = Image.new("RGB", desktop, (58, 62, 70))
    draw = ImageDraw.Draw(canvas)
    font = _font(13)
    for (x, y), title, image in windows:
        h, w = image.shape[:2]
        draw.rectangle([x, y - title_height, x + w - 1, y - 1], fill=(30, 32, 38))
        draw.text((x + 8, y - title_height + 5), title, fill=(220, 220, 220), font=font)
        canvas.paste(Image.fromarray(np.asarray(image, np.uint8)), (x, y))
    return np.asarray(canvas)


def main(argv: list[str] | None = None) -> int:
    """Open the window on a capture, draw one frame, write the composed picture (temp name, then rename)."""
    from PIL import Image

    from dsr_bench.annotator import window as win
    from dsr_bench.annotator.session import Session

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("capture", type=Path, help="a simulated capture directory")
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("--screen", default="1600x1000", help="screen size WxH px (default 1600x1000)")
    parser.add_argument("--colors", type=int, default=256, help="palette size of the PNG (default 256)")
    args = parser.parse_args(argv)
    try:
        screen = parse_window_size(args.screen)
        with tempfile.TemporaryDirectory() as work:
            session = Session.open(args.capture, Path(work) / "annotation")
            _place(session)
            window = win.AnnotatorWindow(session, screen=screen, echo=lambda s: None)
            try:
                window.ctl.view.message = "snapped: rmse 1.4 mm, coverage 0.86 (example message)"
                window.refresh()
                for _ in range(3):
                    window.render()
                view, panel = window.screenshot(), window.panel_screenshot()
                lay = window.layout
            finally:
                window.close()
        image = compose(screen, [(lay.view[:2], "dsr-bench annotator: 3D (Esc quits)", view),
                                 (lay.panel[:2], "dsr-bench annotator: cameras and keys", panel)])
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_name(args.out.name + ".tmp.png")
        Image.fromarray(image).quantize(colors=args.colors, method=Image.Quantize.FASTOCTREE).save(tmp, optimize=True)
        os.replace(tmp, args.out)
    except UserError as exc:
        print(f"annotator.screenshot: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KiB, {screen[0]}x{screen[1]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
