"""Screenshots of the leaderboard page and of evaluate's per-step plot as headless Chromium draws them, for the docs.

    python scripts/page_screenshots.py --steps-plot RESULTS-steps.png [--out docs] [--board leaderboard]

Drives Chromium over its DevTools pipe with the test suite's driver (tests/test_leaderboard.py), at a 1180 x 1000
CSS-pixel window: the page's top (docs/leaderboard-page.png), the figures of the cpu-novel-test 3D table and of the
plan-novel-test planning table as the page shows them (leaderboard-page-3d-figure.png,
leaderboard-page-planning.png), and the evaluate plot opened in the browser (evaluate-plot.png, the window's black
margins cut). Exits 2 with one line when Chromium or a file is missing.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = {"cpu-novel-test-3d-reproduced": "leaderboard-page-3d-figure.png",
            "plan-novel-test-planning-reproduced": "leaderboard-page-planning.png"}


def _small(image):
    """A screenshot of text and few colours in a 200-colour palette (a third of the bytes; the figures' crops keep
    every colour: a thin line of a rare colour would be lost)."""
    from PIL import Image

    return image.convert("RGB").quantize(colors=200, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps-plot", type=Path, required=True, help="a results-steps.png of `dsr-bench evaluate`")
    parser.add_argument("--out", type=Path, default=ROOT / "docs", help="where the screenshots go (default docs/)")
    parser.add_argument("--board", type=Path, default=ROOT / "leaderboard", help="the built leaderboard directory")
    args = parser.parse_args(argv)
    binary = shutil.which("chromium") or shutil.which("chromium-browser")
    if binary is None:
        sys.exit("error: no chromium binary on PATH; apt-get install chromium (or run scripts/setup.sh as root)")
    for path in (args.steps_plot, args.board / "index.html"):
        if not path.is_file():
            sys.exit(f"error: {path}: no such file; run `dsr-bench evaluate --out` / `dsr-bench leaderboard build`")
    import numpy as np

    sys.path.insert(0, str(ROOT / "tests"))
    from test_leaderboard import _Chromium

    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        browser = _Chromium(binary, Path(tmp) / "profile", width=1180, height=1000)
        try:
            browser.load((args.board / "index.html").resolve().as_uri())
            _small(browser.screenshot()).save(args.out / "leaderboard-page.png", optimize=True)
            for anchor, name in SECTIONS.items():  # the section's figure, scrolled to the top of the window
                box = browser.js(
                    f"(() => {{let e = document.getElementById('{anchor}'); while (e && e.tagName !== 'FIGURE') "
                    "e = e.nextElementSibling; e.scrollIntoView(); const r = e.getBoundingClientRect();"
                    "return [r.left, r.top, r.right, Math.min(r.bottom, innerHeight)];})()")
                browser.screenshot().crop(tuple(max(0, round(v)) for v in box)).save(args.out / name, optimize=True)
            browser.load(args.steps_plot.resolve().as_uri())
            shot = browser.screenshot()
            rows = np.where(np.asarray(shot).mean(axis=(1, 2)) > 40)[0]  # the image, not the viewer's black margin
            _small(shot.crop((0, int(rows[0]), shot.width, int(rows[-1]) + 1))).save(args.out / "evaluate-plot.png",
                                                                                    optimize=True)
        finally:
            browser.close()
    print(f"wrote {len(SECTIONS) + 2} screenshots to {args.out}")


if __name__ == "__main__":
    main()
