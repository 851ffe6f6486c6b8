"""The containers librealsense records into, read without librealsense (`annotator.bag` reads its topics from them;
docs/annotator.md, "RealSense recordings").

- ROS1 bag v2.0 (`.bag`, librealsense up to 2.57): `rosbags.rosbag1`; chunks LZ4 (the recorder's compression),
  uncompressed, or bz2 (after `rosbag compress`). Messages are decoded with the definitions the bag stores.
- ROS2 SQLite database (`.db3`, librealsense 2.58 on, which writes no metadata.yaml beside it): read with Python's
  `sqlite3` (tables `topics` and `messages`), each message's CDR bytes zstd-decompressed where the recorder
  compressed them (2.58's "message" compression: each blob a zstd frame).
- ROS2 bag directory (metadata.yaml with its .db3 or .mcap files, e.g. after `ros2 bag reindex` or a conversion):
  `rosbags.rosbag2`.

ROS2 messages are decoded with the standard message definitions (rosbags' ROS2 Humble typestore). The container is
recognised from the file's first bytes, not its name (a .db3 renamed .bag is still read as what it is).
"""

from __future__ import annotations

import re
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any


ROS1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
ROS2_METADATA = "metadata.yaml"


class ContainerError(Exception):
    """A container that cannot be read (the message says why); `annotator.bag` names the file in a UserError."""


def _zstd_decompress(data: bytes) -> bytes:
    """One zstd frame decompressed (Python 3.14's module, else the backport rosbags installs)."""
    try:
        from compression import zstd  # Python 3.14
    except ImportError:
        from backports import zstd  # rosbags' own dependency
    return zstd.decompress(data)


def _ros2_store():
    """rosbags' typestore of the standard ROS2 messages (the types librealsense records)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


class Container:
    """A recording's messages by topic: `topics` {topic: msgtype ("sensor_msgs/msg/Image")}, `messages(topic)` its
    (time ns, raw bytes) in time order, `decode(topic, raw)` a message; `kind` says which container it is."""

    kind: str = ""
    ros2: bool = False
    topics: dict[str, str]

    def messages(self, topic: str, start: int | None = None, stop: int | None = None) -> Iterator[tuple[int, bytes]]:
        """(time ns, raw message) of `topic` with start <= time < stop, in time order."""
        raise NotImplementedError

    def times(self, topic: str) -> list[int]:
        """The times (ns) of `topic`'s messages, in order."""
        return [time for time, _ in self.messages(topic)]

    def decode(self, topic: str, raw: bytes):
        """The message `raw` of `topic`, deserialised (rosbags' message classes)."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the file."""

    def __enter__(self) -> Container:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Ros1Bag(Container):
    """A ROS1 bag v2.0 through `rosbags.rosbag1`."""

    def __init__(self, path: Path):
        from rosbags.rosbag1 import Reader

        self.reader = Reader(path)
        self.reader.open()
        self.connections = {c.topic: c for c in self.reader.connections}
        self.topics = {t: c.msgtype for t, c in self.connections.items()}
        self._stores: dict = {}
        names = {getattr(getattr(c, "decompressor", None), "__module__", "") or "" for c in
                 getattr(self.reader, "chunks", {}).values()}
        compression = sorted({"LZ4" if "lz4" in n else "bz2" if "bz2" in n else "uncompressed" for n in names})
        self.kind = f"ROS1 bag v2.0 ({', '.join(compression) or 'no'} chunks)"

    def messages(self, topic: str, start: int | None = None, stop: int | None = None) -> Iterator[tuple[int, bytes]]:
        for _, time, raw in self.reader.messages(connections=[self.connections[topic]], start=start, stop=stop):
            yield time, raw

    def decode(self, topic: str, raw: bytes):
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        connection = self.connections[topic]
        if topic not in self._stores:  # the definition the bag stores, as recorded
            store = get_typestore(Stores.EMPTY)
            store.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
            self._stores[topic] = store
        return self._stores[topic].deserialize_ros1(raw, connection.msgtype)

    def close(self) -> None:
        self.reader.close()


