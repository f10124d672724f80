"""What a plan's latency costs closed loop: success per latency and execution (replay --latency --execution), each
paired with the same policy without latency on the same scenes, with the person still and moving; and the policy
server's transport benchmark (bench/serve.py)."""

from __future__ import annotations

import re

from ..sim.tasks import FORCE_LIMIT_N as SAFE_FORCE_N
from .stats import paired_success, rate_cell

LATENCY = re.compile(r"^(?P<policy>.+)/lat-(?P<ms>[0-9.]+ms|measured)(?:-(?P<mode>sync|async))?$")
POLICY_NAMES = {"fm_cnn/euler-1": "FM-1", "dp_cnn/ddpm-16": "DP-16"}


def _policy_name(label: str) -> str:
    base = label.rsplit("/Ta-", 1)[0]
    return POLICY_NAMES.get(base, base)


def latency_rows(details: dict) -> dict[tuple[str, str], dict[str, str]]:
    """(latency, execution) -> policy -> its success cell, paired with its own lat-0 row."""
    per = details["per_episode"]
    diags = details.get("diagnostics", {})
    base: dict[str, str] = {}
    rows: dict[tuple[str, str], dict[str, str]] = {}
    parsed = [(label, LATENCY.match(label)) for label in per]
    for label, m in parsed:
        if m is not None and m["ms"] == "0ms":
            base[m["policy"]] = label
    for label, m in parsed:
        if m is None:
            continue
        scenes = sorted(per[label])
        ok = [per[label][s] for s in scenes]
        force = sum(diags.get(label, {}).get(s, {}).get("peak_force_n", 0.0) > SAFE_FORCE_N for s in scenes)
        cell = f"{rate_cell(sum(ok), len(ok))}"
        if m["ms"] != "0ms" and m["policy"] in base:
            ref = [per[base[m["policy"]]][s] for s in scenes]
            pair = paired_success(ok, ref)
            delta = 100 * (sum(ok) - sum(ref)) / len(ok)
            cell += f" ({delta:+.1f}, p = {pair.p_value:.2f})"
        cell += f"; {force} over {SAFE_FORCE_N:g} N"
        rows.setdefault((m["ms"], m["mode"] or "-"), {})[_policy_name(m["policy"])] = cell
    return rows


def _ms_key(key: tuple[str, str]) -> tuple[float, str]:
    ms, mode = key
    return (float("inf") if ms == "measured" else float(ms[:-2]), mode)


def latency_lines(still: dict, moving: dict | None) -> list[str]:
    """The sweep's table: one row per latency and execution, a column per policy and person."""
    worlds = [("still", latency_rows(still))] + ([("moving", latency_rows(moving))] if moving else [])
    policies = sorted({p for _, rows in worlds for cells in rows.values() for p in cells})
    n = len(next(iter(still["per_episode"].values())))
    head = [f"{p}, person {w}" for w, _ in worlds for p in policies]
    lines = [f"| latency per plan | the arm meanwhile | {' | '.join(head)} |",
             "| ---: | --- |" + " ---: |" * len(head)]
    keys = sorted({k for _, rows in worlds for k in rows}, key=_ms_key)
    meanwhile = {"sync": "holds its last command", "async": "goes on with the previous plan", "-": "-"}
    for key in keys:
        cells = [rows.get(key, {}).get(p, "-") for _, rows in worlds for p in policies]
        lines.append(f"| {key[0].replace('ms', ' ms')} | {meanwhile[key[1]]} | {' | '.join(cells)} |")
    lines += ["", f"Success % [95 %] over the same {n} fresh scenes in every cell (Ta 8 of 16 waypoints at 10 Hz); in "
              "brackets the change against the same policy without latency, points, and McNemar's exact p on the "
              f"paired scenes; then the scenes with a force on the person over {SAFE_FORCE_N:g} N."]
    return lines


def serve_lines(bench: dict, load: dict | None = None) -> list[str]:
    """bench/serve.py's figures: round trip against in-process planning, plans per second by clients, and (load)
    8 clients for minutes with the server's resident memory."""
    host = bench["host"]
    lines = ["| policy | in-process plan ms | round trip ms | transport overhead ms [IQR] | plans/s with 1 / 2 / 4 / 8 "
             "clients | median round trip ms with 1 / 2 / 4 / 8 |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for path, row in bench["models"].items():
        if "latency" not in row:
            continue
        lat, thr = row["latency"], row["throughput"]
        name = {"fm": "FM-1", "ddpm": "DP-16"}.get(row["family"], path)
        name = f"{name} ({row['steps']} step{'s' if row['steps'] > 1 else ''})"
        rates = " / ".join(f"{t['plans_per_s']:.0f}" for t in thr)
        trips = " / ".join(f"{t['median_round_trip_ms']:.0f}" for t in thr)
        iqr = lat["overhead_iqr_ms"]
        lines.append(f"| {name} | {lat['in_process_ms']:.1f} | {lat['round_trip_ms']:.1f} | "
                     f"{lat['overhead_ms']:.1f} [{iqr[0]:.1f}, {iqr[1]:.1f}] | {rates} | {trips} |")
    shape = " x ".join(map(str, bench.get("image", [])))
    lines += ["", f"Loopback on {host['cpus']} CPU cores ({host['machine']}), torch {host['torch']} with "
              f"{host['threads']} thread(s) on each side, batch 1, an observation of two recorded frames ({shape} "
              "uint8) with its state and command; medians over the rounds, in-process and round trip alternating."]
    for path, row in (load or {}).get("models", {}).items():
        run = row.get("load")
        if run:
            rss = [mb for _, mb in run["server_rss_mb"]]
            lines += ["", f"Load: {run['clients']} clients planning back to back for {run['seconds'] / 60:.0f} min "
                      f"({path.rsplit('/', 1)[-1]}, beside other work on the machine): {run['plans']:,} plans, "
                      f"{len(run['errors'])} errors, the server's resident memory {rss[0]:.1f} MB after 5 s and "
                      f"{rss[-1]:.1f} MB at the end (at most {max(rss):.1f})."]
    return lines
