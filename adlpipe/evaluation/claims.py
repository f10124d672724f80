"""The paper's claims as measured on a run (best validation checkpoints, default samplers), each supported,
contradicted, not resolved at its n, or no finding when a model it rests on did not converge; and the convergence
table those verdicts lean on."""

from __future__ import annotations

import math

from .stats import paired_difference, paired_success
from .tables import error_cell

FAST_RATIO = 8.0  # "much faster": DP-16 takes at least this many times FM-1's milliseconds
AS_ACCURATE = 0.10  # "about as accurate": FM-1 px at most 10 % above DP-16 px


def _row(ev: dict, model: str, method: str, steps: int, checkpoint: str = "best") -> dict | None:
    return ev.get("models", {}).get(model, {}).get(checkpoint, {}).get(f"{method}/{steps}")


UNDERTRAINED_RATIO = 2.0  # a generative model this many times worse than MSE regression on the same network


def _converged(ev: dict, *models: str) -> list[str]:
    """'<model> not converged' (by training's rule) or '<model> undertrained' (see _undertrained) for the models
    among `models` a claim cannot rest on."""
    out = []
    for m in models:
        if not ev.get("training", {}).get(m, {}).get("converged"):
            out.append(f"{m} not converged")
        elif _undertrained(ev, m):
            out.append(f"{m} undertrained: over {UNDERTRAINED_RATIO:.0f}x BC-CNN's error with the same network")
    return out


def _undertrained(ev: dict, model: str) -> bool:
    """A plateau of val px within one run can come from the learning-rate schedule running out, not from the model
    having learnt the data (DP at the default budget: flat at ~22 px as the cosine schedule ends, 2.3 px after
    7,000 steps). A generative U-Net model far worse than BC-CNN, the MSE regressor on the same U-Net and encoder,
    has not learnt what regression learns from the same data: it is undertrained, whatever its curve says."""
    if not model.endswith("_cnn") or model == "bc_cnn":
        return False
    method = "ddpm" if model.startswith("dp_") else "euler"
    row, bc = _row(ev, model, method, 16), _row(ev, "bc_cnn", "direct", 1)
    return bool(row and bc and row["px"] > UNDERTRAINED_RATIO * bc["px"])


def _verdict(holds: bool, not_converged: list[str]) -> str:
    if not_converged:
        measured = "holds" if holds else "fails"
        return f"**not a finding** ({', '.join(not_converged)}; measured: {measured})"
    return "**supported**" if holds else "**not supported**"


def _ratio(fm1: dict, dp16: dict, key: str) -> tuple[float, float | None, float | None]:
    """DP-16's `key` milliseconds over FM-1's, with the interval its medians' bootstrap intervals bound (the slowest
    DP over the fastest FM to the fastest DP over the slowest FM: conservative); None ends without intervals."""
    ratio = dp16[key] / fm1[key]
    a, b = fm1.get(f"{key}_ci"), dp16.get(f"{key}_ci")
    return (ratio, b[0] / a[1], b[1] / a[0]) if a and b else (ratio, None, None)


def _ratio_verdict(lo: float | None, hi: float | None, ratio: float) -> str:
    if lo is None or hi is None:  # measured before latencies had intervals
        return "supported" if ratio >= FAST_RATIO else "not supported"
    return "supported" if lo >= FAST_RATIO else "contradicted" if hi < FAST_RATIO else "not resolved"


def _host_words(host: dict | None) -> str:
    if not host:
        return "a host not recorded"
    return host.get("gpu") or f"{host.get('cpu', '?')}, {host.get('torch_threads', '?')} torch threads"


