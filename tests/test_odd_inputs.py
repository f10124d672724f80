"""The last odd inputs (issue R, fourth round): each is one line, a non-zero exit and nothing written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from conftest import REPO, one_line_error, run_module

RUN = REPO / "results" / "default"


def test_report_refuses_an_eval_file_without_figures(tmp_path: Path) -> None:
    empty = tmp_path / "eval.json"
    empty.write_text(json.dumps({"models": {}, "n_test": 0}))
    out = tmp_path / "reports" / "report.md"
    proc = run_module("report", "--eval", empty, "--replay", RUN / "replay_details.json", "-o", out)
    line = one_line_error(proc)
    assert "eval.json" in line and "no usable figures" in line
    assert not out.parent.exists()


def test_report_refuses_a_binary_table(tmp_path: Path) -> None:
    table = tmp_path / "table1.md"
    table.write_bytes(bytes(range(256)) * 4)
    out = tmp_path / "reports" / "report.md"
    proc = run_module("report", "--eval", RUN / "eval_details.json", "--replay", RUN / "replay_details.json",
                      "--table1", table, "--train-logs", tmp_path / "none", "-o", out)
    line = one_line_error(proc)
    assert "table1.md" in line and "markdown table" in line and "Traceback" not in proc.stderr
    assert not out.parent.exists()


def test_gather_with_nothing_to_gather_says_so(tmp_path: Path) -> None:
    index = tmp_path / "adl.h5"
    proc = run_module("ingest", "--gather", "-o", index)
    line = one_line_error(proc)
    assert "nothing to gather" in line and "adl.shards" in line
    assert not index.exists()
    shutil.rmtree(tmp_path / "adl.shards", ignore_errors=True)


INTERRUPTS = """
import json, random, signal, sys
from adlpipe.dataset import schema
from adlpipe.plumbing.errors import AdlError

data = sys.argv[1]
signal.signal(signal.SIGALRM, signal.default_int_handler)


def disarm():
    while True:  # an interrupt may land here too: disarming is retried until it holds
        try:
            signal.setitimer(signal.ITIMER_REAL, 0)
            return
        except KeyboardInterrupt:
            continue


rng, outcomes = random.Random(0), []
for _ in range(50):
    try:
        try:
            # re-armed every 5 ms: an interrupt Python drops in a finaliser is followed by the next, as a user
            # presses Ctrl-C again
            signal.setitimer(signal.ITIMER_REAL, rng.uniform(0.0005, 0.02), 0.005)
            while True:
                with schema.open_dataset(data) as f:
                    schema.read_episode(f, schema.episode_names(f)[0])
        finally:
            disarm()
    except KeyboardInterrupt:
        outcomes.append("interrupt")
    except AdlError as exc:
        outcomes.append(str(exc))
print(json.dumps(outcomes))
"""


def test_an_interrupt_inside_hdf5_reads_is_an_interrupt_not_damage(ingested: Path) -> None:
    """Ctrl-C (SIGALRM with Python's SIGINT handler) at 50 random moments of reading and checking a dataset: every
    one comes out as KeyboardInterrupt, never as a 'damaged' file (h5py turns an interrupt inside its compiled code
    into a SystemError caused by it). In a process of its own, as a stage runs."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", INTERRUPTS, str(ingested)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    outcomes = json.loads(proc.stdout.splitlines()[-1])
    assert outcomes == ["interrupt"] * 50, [o for o in outcomes if o != "interrupt"][:3]


def test_list_counts_channels_no_decoder_knows_and_errors_stay_short(tmp_path: Path) -> None:
    """An MCAP written without ROS schemas (protobuf, by mcap's own writer) with 40 channels: --list lists every
    topic with its counts and says it was not decoded; ingest's refusal names a few topics and how many more."""
    from mcap.writer import Writer

    bag = tmp_path / "foxglove.mcap"
    with open(bag, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="foxglove.RawImage", encoding="protobuf", data=b"\x0a\x00")
        channels = [w.register_channel(topic=f"/cam{i:02d}/image", message_encoding="protobuf", schema_id=sid)
                    for i in range(40)]
        for k in range(3):
            for c in channels:
                w.add_message(channel_id=c, log_time=k * 10**8, publish_time=k * 10**8, data=b"\x08\x01")
        w.finish()
    proc = run_module("ingest", "--list", bag)
    assert proc.returncode == 0, proc.stderr
    rows = [ln for ln in proc.stdout.splitlines() if "/image" in ln]
    assert len(rows) == 40 and all("declared      3 read      3" in r for r in rows)
    assert all("not decoded: no decoder for encoding 'protobuf'" in r for r in rows)
    line = one_line_error(run_module("ingest", bag, "-o", tmp_path / "adl.h5"))
    assert len(line) < 700 and "/cam00/image (foxglove.RawImage)" in line and "and 32 more" in line
    assert not (tmp_path / "adl.h5").exists()


def test_images_with_zero_stamps_are_one_line_naming_the_topic(tmp_path: Path) -> None:
    """A camera driver that never sets header.stamp (0) while the log times are right: one line naming the image
    topic and the zero stamps, not a claim that the end effector starts decades after the first image."""
    import yaml
    from layouts import Layout, topic_map, write_layout_bag

    lay = Layout(zero_image_stamps=True)
    bag, _t, _p = write_layout_bag(tmp_path / "zero.mcap", lay)
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(lay)))
    line = one_line_error(run_module("ingest", bag, "-o", tmp_path / "adl.h5", "--config", cfg))
    assert f"topic {topic_map(lay)['image']}" in line and "header.stamp is zero" in line
    assert "after the first image" not in line and not (tmp_path / "adl.h5").exists()


