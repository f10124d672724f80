"""How well the doctor's frame-order check separates two swapped frames from a clean recording, on a dataset.

    python bench/frame_order.py data/adl.h5 [-o results/bench/frame_order.txt]

Per episode (the frames at 32 px grey, as the doctor reads them): the check's ratio at a quarter, half and three
quarters of the episode with those two frames swapped (what a planted swap gives), and the episode's lowest ratio
as stored (what a clean episode gives the doctor); the share of swaps below the doctor's limit and of clean
episodes below it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from adlpipe.curation.doctor import Limits
from adlpipe.curation.doctor_checks import frame_order
from adlpipe.dataset import schema


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path)
    p.add_argument("-o", "--out", type=Path)
    a = p.parse_args()
    swapped, clean = [], []
    with schema.open_dataset(a.data) as f:
        for name in schema.episode_names(f):
            rgb = f[schema.EPISODES][name]["frames/rgb"]
            small = [cv2.resize(rgb[i].mean(2, dtype=np.float32), (32, 32), interpolation=cv2.INTER_AREA)
                     for i in range(rgb.shape[0])]
            ratios = [r for k in range(1, len(small) - 2) if (r := frame_order(small, k)) is not None]
            if ratios:
                clean.append(min(ratios))
            for k in (len(small) // 4, len(small) // 2, 3 * len(small) // 4):
                s = list(small)
                s[k], s[k + 1] = s[k + 1], s[k]
                if (r := frame_order(s, k)) is not None:
                    swapped.append(r)
    limit = Limits().frame_swap
    sw, cl = np.array(swapped), np.array(clean)
    text = (f"{a.data}: {len(cl)} episodes, {len(sw)} planted swaps (a quarter, half, three quarters in)\n"
            f"swapped: ratio median {np.median(sw):.3f}, 90th percentile {np.percentile(sw, 90):.3f}, "
            f"max {sw.max():.3f}; below the limit {limit}: {(sw < limit).mean():.1%}\n"
            f"clean: the episode's lowest ratio min {cl.min():.3f}, median {np.median(cl):.3f}; below the limit: "
            f"{(cl < limit).mean():.1%}\n")
    print(text, end="")
    if a.out:
        a.out.write_text(text)


if __name__ == "__main__":
    main()