def speed_verdict(fm1: dict, dp16: dict, host: dict | None = None) -> str:
    """The speed-up DP-16 / FM-1 against FAST_RATIO. Judged on the sampler (the network evaluations after the
    encoder: 1 against 16, which no host changes) when the parts were timed; the whole plan's ratio, encoder
    included, is stated for the host it was measured on, since the encoder's share differs by host (measured: 10.4x
    on one 2-core host, 7.3x on a slower one with the same checkpoints' kind)."""
    ratio, lo, hi = _ratio(fm1, dp16, "ms")
    cell = f"{ratio:.1f}x" + (f" [{lo:.1f}, {hi:.1f}]" if lo is not None else "")
    plan = (f"{fm1['ms']:.1f} vs {dp16['ms']:.1f} ms per plan, batch 1, encoder included ({cell}: "
            f"{_ratio_verdict(lo, hi, ratio)} on {_host_words(host)})")
    if not (fm1.get("sampler_ms") and dp16.get("sampler_ms")):  # measured before the parts were timed
        return f"**{_ratio_verdict(lo, hi, ratio)}** on this host. {plan}."
    s_ratio, s_lo, s_hi = _ratio(fm1, dp16, "sampler_ms")
    s_cell = f"{s_ratio:.1f}x" + (f" [{s_lo:.1f}, {s_hi:.1f}]" if s_lo is not None else "")
    share = fm1["encoder_ms"] / fm1["ms"]
    evals = (f"{fm1.get('evaluations', 1)} vs {dp16.get('evaluations', 16)} network evaluations"
             if fm1.get("evaluations") else "1 vs 16 network evaluations")
    return (f"**{_ratio_verdict(s_lo, s_hi, s_ratio)}** on the sampler ({evals}: {fm1['sampler_ms']:.2f} vs "
            f"{dp16['sampler_ms']:.2f} ms, {s_cell}, from the medians' 95 % intervals); {plan}; the encoder is "
            f"{100 * share:.0f} % of FM-1's plan, so the whole plan's ratio is lower where the encoder weighs more.")


def _paired_verdict(a: dict, b: dict, not_converged: list[str], scale: float = 1.0) -> str:
    """The claim "a's px is below scale x b's" on the episodes both were evaluated on: supported or contradicted
    only when the paired 95 % bootstrap interval of the per-episode difference excludes zero, else not resolved
    (adlpipe.evaluation.stats.PairedDifference); never a finding when a model it rests on is not converged."""
    if a.get("px_per_episode") and b.get("px_per_episode"):
        d = paired_difference(a["px_per_episode"], b["px_per_episode"], scale)
        of = f", of first - {scale:g} x second" if scale != 1 else ""  # the tolerance is part of the claim
        verdict, detail = d.verdict(), f" ({d} px{of})"
    else:  # details written before per-episode errors were kept
        verdict = "supported" if a["px"] <= scale * b["px"] else "contradicted"
        detail = " (unpaired: no per-episode errors)"
    if not_converged:
        return f"**not a finding** ({', '.join(not_converged)}; measured: {verdict}){detail}"
    return f"**{verdict}**{detail}"


def _instability(ev: dict, model: str) -> float | None:
    """How much val px goes back up over the second half of training: the mean rise of log val px between
    successive validations (falls count as zero: a curve still improving is not unstable)."""
    hist = [r for r in ev.get("training", {}).get(model, {}).get("val_history", []) if r[1]]
    half = [v for e, v in hist if e > hist[-1][0] / 2] if hist else []
    if len(half) < 3:
        return None
    return sum(max(0.0, math.log(b / a)) for a, b in zip(half[:-1], half[1:], strict=True)) / (len(half) - 1)


# The FM / DP pairs, each on the same U-Net: both predicting the clean trajectory (the default pair), and both
# predicting what the paper's methods predict (a velocity, the noise).
PAIRS = (("fm_cnn", "dp_cnn", "clean-trajectory output for both"),
         ("fm_cnn_velocity", "dp_cnn_epsilon", "the paper's pair: velocity vs noise output"))


