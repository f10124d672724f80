"""One writing interface over the three bag formats; each format is written with its own real writer."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer

from ..plumbing.atomic import temp_name
from .messages import MessageFactory

FORMATS = {"mcap": ".mcap", "bag": ".bag", "db3": ""}  # db3: a rosbag2 folder holding <name>.db3 + metadata.yaml


class BagWriter:
    """Writes messages to `path` via a temp path renamed into place on close (no half-written bags)."""

    def __init__(self, path: Path, fmt: str) -> None:
        if fmt not in FORMATS:
            raise ValueError(f"unknown bag format {fmt!r}; use one of {sorted(FORMATS)}")
        self.path, self.fmt = Path(path), fmt
        self.msgs = MessageFactory(1 if fmt == "bag" else 2)
        self.tmp = temp_name(self.path)
        self.remove(self.tmp)
        self._channels: dict[str, object] = {}
        if fmt == "mcap":
            self._file = open(self.tmp, "wb")
            # 256 KiB chunks: a truncated file loses at most one chunk of messages (see ingest --recover)
            self._w = McapWriter(self._file, compression=CompressionType.ZSTD, chunk_size=256 * 1024)
            self._w.start(profile="ros2", library="adlpipe")
            self._seq = 0
        elif fmt == "bag":
            self._w = Ros1Writer(self.tmp)
            self._w.open()
        else:
            self._w = Ros2Writer(self.tmp, version=9, storage_plugin=StoragePlugin.SQLITE3)
            self._w.open()

    @staticmethod
    def remove(p: Path) -> None:
        """A bag file, or a rosbag2 folder."""
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()

    def _channel(self, topic: str, msgtype: str) -> object:
        if topic not in self._channels:
            if self.fmt == "mcap":
                schema = self._w.register_schema(name=msgtype, encoding="ros2msg",
                                                 data=self.msgs.msgdef(msgtype).encode())
                self._channels[topic] = self._w.register_channel(topic=topic, message_encoding="cdr",
                                                                 schema_id=schema)
            else:
                self._channels[topic] = self._w.add_connection(topic, msgtype, typestore=self.msgs.store)
        return self._channels[topic]

    def declare_counts(self, counts: dict[str, int]) -> None:
        """MCAP: record the per-topic message counts up front, so a truncated file still says what it held."""
        if self.fmt == "mcap":
            from .reader import COUNTS_METADATA

            self._w.add_metadata(COUNTS_METADATA, {k: str(v) for k, v in counts.items()})

    def write(self, topic: str, msgtype: str, t_ns: int, msg: object) -> None:
        ch = self._channel(topic, msgtype)
        data = self.msgs.serialize(msg, msgtype)
        if self.fmt == "mcap":
            self._seq += 1
            self._w.add_message(ch, log_time=t_ns, data=data, publish_time=t_ns, sequence=self._seq)
        else:
            self._w.write(ch, t_ns, data)

    def close(self) -> Path:
        if self.fmt == "mcap":
            self._w.finish()
            self._file.close()
        else:
            self._w.close()
        if self.fmt == "db3":  # rosbags names the storage file after the folder: keep names consistent
            inner = self.tmp / f"{self.tmp.name}.db3"
            if inner.exists():
                inner.rename(self.tmp / f"{self.path.name}.db3")
                meta = self.tmp / "metadata.yaml"
                meta.write_text(meta.read_text().replace(f"{self.tmp.name}.db3", f"{self.path.name}.db3"))
        self.remove(self.path)
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        try:
            self.close_quietly()
        finally:
            self.remove(self.tmp)

    def close_quietly(self) -> None:
        try:
            if self.fmt == "mcap":
                self._file.close()
            else:
                self._w.close()
        except Exception:  # noqa: BLE001 - best effort on an already failing write
            pass
