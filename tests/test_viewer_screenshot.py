"""`dsr-bench view`, as a person sees it: the real rerun viewer renders a recording off-screen (Xvfb, and wgpu on
Mesa's lavapipe, a CPU Vulkan driver) and writes a screenshot, which must show the scene and the comparison of
prediction and truth in their colours. Skips, saying which, where Xvfb, Mesa's Vulkan driver or rerun is missing
(Debian: `apt-get install xvfb mesa-vulkan-drivers`)."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun")
Image = pytest.importorskip("PIL.Image")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.dataset.sequence import SequenceReader  # noqa: E402
from dsr_bench.scoring.predictions import write_predictions  # noqa: E402
from dsr_bench.testing import write_synthetic_sequence  # noqa: E402
from dsr_bench.viewer import COMPARE_COLORS  # noqa: E402
from helpers import virtual_display  # noqa: E402

LAVAPIPE = Path("/usr/share/vulkan/icd.d/lvp_icd.x86_64.json")
WINDOW = (1400, 900)


def _tools() -> str:
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb is not installed (Debian: apt-get install xvfb)")
    if not LAVAPIPE.is_file():
        pytest.skip(f"Mesa's lavapipe Vulkan driver is not installed ({LAVAPIPE}; Debian: mesa-vulkan-drivers)")
    local = Path(sys.executable).parent / "rerun"
    rerun = str(local) if local.exists() else shutil.which("rerun")
    if rerun is None:
        pytest.skip("the rerun command-line tool is not installed")
    return rerun


def screenshot(rrd: Path, png: Path, timeout: float = 240.0) -> subprocess.CompletedProcess:
    """Render `rrd` in the native rerun viewer on a virtual display (1400x900 window) and save it as `png`."""
    rerun = _tools()
    cmd = [rerun, str(rrd), "--window-size", f"{WINDOW[0]}x{WINDOW[1]}", "--screenshot-to", str(png)]
    with virtual_display("1600x1200x24") as display_env:
        env = {**display_env, "VK_ICD_FILENAMES": str(LAVAPIPE)}
        return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)


def _near(pixels: np.ndarray, color: tuple[int, int, int], tol: int = 40) -> int:
    """How many pixels (H, W, 3) lie within `tol` of `color` in every channel."""
    return int((np.abs(pixels.astype(int) - np.array(color)).max(-1) < tol).sum())


@pytest.mark.slow
def test_screenshot_shows_the_scene_and_prediction_against_truth(tmp_path):
    _tools()
    seq = write_synthetic_sequence(tmp_path / "data" / "seq_0001.h5", 2, 2, seed=3)
    with SequenceReader(seq) as reader:
        gt, flow = reader.read("mask_3d")[:2], reader.read("scene_flow_3d")
    mask = np.roll(gt, 3, axis=2)  # every object predicted 12 mm too high: extra on top (red), missed below (blue)
    write_predictions(tmp_path / "pred" / "seq_0001.h5", mask, np.zeros_like(flow), num_slots=2)
    rrd, png = tmp_path / "x.rrd", tmp_path / "shot.png"
    assert main(["view", "seq_0001", "--data", str(tmp_path / "data"), "--predictions", str(tmp_path / "pred"),
                 "--save", str(rrd)]) == 0
    result = screenshot(rrd, png)
    assert result.returncode == 0 and png.is_file(), result.stderr[-2000:]
    pixels = np.asarray(Image.open(png).convert("RGB"))
    assert pixels.shape[1] >= WINDOW[0] and pixels.shape[0] >= WINDOW[1]  # (HiDPI: a multiple of the window)
    assert pixels.std() > 20 and len(np.unique(pixels.reshape(-1, 3), axis=0)) > 200, "a blank screenshot"
    h, w = pixels.shape[:2]
    # the 3D views on the left (3/5 of the width): ground truth above, prediction against truth below
    truth, compare = pixels[: h // 2, : w * 3 // 5], pixels[h // 2:, : w * 3 // 5]
    assert _near(compare, COMPARE_COLORS["only_predicted"], 20) > 500  # the extra voxels, red, large enough to see
    assert _near(compare, COMPARE_COLORS["only_true"], 20) > 500  # the missed ones, blue
    assert _near(truth, COMPARE_COLORS["only_true"], 20) < 50  # the comparison stays in its own view
    assert (truth.max(-1) > 90).mean() > 0.05  # the scene fills part of its view (framed, not far away)
