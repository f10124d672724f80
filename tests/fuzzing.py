"""Mutated-bag fuzzing of the ingest, shared by tests/test_robustness.py (a few hundred cases in CI) and
bench/fuzz_ingest.py (thousands). A case passes when ingest either succeeds or raises AdlError (one clear line),
within a time limit, and leaves no partial output or temp file."""

from __future__ import annotations

import shutil
import signal
import struct
import tempfile
import traceback
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from adlpipe.bags.topics import TopicMap
from adlpipe.dataset import schema
from adlpipe.ingest import ingest
from adlpipe.plumbing.errors import AdlError

MUTATIONS = ["truncate", "flip", "length", "zero", "duplicate", "splice"]
# Structure-aware mutations: they change what a parser trusts (schema text, summary counts, declared lengths,
# headers, database pages, names) and leave the rest of the file valid, so they reach deeper than random bytes.
STRUCTURED = {
    "mcap": ["schema_text", "summary_counts", "array_length", "nul_name"],
    "bag": ["ros1_header", "array_length", "nul_name"],
    "db3": ["sqlite_page", "sqlite_types", "nul_name"],
}


@dataclass
class Outcome:
    ok: bool  # the case passed (ingested or a clean AdlError)
    kind: str  # "ingested", "error", or what went wrong
    detail: str = ""


def mutate(data: bytes, mutation: str, rng: np.random.Generator) -> bytes:
    b = bytearray(data)
    n = len(b)
    if mutation == "truncate":
        return bytes(b[: int(rng.integers(0, n))])
    if mutation == "flip":
        for pos in rng.integers(0, n, size=int(rng.integers(1, 16))):
            b[pos] ^= 1 << int(rng.integers(0, 8))
        return bytes(b)
    if mutation == "length":  # a huge or wrong little-endian length/size field somewhere
        pos = int(rng.integers(0, max(1, n - 8)))
        value = int(rng.choice([0, 1, 2**31 - 1, 2**32 - 1, 2**63 - 1, int(rng.integers(0, 2**40))]))
        b[pos:pos + 8] = struct.pack("<Q", value)[: len(b[pos:pos + 8])]
        return bytes(b)
    if mutation == "zero":
        pos = int(rng.integers(0, n))
        b[pos:pos + int(rng.integers(1, 4096))] = bytes(len(b[pos:pos + int(rng.integers(1, 4096))]))
        return bytes(b[:n])
    if mutation == "duplicate":
        pos, ln = int(rng.integers(0, n)), int(rng.integers(1, 2048))
        return bytes(b[:pos] + b[pos:pos + ln] + b[pos:])
    pos, ln = int(rng.integers(0, n)), int(rng.integers(1, 512))  # splice random bytes in
    return bytes(b[:pos] + bytes(rng.integers(0, 256, size=ln, dtype=np.uint8)) + b[pos + ln:])


def _rewrite_mcap(data: bytes, rng: np.random.Generator, edit_schema: bool = False,
                  edit_payload: object = None) -> bytes:
    """Read an MCAP's records and write them again with the real writer (uncompressed), editing on the way."""
    import io

    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.NONE)
    w.start(profile="ros2", library="adlpipe-fuzz")
    schema_ids, channel_ids = {}, {}
    victim = int(rng.integers(0, max(1, len(summary.schemas))))
    for i, (sid, sc) in enumerate(sorted(summary.schemas.items())):
        text = sc.data
        if edit_schema and i == victim:
            text = _edit_schema_text(text, rng)
        schema_ids[sid] = w.register_schema(sc.name, sc.encoding, text)
    for cid, ch in sorted(summary.channels.items()):
        channel_ids[cid] = w.register_channel(ch.topic, ch.message_encoding, schema_ids.get(ch.schema_id, 0))
    for _schema, channel, message in reader.iter_messages():
        payload = message.data
        if edit_payload is not None:
            payload = edit_payload(payload, rng)
        w.add_message(channel_ids[channel.id], message.log_time, payload, message.publish_time, message.sequence)
    w.finish()
    return out.getvalue()


def _edit_schema_text(text: bytes, rng: np.random.Generator) -> bytes:
    """Drop, retype or rename a field of a message definition."""
    lines = text.split(b"\n")
    fields = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith((b"#", b"=", b"MSG:"))
              and b" " in ln.strip()]
    if not fields:
        return text + b"\nint32 extra"
    i = int(rng.choice(fields))
    how = int(rng.integers(0, 4))
    typ, _, name = lines[i].strip().partition(b" ")
    if how == 0:
        del lines[i]
    elif how == 1:
        lines[i] = rng.choice([b"string", b"uint8[]", b"float64", b"int64[]"]) + b" " + name
    elif how == 2:
        lines[i] = typ + b" renamed_" + name
    else:
        lines.insert(i, b"uint32 inserted_field")
    return b"\n".join(lines)


