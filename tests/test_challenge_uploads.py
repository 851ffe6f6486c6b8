"""Uploads that must be refused, with nothing half-stored: archives with absolute paths, '..', links, devices,
FIFOs, folders, repeated or foreign names, a compression bomb, a truncated or non-tar stream, a stream over the
size limit (declared or not), a stalled client, a client that hangs up mid-body, and a disk too full to hold one."""

import gzip
import random
import socket
import tarfile

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")
pytest.importorskip("argon2")

import httpx  # noqa: E402
from challenge_helpers import LiveServer, copy_challenge, member, post, tar_bytes, wait_until  # noqa: E402

LIMIT = 4 << 20


@pytest.fixture
def served(tmp_path, tmp_path_factory):
    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.layout import Layout
    from dsr_bench.challenge.server import Settings, create_app
    from dsr_bench.challenge.service import add_team

    root, predictions = copy_challenge(tmp_path_factory, tmp_path)
    layout = Layout(root)
    engine, sessions = open_database(layout.default_db_url())
    token = add_team(sessions, "uploader")
    settings = Settings(idle_timeout=1.0, keep_free=0, overrides={"max_upload_bytes": LIMIT,
                                                                  "max_extracted_bytes": 64 << 20, "max_ratio": 50.0})
    with LiveServer(create_app(root, settings=settings)) as live:
        yield live.url, token, layout, sessions, predictions
    engine.dispose()


def _nothing_stored(layout, sessions) -> None:
    """Nothing in uploads/ (once the server is done with the refused upload: waited for), nothing accepted."""
    from sqlalchemy import func, select

    from dsr_bench.challenge.db import Submission

    wait_until(lambda: not (layout.uploads.exists() and list(layout.uploads.iterdir())),
               "the refused upload's temporary removed")
    assert not (layout.submissions.exists() and list(layout.submissions.iterdir()))
    with sessions() as session:
        assert session.scalar(select(func.count()).select_from(Submission)) == 0


def _post(url, token, body, **kw):
    return post(f"{url}/api/submissions", params={"method": "m"}, content=body,
                headers={"Authorization": f"Bearer {token}"}, **kw)


H5 = b"\x89HDF\r\n\x1a\n" + b"\0" * 100


@pytest.mark.parametrize("archive,expected", [
    (tar_bytes([(member("/etc/seq_0000.h5"), H5)]), "absolute path"),
    (tar_bytes([(member("../seq_0000.h5"), H5)]), "'..'"),
    (tar_bytes([(member("seq_0000.h5", tarfile.SYMTYPE, "/work/secret_seed"), None)]), "a link"),
    (tar_bytes([(member("seq_0000.h5", tarfile.LNKTYPE, "secret_seed"), None)]), "a link"),
    (tar_bytes([(member("seq_0000.h5", tarfile.CHRTYPE), None)]), "a device or FIFO"),
    (tar_bytes([(member("seq_0000.h5", tarfile.FIFOTYPE), None)]), "a device or FIFO"),
    (tar_bytes([(member("sub", tarfile.DIRTYPE), None)]), "a directory"),
    (tar_bytes([(member("sub/seq_0000.h5"), H5)]), "not a plain file name"),
    (tar_bytes([(member("secret_seed"), b"1\n")]), "not a file of this challenge"),
    (tar_bytes([(member("seq_0000.h5"), H5), (member("seq_0000.h5"), H5)]), "appears twice"),
    (tar_bytes([(member("seq_0000.h5"), b"\0" * (40 << 20))], mode="w:gz"), "compression bomb"),
    (tar_bytes([(member("seq_0000.h5"), random.Random(0).randbytes(300_000))])[:100_000], "truncated or damaged"),
    (tar_bytes([(member("seq_0000.h5"), random.Random(0).randbytes(300_000))], mode="w:gz")[:100_000],
     "truncated or damaged"),
    (b"this is not an archive" * 100, "not a readable tar archive"),
], ids=["absolute", "dotdot", "symlink", "hardlink", "device", "fifo", "folder", "nested", "foreign", "twice", "bomb",
        "truncated", "truncated-gz", "not-tar"])
def test_hostile_archives_are_refused_and_nothing_is_stored(served, archive, expected):
    url, token, layout, sessions, _ = served
    reply = _post(url, token, archive)
    assert reply.status_code == 400, reply.text
    assert expected in reply.json()["detail"]
    _nothing_stored(layout, sessions)


def test_a_bomb_past_the_extracted_limit_is_refused_however_it_compresses(served):
    url, token, layout, sessions, _ = served
    zeros = tar_bytes([(member("seq_0000.h5"), b"\0" * (70 << 20))])
    reply = _post(url, token, gzip.compress(zeros, 9))
    assert reply.status_code == 400 and "compression bomb" in reply.json()["detail"]
    _nothing_stored(layout, sessions)


def test_streams_over_the_limit_are_cut_off(served):
    url, token, layout, sessions, _ = served

    def ten_times_the_limit():  # no Content-Length: the limit is enforced while the body streams
        for _ in range(40):
            yield b"\0" * (1 << 20)

    try:
        reply = _post(url, token, ten_times_the_limit())
        assert reply.status_code == 413 and "over the limit" in reply.json()["detail"]
    except httpx.TransportError:
        pass  # the server may close the connection while the client still sends: refused all the same
    declared = _post(url, token, b"\0" * (LIMIT + 1))
    assert declared.status_code == 413
    _nothing_stored(layout, sessions)