@pytest.mark.parametrize("there", ["truncated copy", "folder"])
def test_a_truncated_copy_under_hdf5_ext_prefix_is_blamed_not_the_datasets_file(ingested: Path, tmp_path: Path,
                                                                                there: str) -> None:
    """HDF5_EXT_PREFIX sends HDF5 to a truncated copy of an episode file, or to a folder of its name: the refusal
    names the variable and the dataset's own (healthy) file as the one to read (a folder blamed the dataset's file
    before), and without the variable the same dataset reads."""
    import os
    import subprocess
    import sys

    data = ingested
    prefix = tmp_path / "prefix"
    for episode in (data.parent / "adl.shards").rglob("*.h5"):
        copy = prefix / episode.relative_to(data.parent)
        copy.parent.mkdir(parents=True, exist_ok=True)
        if there == "folder":
            copy.mkdir()
        else:
            copy.write_bytes(episode.read_bytes()[:2000])
    env = {**os.environ, "HDF5_EXT_PREFIX": str(prefix)}
    proc = subprocess.run([sys.executable, "-m", "adlpipe.split", data, "-o", tmp_path / "split.json"],
                          capture_output=True, text=True, env=env, cwd=tmp_path)
    line = one_line_error(proc)
    assert f"HDF5_EXT_PREFIX={prefix}" in line and "unset HDF5_EXT_PREFIX to read" in line
    run_module("split", data, "-o", tmp_path / "split.json", check=True)


def test_a_ctrl_c_swallowed_by_a_finaliser_still_stops_the_stage_before_it_commits(tmp_path: Path) -> None:
    """Python drops a KeyboardInterrupt raised inside a weakref callback or a finaliser (as h5py's and torch's
    objects run): a real SIGINT landing there must still stop the stage before it replaces an output, and the stage
    says that nothing was replaced."""
    import io
    import os
    import signal
    import sys
    import weakref
    from contextlib import redirect_stderr

    from adlpipe.plumbing.atomic import write_text_atomic
    from adlpipe.plumbing.errors import run_cli

    out = tmp_path / "out.txt"
    out.write_text("old")

    class Held:
        pass

    def main(_argv: list[str] | None) -> int:
        def swallowing(_ref: object) -> None:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(100_000):  # Python runs the handler at a loop's back edge: here, inside the callback,
                pass  # where the KeyboardInterrupt it raises is dropped

        held = Held()
        ref = weakref.ref(held, swallowing)  # noqa: F841 - the callback runs when `held` goes
        del held
        write_text_atomic(out, "new")
        return 0

    old, old_hook = signal.getsignal(signal.SIGINT), sys.unraisablehook
    err, dropped = io.StringIO(), []
    sys.unraisablehook = lambda u: dropped.append(u.exc_type)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as a stage starts (whatever an earlier test left)
    try:
        with redirect_stderr(err):
            rc = run_cli("adlpipe.test", main, [])
    finally:
        signal.signal(signal.SIGINT, old)
        sys.unraisablehook = old_hook
    assert KeyboardInterrupt in dropped  # Python dropped the interrupt where it landed (other garbage may go too) ...
    assert rc == 130 and out.read_text() == "old"  # ... and the stage stopped before replacing the output
    assert "interrupted; no output was replaced" in err.getvalue()


def test_ingests_full_disk_hooks_pass_everything_else_to_the_hooks_before_them() -> None:
    """ingest quiets h5py's destructor noise after a full disk; anything else (a Ctrl-C in a finaliser) goes on to
    the hook set before it (run_cli's quiet one), not to Python's default, which printed the 5-8 line trace."""
    import errno
    import sys

    from adlpipe import ingest

    seen: list[type] = []
    saved = sys.unraisablehook, sys.excepthook
    sys.unraisablehook = lambda u: seen.append(u.exc_type)
    sys.excepthook = lambda kind, exc, tb: seen.append(kind)
    try:
        ingest._report_full_disk_once()

        def raise_in_finaliser(exc: BaseException) -> None:
            class Dying:
                def __del__(self) -> None:
                    raise exc
            Dying()

        raise_in_finaliser(OSError(errno.ENOSPC, "No space left on device"))
        raise_in_finaliser(KeyboardInterrupt())
        sys.excepthook(OSError, OSError(errno.ENOSPC, "full"), None)
        sys.excepthook(ValueError, ValueError("other"), None)
    finally:
        sys.unraisablehook, sys.excepthook = saved
    assert seen == [KeyboardInterrupt, ValueError]