def _patch_summary_counts(data: bytes, rng: np.random.Generator) -> bytes:
    """Change a message count in the MCAP summary's Statistics record (and clear the summary CRC, so the lie is
    read rather than caught by the checksum)."""
    b = bytearray(data)
    footer = len(b) - 8 - 29  # opcode, length, summary_start, summary_offset_start, summary_crc; then magic
    summary_start = struct.unpack_from("<Q", b, footer + 9)[0]
    struct.pack_into("<I", b, footer + 25, 0)
    pos = summary_start
    while 0 < pos < footer:
        op, ln = b[pos], struct.unpack_from("<Q", b, pos + 1)[0]
        if op == 0x0B:  # Statistics: message_count u64 ... channel_message_counts map<u16, u64>
            content = pos + 9
            maplen_at = content + 8 + 2 + 4 * 4 + 16
            entries = struct.unpack_from("<I", b, maplen_at)[0] // 10
            value = int(rng.choice([0, 1, 2**32, 2**63 - 1, int(rng.integers(0, 1000))]))
            if entries and rng.random() < 0.7:
                k = int(rng.integers(0, entries))
                struct.pack_into("<Q", b, maplen_at + 4 + 10 * k + 2, value)
            else:
                struct.pack_into("<Q", b, content, value)
            break
        pos += 9 + ln
    return bytes(b)


def _array_length(payload: bytes, rng: np.random.Generator) -> bytes:
    """Overwrite a 4-byte little-endian value that looks like a sequence/string length with a wrong one."""
    b = bytearray(payload)
    cands = [i for i in range(4, len(b) - 4, 4)
             if 0 < struct.unpack_from("<I", b, i)[0] <= len(b) - i - 4][:64]
    if not cands or rng.random() < 0.5:  # most payloads: leave them; the bag stays readable around the edit
        return payload
    i = int(rng.choice(cands))
    struct.pack_into("<I", b, i, int(rng.choice([0, 2**31 - 1, 2**32 - 1, int(rng.integers(0, 1 << 20))])))
    return bytes(b)


def _nul_name(data: bytes, rng: np.random.Generator) -> bytes:
    """A NUL byte inside a frame, topic or joint name (same length: the file's structure stays valid)."""
    names = [b"base_link", b"ee_link", b"camera_color_optical_frame", b"joint1", b"manikin", b"finger_left"]
    hits = [(m, i) for m in names for i in _find_all(data, m)]
    if not hits:
        return data
    m, i = hits[int(rng.integers(0, len(hits)))]
    b = bytearray(data)
    b[i + int(rng.integers(1, len(m)))] = 0
    return bytes(b)


def _find_all(data: bytes, sub: bytes) -> list[int]:
    out, i = [], data.find(sub)
    while i >= 0 and len(out) < 200:
        out.append(i)
        i = data.find(sub, i + 1)
    return out


def _ros1_header(data: bytes, rng: np.random.Generator) -> bytes:
    """Edit a field of a ROS1 connection header: its type, md5sum, definition text or a field's length prefix."""
    b = bytearray(data)
    keys = [b"type=", b"md5sum=", b"message_definition=", b"topic=", b"latching="]
    hits = [(k, i) for k in keys for i in _find_all(data, k)]
    if not hits:
        return data
    k, i = hits[int(rng.integers(0, len(hits)))]
    how = int(rng.integers(0, 3))
    if how == 0 and i >= 4:  # the field's length prefix
        struct.pack_into("<I", b, i - 4, int(rng.choice([0, 3, 2**31 - 1, int(rng.integers(0, 4096))])))
    elif how == 1:  # its value: a few bytes replaced
        j = i + len(k)
        b[j:j + 4] = bytes(rng.integers(32, 127, size=len(b[j:j + 4]), dtype=np.uint8))
    else:  # the key itself
        b[i] = ord("x")
    return bytes(b)


def _sqlite_page(data: bytes, rng: np.random.Generator) -> bytes:
    """Zero, swap or corrupt the header of a page of the sqlite database."""
    page = struct.unpack_from(">H", data, 16)[0] if len(data) > 18 else 4096
    page = 65536 if page == 1 else page
    n = len(data) // page
    if n < 2:
        return data
    b = bytearray(data)
    p1, p2 = int(rng.integers(1, n)), int(rng.integers(1, n))
    how = int(rng.integers(0, 3))
    if how == 0:
        b[p1 * page:(p1 + 1) * page] = bytes(page)
    elif how == 1:
        a, c = bytes(b[p1 * page:(p1 + 1) * page]), bytes(b[p2 * page:(p2 + 1) * page])
        b[p1 * page:(p1 + 1) * page], b[p2 * page:(p2 + 1) * page] = c, a
    else:
        b[p1 * page] = int(rng.integers(0, 256))  # the b-tree page type byte
        struct.pack_into(">H", b, p1 * page + 3, int(rng.integers(0, 65536)))  # its cell count
    return bytes(b)


