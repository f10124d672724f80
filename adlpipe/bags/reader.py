"""Streaming, format-agnostic bag reading: ROS2/ROS1 MCAP (mcap decoders), ROS1 .bag and ROS2 folders/.db3
(rosbags AnyReader). Every library failure becomes an AdlError naming the bag."""

from __future__ import annotations

import contextlib
import io
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from ..plumbing.errors import AdlError, NoDecoder
from .foxglove import AS_ROS, JsonDecoderFactory, SafeFactory, as_ros
from .messages import typestore
from .splits import recording_parts

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
COUNTS_METADATA = "adlpipe.message_counts"  # MCAP metadata record: topic -> message count, written first


@dataclass
class TopicInfo:
    msgtype: str
    declared: int | None  # the bag's own message count for the topic (None: the bag does not say)


def bag_kind(path: Path) -> str:
    if path.is_dir():
        if not (path / "metadata.yaml").exists():
            raise AdlError(f"{path}: folder is not a rosbag2 bag (no metadata.yaml)")
        return "rosbag2"
    if not path.exists():
        raise AdlError(f"{path}: no such file")
    if path.suffix == ".mcap":
        return "mcap"
    if path.suffix == ".bag":
        return "ros1"
    if path.suffix == ".db3":
        if not (path.parent / "metadata.yaml").exists():
            raise AdlError(f"{path}: a .db3 file needs the metadata.yaml of its rosbag2 folder beside it")
        return "rosbag2"
    if path.suffix in (".zstd", ".lz4") and Path(path.stem).suffix in (".mcap", ".db3"):  # rosbag2's file mode
        raise AdlError(f"{path}: a compressed rosbag2 split (the whole file {path.suffix[1:]}-compressed); give its "
                       "folder, with metadata.yaml, instead of the bare file")
    raise AdlError(f"{path}: unknown bag format (expected .mcap, .bag, .db3 or a rosbag2 folder)")


