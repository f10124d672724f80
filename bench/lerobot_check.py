"""Load adlpipe's LeRobot export with LeRobot's own loader and compare it with the source dataset.

LeRobot (0.4.4 pins torch < 2.11 and rerun-sdk < 0.27) cannot be installed beside adlpipe's torch 2.13 and rerun
0.41, so the check runs in two environments:

    # 1. adlpipe's venv: export, and write what the source holds (frames per episode, tasks, state statistics)
    python bench/lerobot_check.py expect data/adl.h5 /tmp/adl_lerobot
    # 2. a venv with LeRobot (here: torch 2.14.1 + torchvision 0.29.1 from this machine's disk, then
    #    pip install --no-deps lerobot==0.4.4 and its dataset dependencies: datasets, huggingface_hub, pandas,
    #    jsonlines, deepdiff, draccus, einops, termcolor, av, packaging):
    HF_HUB_OFFLINE=1 python bench/lerobot_check.py check /tmp/adl_lerobot

Step 2 imports only LeRobot and the standard library: LeRobotDataset(repo_id, root=...) reads the local folder,
with no download. It prints each comparison and exits 1 on a mismatch.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

EXPECTED = "adlpipe_expected.json"
THUMBS = "adlpipe_expected_frames.npy"  # every frame of the source, 16 x 16 (area means), uint8 RGB
TOLERANCE = 4.0  # grey levels: the mean absolute difference H.264 (CRF 15, yuv420p) may leave


def thumbnails(frames):  # noqa: ANN001, ANN201 - (T, S, S, 3) uint8 -> (T, 16, 16, 3) float
    t, s = frames.shape[0], frames.shape[1]
    return frames.reshape(t, 16, s // 16, 16, s // 16, 3).mean((2, 4))


def expect(data: Path, out: Path) -> None:
    import numpy as np

    from adlpipe.dataset import schema
    from adlpipe.export import export_lerobot

    export_lerobot(data, out)  # the cameras as video
    with schema.open_dataset(data) as f:
        names = schema.episode_names(f)
        eps = [f[schema.EPISODES][n] for n in names]
        state = np.concatenate([np.concatenate([g["frames/ee_pos"][()], g["frames/joint_pos"][()],
                                                g["frames/gripper"][()][:, None]], 1) for g in eps])
        want = {"episodes": len(names), "lengths": [len(g["frames/t"]) for g in eps],
                "tasks": [str(g.attrs["task"]) for g in eps], "state_min": np.nanmin(state, 0).tolist(),
                "state_max": np.nanmax(state, 0).tolist(), "state_mean": np.nanmean(state, 0).tolist(),
                "image_size": int(f.attrs["image_size"])}
        fr = eps[0]["frames"]
        if "depth_index" in fr and fr["depth_index"][0] >= 0:  # the first frame's depth, millimetres
            d = fr["depth"][int(fr["depth_index"][0])].astype(np.int64)
            want["depth0_sum_max"] = [int(d.sum()), int(d.max())]
        np.save(out / THUMBS, np.concatenate([thumbnails(g["frames/rgb"][()]) for g in eps]))
    (out / EXPECTED).write_text(json.dumps(want))
    print(f"exported {len(names)} episodes, {sum(want['lengths'])} frames to {out}")


def check(root: Path) -> int:
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    want = json.loads((root / EXPECTED).read_text())
    ds = LeRobotDataset("adlpipe/adl", root=root)
    got_lengths = [int(ds.meta.episodes[i]["length"]) for i in range(ds.meta.total_episodes)]
    item = ds[0]
    last = ds[len(ds) - 1]
    stats = ds.meta.stats["observation.state"]
    checks = {
        "episodes": (ds.num_episodes, want["episodes"]),
        "frames": (ds.num_frames, sum(want["lengths"])),
        "frames per episode": (got_lengths, want["lengths"]),
        "task of each episode": ([ds.meta.episodes[i]["tasks"][0] for i in range(ds.num_episodes)], want["tasks"]),
        "first item's task": (item["task"], want["tasks"][0]),
        "last item's episode": (int(last["episode_index"]), want["episodes"] - 1),
        "rgb tensor": (tuple(item["observation.images.rgb"].shape), (3, want["image_size"], want["image_size"])),
        "state min": (np.allclose(stats["min"], want["state_min"], rtol=1e-5, equal_nan=True), True),
        "state max": (np.allclose(stats["max"], want["state_max"], rtol=1e-5, equal_nan=True), True),
        "state mean": (np.allclose(stats["mean"], want["state_mean"], rtol=1e-4, atol=1e-6, equal_nan=True), True),
    }
    # every frame decoded from the video by LeRobot's own decoder, against the source frame
    thumbs = np.load(root / THUMBS)
    worst = max(float(np.abs(thumbnails(ds[i]["observation.images.rgb"].permute(1, 2, 0).numpy()[None] * 255.0)
                             - thumbs[i]).mean()) for i in range(len(ds)))
    checks[f"every frame within {TOLERANCE} grey levels (mean, 16 x 16 areas)"] = (worst < TOLERANCE, True)
    print(f"    the worst frame differs by {worst:.2f} grey levels")
    if "depth0_sum_max" in want:  # LeRobot 0.4.4 reads 16-bit PNG as int16: exact below 32.767 m
        d = item["observation.images.depth"].long()
        checks["depth of the first frame (mm: sum, max)"] = ([int(d.sum()), int(d.max())], want["depth0_sum_max"])
    bad = 0
    for name, (got, exp) in checks.items():
        ok = got == exp
        bad += not ok
        print(f"{'ok ' if ok else 'BAD'} {name}: {got if not ok else exp}" + ("" if ok else f" (expected {exp})"))
    print(f"LeRobotDataset read {ds.num_episodes} episodes, {ds.num_frames} frames, {len(ds.meta.tasks)} tasks: "
          f"{'all equal to the source' if not bad else f'{bad} mismatch(es)'}")
    return 1 if bad else 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "expect":
        expect(Path(sys.argv[2]), Path(sys.argv[3]))
    elif len(sys.argv) == 3 and sys.argv[1] == "check":
        sys.exit(check(Path(sys.argv[2])))
    else:
        sys.exit(__doc__)
