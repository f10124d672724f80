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

from adlpipe import schema
from adlpipe.bags.topics import TopicMap
from adlpipe.errors import AdlError
from adlpipe.ingest import ingest

MUTATIONS = ["truncate", "flip", "length", "zero", "duplicate", "splice"]


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


class _Timeout(Exception):
    pass


def run_case(base: Path, mutation: str, seed: int, recover: bool = False, timeout_s: int = 20) -> Outcome:
    """Mutate one bag (file, or a rosbag2 folder's .db3) and ingest it in this process."""
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if base.is_dir():
            bag = work / base.name
            shutil.copytree(base, bag)
            db = next(bag.glob("*.db3"))
            db.write_bytes(mutate(db.read_bytes(), mutation, rng))
        else:
            bag = work / base.name
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
        leftovers = [p.name for p in out.parent.iterdir() if p != out]
        if leftovers:
            return Outcome(False, "partial files", str(leftovers))
        if out.exists():
            with h5py.File(out, "r") as f:
                if len(schema.episode_names(f)) != 1 or kind != "ingested":
                    return Outcome(False, "partial output", "output written without a complete episode")
        elif kind == "ingested":
            return Outcome(False, "no output", "ingest reported success but wrote nothing")
        return Outcome(True, kind)