def _sqlite_types(db: Path, rng: np.random.Generator) -> None:
    """Rewrite the topics table: a type renamed, a serialization format changed, a topic name with a NUL."""
    import sqlite3

    con = sqlite3.connect(db)
    try:
        rows = con.execute("select id, name, type from topics").fetchall()
        i, name, typ = rows[int(rng.integers(0, len(rows)))]
        how = int(rng.integers(0, 3))
        if how == 0:
            con.execute("update topics set type=? where id=?", (typ.replace("msg/", "msgs/"), i))
        elif how == 1:
            con.execute("update topics set serialization_format=? where id=?", ("ros1", i))
        else:
            con.execute("update topics set name=? where id=?", (name[:2] + "\x00" + name[2:], i))
        con.commit()
    finally:
        con.close()


def structured_mutate(bag: Path, fmt: str, mutation: str, rng: np.random.Generator) -> None:
    """Apply one structure-aware mutation in place (bag: the .mcap/.bag file, or the rosbag2 folder)."""
    if fmt == "db3":
        db = next(bag.glob("*.db3"))
        if mutation == "sqlite_types":
            _sqlite_types(db, rng)
        elif mutation == "sqlite_page":
            db.write_bytes(_sqlite_page(db.read_bytes(), rng))
        else:
            db.write_bytes(_nul_name(db.read_bytes(), rng))
        return
    data = bag.read_bytes()
    if mutation == "schema_text":
        data = _rewrite_mcap(data, rng, edit_schema=True)
    elif mutation == "summary_counts":
        data = _patch_summary_counts(_rewrite_mcap(data, rng), rng)
    elif mutation == "array_length":
        data = _rewrite_mcap(data, rng, edit_payload=_array_length) if fmt == "mcap" else _ros1_array(data, rng)
    elif mutation == "nul_name":
        data = _nul_name(_rewrite_mcap(data, rng) if fmt == "mcap" else data, rng)
    elif mutation == "ros1_header":
        data = _ros1_header(data, rng)
    bag.write_bytes(data)


def _ros1_array(data: bytes, rng: np.random.Generator) -> bytes:
    """In an uncompressed ROS1 bag: overwrite a 4-byte length in a message record's data."""
    b = bytearray(data)
    for _ in range(8):
        i = int(rng.integers(0, max(1, len(b) - 8)))
        i -= i % 4
        v = struct.unpack_from("<I", b, i)[0]
        if 0 < v < len(b) - i:
            struct.pack_into("<I", b, i, int(rng.choice([0, 2**31 - 1, 2**32 - 1, v + int(rng.integers(1, 64))])))
            break
    return bytes(b)


class _Timeout(Exception):
    pass


def run_case(base: Path, mutation: str, seed: int, recover: bool = False, timeout_s: int = 20) -> Outcome:
    """Mutate one bag (file, or a rosbag2 folder's .db3) and ingest it in this process."""
    rng = np.random.default_rng(seed)
    fmt = "db3" if base.is_dir() else base.suffix.lstrip(".")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        bag = work / base.name
        if base.is_dir():
            shutil.copytree(base, bag)
        else:
            shutil.copy(base, bag)
        if mutation in STRUCTURED.get(fmt, []):
            try:
                structured_mutate(bag, fmt, mutation, rng)
            except Exception as exc:  # noqa: BLE001 - the mutator's own trouble is not the ingest's
                return Outcome(True, "not mutated", f"{type(exc).__name__}: {exc}")
        elif base.is_dir():
            db = next(bag.glob("*.db3"))
            db.write_bytes(mutate(db.read_bytes(), mutation, rng))
        else:
            bag.write_bytes(mutate(base.read_bytes(), mutation, rng))
        out = work / "out" / "adl.h5"
        out.parent.mkdir()

        def alarm(_sig: int, _frame: object) -> None:
            raise _Timeout

        old = signal.signal(signal.SIGALRM, alarm)
        signal.alarm(timeout_s)
        try:
            ingest([bag], out, TopicMap(), n_waypoints=32, size=64, recover=recover)
            kind = "ingested"
        except AdlError as exc:
            msg = str(exc)
            if "\n" in " ".join(msg.split()) or not msg.strip():
                return Outcome(False, "bad error message", msg)
            kind = "error"
        except _Timeout:
            return Outcome(False, "hang", f"no answer within {timeout_s} s")
        except Exception:  # noqa: BLE001 - the point of fuzzing: report it
            return Outcome(False, "crash", traceback.format_exc(limit=6))
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, old)
        shards = out.with_name("adl.shards")
        leftovers = [p.name for p in out.parent.iterdir() if p != out and not (p == shards and out.exists())]
        if leftovers:
            return Outcome(False, "partial files", str(leftovers))
        if out.exists():
            with h5py.File(out, "r") as f:
                if len(schema.episode_names(f)) != 1 or kind != "ingested":
                    return Outcome(False, "partial output", "output written without a complete episode")
        elif kind == "ingested":
            return Outcome(False, "no output", "ingest reported success but wrote nothing")
        return Outcome(True, kind)
