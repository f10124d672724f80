"""Mutated-dataset fuzzing of the stages that read a dataset, shared by tests/test_robustness.py (a few dozen cases
in CI) and bench/fuzz_ingest.py --dataset (thousands). A sharded dataset (index, catalog, links, episode files) is
damaged one way per case, then split, export and (every `train_every`-th case) train and inspect run on it in this
process, as their command lines do. A case passes when every stage either succeeds or fails with one stderr line
and a non-zero exit, within a time limit, and a stage that failed left no output behind."""

from __future__ import annotations

import contextlib
import importlib
import io
import shutil
import signal
import tempfile
import traceback
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from fuzzing import MUTATIONS, mutate

from adlpipe.dataset import schema
from adlpipe.plumbing.errors import run_cli

# Each changes one thing a reader trusts: the index's or an episode file's bytes, a catalog row, an episode link,
# a dataset's presence, shape, type or values, an attribute, or an episode file's existence.
DATASET_MUTATIONS = ["index_bytes", "episode_bytes", "catalog_row", "link_target", "drop_dataset",
                     "reshape_dataset", "non_finite", "attribute", "remove_file"]
EPISODE_DATASETS = ["traj2d", "traj3d", "frames/rgb", "frames/t", "frames/ee_pos", "frames/joint_pos",
                    "frames/depth", "frames/depth_index", "frames/affordance", "frames/affordance_index", "image",
                    "affordance", "objects"]


@dataclass
class StageOutcome:
    ok: bool
    kind: str  # "ran", "error", or what went wrong
    detail: str = ""


def _episode_files(index: Path) -> list[Path]:
    return sorted(schema.shards_root(index).rglob("*.h5"))


def _pick(rng: np.random.Generator, items: list):
    return items[int(rng.integers(0, len(items)))]


def _replace(g: h5py.Group, key: str, data: np.ndarray) -> None:
    del g[key]
    g.create_dataset(key, data=data)


def mutate_dataset(index: Path, mutation: str, rng: np.random.Generator) -> str:
    """Damage the dataset at `index` in place; returns what was done (for the failure report)."""
    files = _episode_files(index)
    if mutation == "index_bytes":
        index.write_bytes(mutate(index.read_bytes(), _pick(rng, MUTATIONS), rng))
        return "index bytes"
    if mutation == "episode_bytes":
        f = _pick(rng, files)
        f.write_bytes(mutate(f.read_bytes(), _pick(rng, MUTATIONS), rng))
        return f"bytes of {f.name}"
    if mutation == "remove_file":
        f = _pick(rng, files)
        f.unlink()
        return f"removed {f.name}"
    if mutation in ("catalog_row", "link_target"):
        with h5py.File(index, "a") as f:
            names = sorted(f[schema.EPISODES])
            i = int(rng.integers(0, len(names)))
            value = _pick(rng, ["", "../../outside.h5", "/etc/passwd", "adl.shards/none/x.h5", names[-1 - i],
                                str(files[0].relative_to(index.parent)), "\x00", "é" * 300])
            if mutation == "catalog_row":
                col = _pick(rng, list(schema.CATALOG_FIELDS))
                data = [v.decode() for v in f[schema.CATALOG][col][()]]
                data[i % len(data)] = value
                del f[schema.CATALOG][col]
                f[schema.CATALOG].create_dataset(col, data=data, dtype=h5py.string_dtype())
                return f"catalog {col}[{i}] = {value!r}"
            del f[schema.EPISODES][names[i]]
            if value and "\x00" not in value:
                f[schema.EPISODES][names[i]] = h5py.ExternalLink(value, _pick(
                    rng, [f"/{schema.EPISODES}/{names[i]}", f"/{schema.EPISODES}/{names[-1 - i]}", "/"]))
            return f"link of {names[i]} -> {value!r}"
    f = _pick(rng, files)
    with h5py.File(f, "a") as h:
        g = h[schema.EPISODES][next(iter(h[schema.EPISODES]))]
        present = [k for k in EPISODE_DATASETS if k in g]
        key = _pick(rng, present)
        if mutation == "drop_dataset":
            del g[key]
            return f"dropped {key} of {f.name}"
        d = g[key]
        if mutation == "reshape_dataset":
            shape = list(d.shape)
            change = _pick(rng, ["shorter", "longer", "extra axis", "scalar", "float", "text"])
            if change == "shorter" and shape:
                shape[0] = max(0, shape[0] - int(rng.integers(1, 5)))
            elif change == "longer" and shape:
                shape[0] += int(rng.integers(1, 5))
            elif change == "extra axis":
                shape.append(2)
            elif change == "scalar":
                shape = []
            if change == "text":
                _replace(g, key, np.array("not numbers", dtype=h5py.string_dtype()))
            else:
                dtype = np.float64 if change == "float" else d.dtype
                _replace(g, key, np.resize(d[()].astype(dtype), shape) if shape else np.zeros((), dtype))
            return f"{key} of {f.name}: {change}"
        if mutation == "non_finite":
            if d.dtype.kind != "f" or d.size == 0:
                _replace(g, key, np.full(d.shape, -1, d.dtype) if d.dtype.kind in "iu" else d[()])
                return f"{key} of {f.name}: -1 everywhere"
            a = d[()]
            with np.errstate(over="ignore"):  # 1e300 in a float32 array is inf, as meant
                a.flat[int(rng.integers(0, a.size))] = _pick(rng, [np.nan, np.inf, -np.inf, 1e300])
            d[...] = a
            return f"{key} of {f.name}: a non-finite value"
        target = _pick(rng, [g, h, h[schema.EPISODES]])  # "attribute"
        attrs = list(target.attrs)
        if attrs and rng.random() < 0.5:
            a = _pick(rng, attrs)
            del target.attrs[a]
            return f"removed attribute {a} of {target.name} in {f.name}"
        a = _pick(rng, attrs or ["task"])
        target.attrs[a] = _pick(rng, ["", -1, 2**40, np.nan, "x" * 10000, np.zeros(3)])
        return f"attribute {a} of {target.name} in {f.name} changed"