def claims(ev: dict, rp: dict) -> list[str]:
    """The paper's four claims, as measured here (best validation checkpoints, default samplers), for each FM/DP
    pair that was trained."""
    out = []
    success = rp.get("success", {})

    def sr(label: str) -> str:
        r = success.get(label)
        return f"{100 * r['overall']:.0f}%" if r else "-"

    def paired(a: str, b: str) -> str:
        """The paired test of two replayed policies on the scenes both ran."""
        pa, pb = rp.get("per_episode", {}).get(a, {}), rp.get("per_episode", {}).get(b, {})
        both = sorted(set(pa) & set(pb))
        return f" ({paired_success([pa[n] for n in both], [pb[n] for n in both])})" if both else ""

    for fm, dp, pair in PAIRS:
        fm1, fm16 = _row(ev, fm, "euler", 1), _row(ev, fm, "euler", 16)
        dp16 = _row(ev, dp, "ddpm", 16)
        if fm1 and dp16:
            verdict = _paired_verdict(fm1, dp16, _converged(ev, fm, dp), 1 + AS_ACCURATE)
            out.append(f"- FM-1 about as accurate as DP-16 (within {100 * AS_ACCURATE:.0f}% or better; {pair}): "
                       f"{verdict}. {fm} 1 step {fm1['px']:.2f} px "
                       f"({fm1['px224']:.2f} px at 224) vs {dp} 16 DDPM steps {dp16['px']:.2f} px "
                       f"({dp16['px224']:.2f}); replay {sr(f'{fm}/euler-1')} vs {sr(f'{dp}/ddpm-16')}"
                       f"{paired(f'{fm}/euler-1', f'{dp}/ddpm-16')}.")
            out.append(f"- FM-1 much faster than DP-16 (at least {FAST_RATIO:.0f}x; {pair}): "
                       f"{speed_verdict(fm1, dp16, ev.get('host'))}")
        if fm16 and dp16:
            out.append(f"- At equal steps (16), {fm} more accurate than {dp}: "
                       f"{_paired_verdict(fm16, dp16, _converged(ev, fm, dp))}. {fm16['px']:.2f} vs "
                       f"{dp16['px']:.2f} px.")
        s_fm, s_dp = _instability(ev, fm), _instability(ev, dp)
        if s_fm is not None and s_dp is not None:
            out.append(f"- FM more stable in training than DP ({pair}): "
                       f"{_verdict(s_fm <= s_dp, _converged(ev, fm, dp))}. Mean rise of log val px between "
                       f"validations over the second half of training: {fm} {s_fm:.4f}, {dp} {s_dp:.4f} (0: never "
                       "went back up); see val_px_vs_epoch.png.")
    for fm, bc, net in (("fm_cnn", "bc_cnn", "U-Net"), ("fm_transformer", "bc_transformer", "transformer")):
        f, b = _row(ev, fm, "euler", 1), _row(ev, bc, "direct", 1)
        if f and b:
            mm = (f"; multimodal tasks {f['px_multimodal']:.2f} vs {b['px_multimodal']:.2f} px"
                  if f.get("px_multimodal") is not None and b.get("px_multimodal") is not None else "")
            out.append(f"- FM better than BC ({net} for both, only the objective differs): "
                       f"{_paired_verdict(f, b, _converged(ev, fm, bc))}. 1 step {f['px']:.2f} vs {b['px']:.2f} "
                       f"px{mm}; "
                       f"replay {sr(f'{fm}/euler-1')} (16 steps: {sr(f'{fm}/euler-16')}) vs {sr(bc)}"
                       f"{paired(f'{fm}/euler-1', bc)}.")
    return out


def convergence_lines(ev: dict) -> list[str]:
    lines = ["| model | optimiser steps | val px best [95 %] (epoch) | val px last [95 %] | converged |",
             "| --- | ---: | ---: | ---: | --- |"]
    for model, t in ev.get("training", {}).items():
        if t.get("val_px_best") is None:
            continue
        state = "yes" if t.get("converged") else "**no**"
        if t.get("converged") and _undertrained(ev, model):
            state = f"flat, but **undertrained** (16-step px over {UNDERTRAINED_RATIO:.0f}x BC-CNN's)"
        lines.append(f"| {model} | {t.get('optimizer_steps', '?')} | {error_cell(t, 'val_px_best')} "
                     f"({t.get('best_epoch')}) | {error_cell(t, 'val_px_last')} | {state} |")
    return lines
