"""The screenshots of docs/annotator.md's "A first annotation": the annotator's windows at each step of a newcomer's
first annotation of a simulated capture, as a 1366 x 768 screen shows them.

    dsr-bench generate-captures --out captures -n 1
    xvfb-run -a -s "-screen 0 1366x768x24" python scripts/annotator_screenshots.py captures/seq_0000 docs/images \
        --work captures/seq_0000/annotation

The person's clicks are scripted from the capture's true poses (picks on the wrong blob first, then on the right
ones), and they do what the panel's "next:" line says; the annotation state goes to a temporary folder unless
`--work` names one (the capture's own, as above, makes the export command the window shows the plain one). Each
picture is composed from the two windows' own images at their layout positions (`annotator.screenshot.compose`),
saved as a palette PNG.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: The screen the pictures show (width, height px) and the palette size of the PNGs.
SCREEN = (1366, 768)
COLOURS = 128


class Clicks:
    """A pick window's clicks: the shown points nearest the wanted cloud points, then the mesh samples nearest the
    wanted mesh points."""

    def __init__(self):
        self.pairs: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, points, colors, title, mesh):
        from scipy.spatial import cKDTree

        assert self.pairs is not None
        return cKDTree(points).query(self.pairs[1] if mesh is None else self.pairs[0])[1]


def pairs(session, obj: int, onto: int) -> tuple[np.ndarray, np.ndarray]:
    """(mesh points of object `obj`, cloud points clicked for them): at its true pose, or centred on object
    `onto`'s true centre (a click on the wrong blob)."""
    from dsr_bench.geometry import pose_to_matrix

    truth = session.capture.truth_poses()[session.step]
    v, _ = session.capture.mesh(obj)
    m = pose_to_matrix(truth[obj])
    pick = v[np.unique([np.argmin(v[:, 0]), np.argmax(v[:, 0]), np.argmin(v[:, 1]), np.argmax(v[:, 1]),
                        np.argmax(v[:, 2])])]
    cloud = pick @ m[:3, :3].T + m[:3, 3]
    if onto != obj:
        w, _ = session.capture.mesh(onto)
        n = pose_to_matrix(truth[onto])
        cloud += (n[:3, :3] @ (0.5 * (w.min(0) + w.max(0))) + n[:3, 3]) - (m[:3, :3] @ (0.5 * (v.min(0) + v.max(0)))
                                                                         + m[:3, 3])
    return pick, cloud


def save(window, path: Path) -> None:
    """The windows as the screen shows them, composed, to `path` (a palette PNG)."""
    from PIL import Image

    from dsr_bench.annotator.screenshot import compose

    for _ in range(2):
        window.render()
    lay = window.layout
    image = compose(SCREEN, [(lay.view[:2], "dsr-bench annotator: 3D (Esc quits)", window.screenshot()),
                             (lay.panel[:2], "dsr-bench annotator: cameras and keys", window.panel_screenshot())])
    Image.fromarray(image).quantize(colors=COLOURS, method=Image.Quantize.FASTOCTREE).save(path, optimize=True)
    print(f"wrote {path} ({path.stat().st_size // 1024} KiB): {window.ctl.view.message} / {window.ctl.view.hint}")


def main() -> int:
    from dsr_bench.annotator import window as win
    from dsr_bench.annotator.session import Session

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("capture", type=Path, help="a simulated capture (dsr-bench generate-captures)")
    parser.add_argument("out", type=Path, help="the folder of the pictures (docs/images)")
    parser.add_argument("--work", type=Path, default=None, help="the annotation's work directory (default: a "
                                                                 "temporary one; it must hold no annotation yet)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        session = Session.open(args.capture, args.work or Path(work) / "annotation")
        clicks = Clicks()
        window = win.AnnotatorWindow(session, screen=SCREEN, picker=clicks, echo=lambda text: None)
        try:
            save(window, args.out / "annotator-1-fresh.png")
            wrong = 2 if session.num_objects > 2 else 1
            clicks.pairs = pairs(session, 0, wrong)
            window.press("M")
            save(window, args.out / "annotator-2-wrong-object.png")
            while session.status()[0] != "unset":
                window.press("Z")
            clicks.pairs = pairs(session, 0, 0)
            window.press("M")
            window.press("Space")
            save(window, args.out / "annotator-3-first-fit.png")
            for obj in range(1, session.num_objects):
                window.press(str(obj + 1))
                clicks.pairs = pairs(session, obj, obj)
                window.press("M")
                window.press("Space")
            window.press("1")
            window.press("R")  # the residual colours of step 0, every object placed
            save(window, args.out / "annotator-4-step-done.png")
            window.press("R")
            for _ in range(session.num_steps):  # N, then what the "next:" line asks of each object left unchecked:
                window.press("N")              # snap it; if it stays off its points, place it again (M, Space);
                for obj, status in enumerate(session.status()):  # else confirm it (Enter)
                    if status in ("snapped", "confirmed"):
                        continue
                    window.press(str(obj + 1))
                    window.press("Space")
                    if session.status()[obj] != "snapped":
                        clicks.pairs = pairs(session, obj, obj)
                        window.press("M")
                        window.press("Space")
                    if session.status()[obj] != "snapped":
                        window.press("Enter")
            save(window, args.out / "annotator-5-all-done.png")
        finally:
            window.close()
            session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
