"""Summarise evaluation and replay into one markdown report, with the paper's comparisons spelled out.

    python -m adlpipe.report --eval metrics/eval.json --replay metrics/replay.json -o reports/report.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .atomic import write_text_atomic
from .errors import AdlError, run_cli


def _load(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise AdlError(f"{path}: cannot read metrics ({exc})") from exc


def _row(models: dict, model: str, method: str, steps: int) -> dict | None:
    return models.get(model, {}).get(f"{method}/{steps}")


def comparisons(ev: dict) -> list[str]:
    """The paper's claims as measured here: FM-1 ~ DP-16 << BC in error, FM-1 << DP-16 in time, and FM vs DP at
    equal steps."""
    m = ev["models"]
    fm1 = _row(m, "fm_cnn", "euler", 1)
    bc = _row(m, "bc_transformer", "direct", 1)
    out = []
    for sampler in ("ddpm", "ddim"):
        dp16 = _row(m, "dp_cnn", sampler, 16)
        if fm1 and dp16:
            out.append(f"- FM-CNN 1 step vs DP-CNN 16 {sampler.upper()} steps: {fm1['px']:.2f} vs {dp16['px']:.2f} px "
                       f"({100 * (fm1['px'] / dp16['px'] - 1):+.0f}%), {fm1['cm']:.2f} vs {dp16['cm']:.2f} cm; "
                       f"{fm1['ms']:.1f} vs {dp16['ms']:.1f} ms (DP-16 / FM-1 = {dp16['ms'] / fm1['ms']:.1f}x)")
    if fm1 and bc:
        mm = (f"; multimodal tasks {fm1['px_multimodal']:.2f} vs {bc['px_multimodal']:.2f} px"
              if fm1.get("px_multimodal") is not None and bc.get("px_multimodal") is not None else "")
        out.append(f"- FM-CNN 1 step vs BC-Transformer: {fm1['px']:.2f} vs {bc['px']:.2f} px{mm}")
    fm16, dp16 = _row(m, "fm_cnn", "euler", 16), _row(m, "dp_cnn", "ddpm", 16)
    if fm16 and dp16:  # equal steps: the two generative objectives over the same U-Net
        vs_bc = f"; BC-Transformer {bc['px']:.2f} px" if bc else ""
        out.append(f"- 16 steps each, FM-CNN vs DP-CNN (DDPM): {fm16['px']:.2f} vs {dp16['px']:.2f} px "
                   f"({100 * (fm16['px'] / dp16['px'] - 1):+.0f}%){vs_bc}")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m adlpipe.report", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--eval", type=Path, default=Path("metrics/eval.json"))
    p.add_argument("--replay", type=Path, default=Path("metrics/replay.json"))
    p.add_argument("--table1", type=Path, default=Path("reports/table1.md"))
    p.add_argument("--table2", type=Path, default=Path("reports/table2.md"))
    p.add_argument("-o", "--output", type=Path, default=Path("reports/report.md"))
    args = p.parse_args(argv)
    ev, rp = _load(args.eval), _load(args.replay)
    compared = comparisons(ev)
    parts = ["# adlpipe report", "", f"Test episodes: {ev['n_test']} (error), {rp['episodes']} (replay).", "",
             "## Comparisons", "", *compared, ""]
    for t in (args.table1, args.table2):
        if t.exists():
            parts += [t.read_text().replace("# ", "## ", 1), ""]
    write_text_atomic(args.output, "\n".join(parts))
    print("\n".join(compared))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.report", main))