def _normalise_type(name: str) -> str:
    """'sensor_msgs/Image' (ROS1) and 'sensor_msgs/msg/Image' (ROS2) -> 'sensor_msgs/msg/Image'."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


class BagSource:
    """Opens a bag, lists its topics and streams decoded messages of chosen topics in log-time order."""

    def __init__(self, path: str | Path, recover: bool = False) -> None:
        self.path = Path(path)
        self.kind = bag_kind(self.path)
        # a ROS1 split recording (name_0.bag, name_1.bag, ...) is read as one, its parts merged in time order
        self.parts = recording_parts(self.path) if self.kind == "ros1" else [self.path]
        self.recover = recover
        self.lost_note = ""
        self._topics: dict[str, TopicInfo] | None = None
        self._damaged: bool | None = None

    # -- topics ----------------------------------------------------------------------------------------------
    def topics(self) -> dict[str, TopicInfo]:
        if self._topics is None:
            try:
                self._topics = self._mcap_topics() if self.kind == "mcap" else self._rosbags_topics()
            except AdlError:
                raise
            except Exception as exc:  # noqa: BLE001 - untrusted input: any library failure is a bad bag
                raise AdlError(f"{self.path}: unreadable {self.kind} bag ({type(exc).__name__}: {exc})") from exc
        return self._topics

    def _mcap_topics(self) -> dict[str, TopicInfo]:
        from mcap.reader import make_reader

        with open(self.path, "rb") as f:
            try:
                summary = make_reader(f).get_summary()
            except Exception as exc:  # noqa: BLE001
                if not self.recover:
                    raise AdlError(f"{self.path}: truncated or corrupt MCAP ({type(exc).__name__}: {exc}); "
                                   "re-run with --recover to keep the complete chunks") from exc
                summary = None
        if summary is None:
            if not self.recover:
                raise AdlError(f"{self.path}: MCAP has no summary section (truncated?); re-run with --recover")
            return self._scan_topics()
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        out = {}
        for cid, ch in summary.channels.items():
            schema = summary.schemas.get(ch.schema_id)
            out[ch.topic] = TopicInfo(_normalise_type(schema.name) if schema else "?", counts.get(cid))
        return out

    def _scan_topics(self) -> dict[str, TopicInfo]:
        """Recovery: topics of the complete records of a damaged MCAP (counts unknown, then counted)."""
        out: dict[str, TopicInfo] = {}
        for _schema, channel, _msg in self._stream_records():
            if channel.topic not in out:
                out[channel.topic] = TopicInfo("?", None)
        return out

    def _rosbags_topics(self) -> dict[str, TopicInfo]:
        with self._any_reader() as reader:
            out: dict[str, TopicInfo] = {}
            for c in reader.connections:
                prev = out.get(c.topic)
                n = (prev.declared or 0) + c.msgcount if prev else c.msgcount
                out[c.topic] = TopicInfo(_normalise_type(c.msgtype), n)
            return out

    def _any_reader(self):  # noqa: ANN202 - rosbags AnyReader
        from rosbags.highlevel import AnyReader

        paths = [self.path.parent] if self.path.suffix == ".db3" else self.parts
        store = typestore(1 if self.kind == "ros1" else 2)
        return AnyReader(paths, default_typestore=store)

    # -- messages --------------------------------------------------------------------------------------------
    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Callable[[], object]]]:
        """(topic, log_time_ns, decode) for the given topics, in log-time order. decode() returns the message;
        callers skip it for messages they do not need (the images after the first frame), which is most bytes."""
        try:
            if self.kind == "mcap":
                yield from self._mcap_messages(topics)
            else:
                yield from self._rosbags_messages(topics)
        except AdlError:
            raise
        except Exception as exc:  # noqa: BLE001 - untrusted input
            raise AdlError(f"{self.path}: unreadable {self.kind} bag while reading messages "
                           f"({type(exc).__name__}: {exc})") from exc

    def _guard(self, topic: str, decode: Callable[[], object]) -> Callable[[], object]:
        """A decode() whose library failures (a message that does not match its schema) are a bad bag."""

        def guarded() -> object:
            try:
                return decode()
            except AdlError:
                raise
            except Exception as exc:  # noqa: BLE001 - untrusted bytes
                raise AdlError(f"{self.path}: topic {topic}: message does not decode "
                               f"({type(exc).__name__}: {exc})") from exc

        return guarded

    def declared_in_metadata(self) -> dict[str, int] | None:
        """Per-topic counts an adlpipe recorder writes at the start of its MCAP files (readable even when the
        file's tail, with its summary, is lost)."""
        from mcap.records import Metadata

        for _schema, _channel, rec in self._stream_records(include_metadata=True):
            if isinstance(rec, Metadata) and rec.name == COUNTS_METADATA:
                try:
                    return {k: int(v) for k, v in rec.metadata.items()}
                except ValueError:
                    return None
        return None

    def _decoders(self) -> list:
        from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoder
        from mcap_ros1.decoder import DecoderFactory as Ros1Decoder
        from mcap_ros2.decoder import DecoderFactory as Ros2Decoder

        return [Ros2Decoder(), Ros1Decoder(), SafeFactory(ProtobufDecoder()), JsonDecoderFactory()]

    def _decode(self, schema, channel, message, cache: dict) -> object:  # noqa: ANN001
        key = channel.id
        if key not in cache:
            decoder = None
            for factory in self._decoders():
                # mcap_ros2's schema parser prints its own "Error with: ..." line; ours is the one that counts
                with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
                    decoder = factory.decoder_for(channel.message_encoding, schema)
                if decoder is not None:
                    break
            if decoder is None:
                name = schema.name if schema else "?"
                raise NoDecoder(f"{self.path}: topic {channel.topic}: no decoder for message type {name} "
                                f"(encoding {channel.message_encoding!r})", channel.message_encoding)
            if schema is not None and schema.name in AS_ROS:  # the Foxglove SDK's: read as the ROS message
                decoder = partial(lambda d, name, data: as_ros(name, d(data)), decoder, schema.name)
            cache[key] = decoder
        if message.data[:4] == ZSTD_MAGIC:  # rosbag2 'message' compression: each payload zstd-compressed
            raise AdlError(f"{self.path}: a compressed rosbag2 split (each message zstd-compressed); give its folder, "
                           "with metadata.yaml, instead of the bare .mcap file")
        return cache[key](message.data)

    def _mcap_messages(self, topics: list[str]) -> Iterator[tuple[str, int, object]]:
        cache: dict = {}
        if self.recover and self.damaged:
            wanted = set(topics)
            for schema, channel, message in self._stream_records():
                if channel.topic in wanted:
                    yield channel.topic, message.log_time, self._guard(channel.topic,
                                                                       partial(self._decode, schema, channel, message,
                                                                               cache))
            return
        from mcap.reader import make_reader

        with open(self.path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)  # a corrupted chunk is an error, not silent garbage
            for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                yield channel.topic, message.log_time, self._guard(channel.topic,
                                                                   partial(self._decode, schema, channel, message,
                                                                           cache))

    @property
    def damaged(self) -> bool:
        """An MCAP whose summary cannot be read (truncated or corrupt tail)."""
        if self.kind != "mcap":
            return False
        if self._damaged is None:
            from mcap.reader import make_reader

            try:
                with open(self.path, "rb") as f:
                    self._damaged = make_reader(f).get_summary() is None
            except Exception:  # noqa: BLE001
                self._damaged = True
        return self._damaged

    def _stream_records(self, include_metadata: bool = False) -> Iterator[tuple]:
        """Complete records of a damaged MCAP, read front to back; stops at the first broken one."""
        from mcap.records import Channel, Message, Metadata, Schema
        from mcap.stream_reader import StreamReader

        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        n_ok = 0
        with open(self.path, "rb") as f:
            records = StreamReader(f, skip_magic=False).records
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    break
                except (Exception, struct.error) as exc:  # noqa: BLE001 - the damaged tail
                    self.lost_note = (f"stopped at damaged data after {n_ok} complete messages "
                                      f"({type(exc).__name__}); the rest of the file is lost")
                    break
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif include_metadata and isinstance(rec, Metadata):
                    yield None, None, rec
                    return
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    n_ok += 1
                    ch = channels[rec.channel_id]
                    yield schemas.get(ch.schema_id), ch, rec

    def _rosbags_messages(self, topics: list[str]) -> Iterator[tuple[str, int, object]]:
        with self._any_reader() as reader:
            conns = [c for c in reader.connections if c.topic in set(topics)]
            for conn, t, raw in reader.messages(connections=conns):
                # Foxy-era metadata names types without /msg/ ('sensor_msgs/Image'): decode as the standard type
                msgtype = _normalise_type(conn.msgtype)
                yield conn.topic, t, self._guard(conn.topic, partial(reader.deserialize, raw, msgtype))