class Ros2Sqlite(Container):
    """A ROS2 SQLite database (.db3) read directly (no metadata.yaml needed), read-only."""

    ros2 = True

    def __init__(self, path: Path):
        self.db = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1", uri=True)
        try:
            rows = self.db.execute("SELECT id, name, type FROM topics").fetchall()
            self.db.execute("SELECT topic_id, timestamp, data FROM messages LIMIT 1").fetchall()
        except sqlite3.Error as exc:
            self.db.close()
            raise ContainerError(f"an SQLite database without a ROS2 bag's topics and messages tables ({exc})") \
                from None
        self.ids = {name: int(i) for i, name, _ in rows}
        self.topics = {name: str(kind) for _, name, kind in rows}
        first = self.db.execute("SELECT data FROM messages LIMIT 1").fetchone()
        self.compressed = first is not None and bytes(first[0][:4]) == ZSTD_MAGIC
        self.kind = "ROS2 SQLite database" + (" (zstd messages)" if self.compressed else "")
        self._store: Any = None

    def messages(self, topic: str, start: int | None = None, stop: int | None = None) -> Iterator[tuple[int, bytes]]:
        query, args = "SELECT timestamp, data FROM messages WHERE topic_id = ?", [self.ids[topic]]
        if start is not None:
            query, args = query + " AND timestamp >= ?", [*args, start]
        if stop is not None:
            query, args = query + " AND timestamp < ?", [*args, stop]
        for time, data in self.db.execute(query + " ORDER BY timestamp, id", args):
            data = bytes(data)
            yield int(time), _zstd_decompress(data) if data[:4] == ZSTD_MAGIC else data

    def times(self, topic: str) -> list[int]:
        return [int(t) for (t,) in self.db.execute("SELECT timestamp FROM messages WHERE topic_id = ? ORDER BY "
                                                   "timestamp, id", [self.ids[topic]])]

    def decode(self, topic: str, raw: bytes):
        if self._store is None:
            self._store = _ros2_store()
        return self._store.deserialize_cdr(raw, self.topics[topic])

    def close(self) -> None:
        self.db.close()


class Ros2Directory(Container):
    """A ROS2 bag directory (metadata.yaml; SQLite or MCAP storage) through `rosbags.rosbag2`."""

    ros2 = True

    def __init__(self, path: Path):
        from rosbags.rosbag2 import Reader

        self.reader = Reader(path)
        self.reader.open()
        self.connections = {c.topic: c for c in self.reader.connections}
        self.topics = {t: c.msgtype for t, c in self.connections.items()}
        found = re.search(r"storage_identifier:\s*['\"]?([\w.-]+)", (path / ROS2_METADATA).read_text(errors="replace"))
        self.kind = f"ROS2 bag directory ({found[1] if found else 'sqlite3'} storage)"
        self._store: Any = None

    def messages(self, topic: str, start: int | None = None, stop: int | None = None) -> Iterator[tuple[int, bytes]]:
        for _, time, raw in self.reader.messages(connections=[self.connections[topic]], start=start, stop=stop):
            yield time, bytes(raw)

    def decode(self, topic: str, raw: bytes):
        if self._store is None:
            self._store = _ros2_store()
        return self._store.deserialize_cdr(raw, self.topics[topic])

    def close(self) -> None:
        self.reader.close()


def sniff(path: Path) -> str:
    """Which container `path` is, from its first bytes (or a directory's metadata.yaml): "ros1", "ros2-sqlite",
    "ros2-directory", or a description of what it is not."""
    if path.is_dir():
        return "ros2-directory" if (path / ROS2_METADATA).is_file() else f"a directory without {ROS2_METADATA}"
    with path.open("rb") as handle:
        head = handle.read(16)
    if head.startswith(ROS1_MAGIC):
        return "ros1"
    if head.startswith(SQLITE_MAGIC):
        return "ros2-sqlite"
    if head.startswith(b"#ROSBAG V"):
        version = head[9:].split(b"\n")[0].decode(errors="replace")
        return f"a ROS1 bag of version {version!r} (not 2.0)"
    if head.startswith(b"\x89MCAP"):
        return f"a bare MCAP file (give its ROS2 bag directory, with {ROS2_METADATA})"
    return "neither a ROS1 bag v2.0, a ROS2 SQLite database nor a ROS2 bag directory"


def open_container(path: Path) -> Container:
    """The container of a recording (module docstring); UserError-ready ContainerError when it is none of them or is
    unreadable."""
    from rosbags.rosbag1 import ReaderError as Ros1Error
    from rosbags.rosbag2 import ReaderError as Ros2Error

    kind = sniff(path)
    try:
        if kind == "ros1":
            return Ros1Bag(path)
        if kind == "ros2-sqlite":
            return Ros2Sqlite(path)
        if kind == "ros2-directory":
            return Ros2Directory(path)
    except (Ros1Error, Ros2Error, sqlite3.Error, OSError, ValueError, KeyError) as exc:
        raise ContainerError(f"unreadable ({type(exc).__name__}: {exc})") from None
    raise ContainerError(f"is {kind}")


def key_values(text: str) -> dict[str, str]:
    """librealsense's ROS2 text messages: "key=value;key=value;..." -> {key: value} (values may hold '=' or ',')."""
    out = {}
    for part in str(text).split(";"):
        if "=" in part:
            key, value = part.split("=", 1)
            out[key.strip()] = value.strip()
    return out