class _Timeout(Exception):
    pass


def run_stage(stage: str, args: list[str], output: Path | None, timeout_s: int) -> StageOutcome:
    """A stage's command line in this process (run_cli, as `python -m adlpipe.<stage>` runs it)."""
    module = importlib.import_module(f"adlpipe.{stage}")
    err = io.StringIO()

    def alarm(_sig: int, _frame: object) -> None:
        raise _Timeout

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(timeout_s)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            rc = run_cli(f"adlpipe.{stage}", module.main, args)
    except SystemExit as exc:  # the parser's own exit
        rc = int(exc.code or 0)
    except _Timeout:
        return StageOutcome(False, "hang", f"{stage}: no answer within {timeout_s} s")
    except Exception:  # noqa: BLE001 - the point of fuzzing: report it
        return StageOutcome(False, "crash", f"{stage}: {traceback.format_exc(limit=6)}")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    lines = [x for x in err.getvalue().splitlines() if x.strip() and not x.startswith("note:")]
    if rc == 0:
        return StageOutcome(True, "ran")
    if len(lines) != 1 or "Traceback" in err.getvalue():
        return StageOutcome(False, "bad error message", f"{stage}: {err.getvalue()[-800:]}")
    if output is not None and output.exists():
        return StageOutcome(False, "partial output", f"{stage} failed but left {output}")
    return StageOutcome(True, "error")


def run_dataset_case(base: Path, mutation: str, seed: int, heavy: bool = False,
                     timeout_s: int = 60) -> list[tuple[str, StageOutcome]]:
    """Copy the dataset at `base` (an index beside its .shards folder), damage it, and run the reading stages:
    split and export always, train and inspect when `heavy`. Returns each stage's outcome."""
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        index = work / base.name
        shutil.copy2(base, index)
        shutil.copytree(schema.shards_root(base), schema.shards_root(index))
        try:
            what = mutate_dataset(index, mutation, rng)
        except Exception as exc:  # noqa: BLE001 - the mutator's own trouble is not the stages'
            return [("mutate", StageOutcome(True, "not mutated", f"{type(exc).__name__}: {exc}"))]
        split = work / "split.json"
        out = [("split", run_stage("split", [str(index), "-o", str(split)], split, timeout_s)),
               ("export", run_stage("export", [str(index), str(work / "lerobot")], work / "lerobot", timeout_s))]
        if heavy and split.exists():
            out.append(("train", run_stage(
                "train", ["--model", "bc_cnn", "--data", str(index), "--split", str(split), "--out",
                          str(work / "model"), "--epochs", "1", "--batch-size", "2", "--image-size", "32",
                          "--val-fraction", "0", "--threads", "1"], None, timeout_s)))
            out.append(("inspect", run_stage(
                "inspect", ["--dataset", "--data", str(index), "--split", str(split), "-o", str(work / "x.rrd")],
                work / "x.rrd", timeout_s)))
        return [(stage, StageOutcome(o.ok, o.kind, f"{what}: {o.detail}" if o.detail else what))
                for stage, o in out]