def test_a_stalled_client_is_dropped(served):
    url, token, layout, sessions, _ = served

    def stalls():
        yield b"\0" * 1000
        seen = []  # stalled past the server's idle timeout of 1 s: until it has dropped the upload's temporary

        def dropped() -> bool:
            parts = list(layout.uploads.glob(".part-*"))
            seen.extend(parts)
            return bool(seen) and not parts

        wait_until(dropped, "the server dropping the stalled upload", interval=0.02)
        yield b"\0" * 1000

    try:
        reply = _post(url, token, stalls())
        assert reply.status_code == 408
    except httpx.TransportError:
        pass
    _nothing_stored(layout, sessions)


def test_a_client_hanging_up_mid_body_leaves_nothing(served):
    url, token, layout, sessions, _ = served
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port))) as s:
        s.sendall(f"POST /api/submissions?method=m HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                  "Content-Type: application/x-tar\r\nContent-Length: 1000000\r\n\r\n".encode() + b"\0" * 5000)
        wait_until(lambda: list(layout.uploads.glob(".part-*")), "the server receiving the upload")  # then hang up
    _nothing_stored(layout, sessions)


def test_a_multipart_form_upload_is_streamed_and_accepted(served, tmp_path):
    from dsr_bench.challenge.client import pack

    url, token, layout, sessions, predictions = served
    pack(predictions, tmp_path / "p.tar")
    form = {"archive": ("p.tar", (tmp_path / "p.tar").read_bytes(), "application/x-tar")}
    reply = post(f"{url}/api/submissions", params={"method": "form"},
                 headers={"Authorization": f"Bearer {token}"}, files=form)
    assert reply.status_code == 202, reply.text
    stored = layout.archive(reply.json()["id"])
    assert stored.read_bytes() == (tmp_path / "p.tar").read_bytes()
    assert not list(layout.uploads.glob(".part-*"))


def test_the_disk_check_reserves_the_uploads_declared_length_not_the_limit(tmp_path, tmp_path_factory):
    """A host's limit far above the free disk (here 1 PiB): an upload is accepted when the disk holds its declared
    length and the margin kept, and one streamed without a length when the margin is free (then checked while it is
    written); a margin beyond the free disk refuses both (507, one line) before the body is read. Before, every
    upload needed the whole limit free beside the margin, so a server with less refused every submission."""
    import shutil

    from dsr_bench.challenge.client import pack
    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.layout import Layout
    from dsr_bench.challenge.server import Settings, create_app
    from dsr_bench.challenge.service import add_team

    root, predictions = copy_challenge(tmp_path_factory, tmp_path)
    layout = Layout(root)
    engine, sessions = open_database(layout.default_db_url())
    token = add_team(sessions, "uploader")
    pack(predictions, tmp_path / "p.tar")
    archive = (tmp_path / "p.tar").read_bytes()

    def streamed():  # no Content-Length: the server cannot know how much disk it will take
        yield archive

    try:
        full = Settings(keep_free=shutil.disk_usage(root).free + (1 << 40), auth_max_delay=0.01)
        with LiveServer(create_app(root, settings=full)) as live:
            for body in (archive, streamed()):
                refused = _post(live.url, token, body)
                assert refused.status_code == 507
                assert refused.json()["detail"] == "the server's disk is full; try again later (the host is told)"
                _nothing_stored(layout, sessions)
        roomy = Settings(keep_free=16 << 20, auth_max_delay=0.01, overrides={"max_upload_bytes": 1 << 50})
        with LiveServer(create_app(root, settings=roomy)) as live:
            for body in (archive, streamed()):
                accepted = _post(live.url, token, body)
                assert accepted.status_code == 202, accepted.text
                assert layout.archive(accepted.json()["id"]).read_bytes() == archive
    finally:
        engine.dispose()


def test_an_upload_that_fills_the_disk_while_it_streams_is_refused_and_removed(tmp_path, monkeypatch):
    """The free disk checked while an upload is written (other uploads and the scores fill it too): once it falls
    under the margin kept the upload is refused (507) and its temporary removed."""
    import asyncio
    import shutil

    from dsr_bench.challenge import storage

    real, checks = shutil.disk_usage, []

    def disk_usage(path):  # the first check finds room, the second a full disk
        checks.append(path)
        return real(path)._replace(free=(1 << 30) if len(checks) == 1 else 1 << 20)

    monkeypatch.setattr(storage.shutil, "disk_usage", disk_usage)
    sent: list[int] = []

    async def chunks(n: int):
        for _ in range(n):
            sent.append(1)
            yield b"\0" * (1 << 20)

    with pytest.raises(storage.UploadRefused) as refused:
        asyncio.run(storage.receive(chunks(64), tmp_path, limit=1 << 30, keep_free=64 << 20))
    assert refused.value.status == 507 and "disk is full" in refused.value.message
    assert checks == [tmp_path, tmp_path] and len(sent) << 20 == 2 * storage.DISK_CHECK_BYTES  # cut at the 2nd
    assert not list(tmp_path.iterdir())
    checks.clear()
    received = asyncio.run(storage.receive(chunks(40), tmp_path, limit=1 << 30, keep_free=0))  # no margin asked
    assert received.size == 40 << 20 and checks == []
