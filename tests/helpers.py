"""Plain helpers shared by test modules (fixtures live in conftest.py)."""

import contextlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from dsr_bench.geometry import pose_to_matrix


def place_from_truth(session, truth, step: int = 0, snap: bool = True) -> None:
    """Initialise every object of an annotator Session at `step` from 4 picked pairs on its true pose (as a
    user's picks would), then snap it (ICP) unless `snap` is False."""
    for i in range(session.num_objects):
        v, _ = session.capture.mesh(i)
        idx = np.linspace(0, len(v) - 1, 4).astype(int)
        m = pose_to_matrix(truth[step, i])
        session.init_from_picks(i, v[idx], v[idx] @ m[:3, :3].T + m[:3, 3])
        if snap:
            session.snap(i)


def stored_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every dataset stored in an HDF5 file, read whole, by path."""
    out: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def assert_same_dataset(got: Path, want: Path, sequences: int = 4) -> None:
    """Two generated datasets are the same: the same `sequences` files, every stored array equal (values and dtypes,
    NaN equal to NaN), the same manifest digests, split checksum and split file, and no temporary, lock or probe left
    anywhere in `got`."""
    from dsr_bench.dataset.manifest import load_manifest, split_digest

    names = sorted(p.name for p in want.glob("seq_*.h5"))
    assert len(names) == sequences and sorted(p.name for p in got.glob("seq_*.h5")) == names
    for name in names:
        a, b = stored_arrays(got / name), stored_arrays(want / name)
        assert sorted(a) == sorted(b), name
        for key in b:
            nan = b[key].dtype.kind in "fc"  # NaN (no depth) equals NaN
            assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key], equal_nan=nan), f"{name}:{key}"
    ma, mb = load_manifest(got), load_manifest(want)
    assert [(s["name"], s["content_sha256"]) for s in ma["sequences"]] == [
        (s["name"], s["content_sha256"]) for s in mb["sequences"]]
    assert split_digest(ma, "all") == split_digest(mb, "all")
    assert (got / "splits" / "all.txt").read_text() == (want / "splits" / "all.txt").read_text()
    assert sorted(str(p.relative_to(got)) for p in got.rglob(".*")) == []


def pin_split(monkeypatch, data_dir: Path, split: str) -> dict:
    """Pin `split` of a (synthetic) dataset in this toolkit for the test: its real pin (`build_pin`: checksum, array
    fingerprints, the scored digests `evaluate` recomputes) stands in split_pins.json's place; returns the pin."""
    from dsr_bench.dataset import splits
    from dsr_bench.dataset.manifest import load_manifest, read_split
    from dsr_bench.dataset.pins import build_pin

    spec = splits.SPLITS[split]
    _, names = read_split(data_dir, split)
    pin = build_pin(data_dir, names, load_manifest(data_dir), split)
    pins = {**splits.pinned_digests(), split: pin}
    monkeypatch.setattr(splits, "pinned_digests", lambda: pins)
    monkeypatch.setitem(splits.SPLITS, split, splits.Split(**{**spec.__dict__, "pinned_checksum": pin["checksum"]}))
    return pin


@contextlib.contextmanager
def virtual_display(screen: str = "1600x1200x24") -> Iterator[dict[str, str]]:
    """Start a private Xvfb server with one `screen` (WIDTHxHEIGHTxDEPTH) and yield os.environ with DISPLAY set to
    it; the server is stopped on exit. The server picks a free display number itself (-displayfd), so parallel
    test workers never race for one as `xvfb-run -a` can (two workers took the same number and a window opened
    on no display). Uses $DISPLAY as it is when Xvfb is not installed but a display is; otherwise skips."""
    import pytest

    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        if os.environ.get("DISPLAY"):
            yield dict(os.environ)
            return
        pytest.skip("no display: neither $DISPLAY nor Xvfb is available (install xvfb: scripts/setup.sh)")
    read_end, write_end = os.pipe()
    log = tempfile.TemporaryFile()  # a file, not a pipe: a chatty server never blocks on a full pipe
    server = subprocess.Popen([xvfb, "-displayfd", str(write_end), "-screen", "0", screen, "-nolisten", "tcp"],
                              pass_fds=(write_end,), stdout=subprocess.DEVNULL, stderr=log)
    os.close(write_end)
    try:
        with os.fdopen(read_end, "rb") as reader:
            number = reader.readline().strip()  # written once the server accepts connections; empty if it died
        if not number.isdigit():
            server.kill()
            server.wait()
            log.seek(0)
            raise RuntimeError(f"Xvfb did not start: {log.read().decode(errors='replace')[-1000:]}")
        env = {k: v for k, v in os.environ.items() if k not in ("XAUTHORITY", "WAYLAND_DISPLAY")}
        yield {**env, "DISPLAY": f":{number.decode()}"}
    finally:
        if server.poll() is None:
            server.terminate()
            try:
                server.wait(timeout=10)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()
        log.close()
