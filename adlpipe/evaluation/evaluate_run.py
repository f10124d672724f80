"""An evaluation run from its configuration (`adlpipe evaluate` parses its options into an EvaluateConfig and calls
run_evaluation): every model's trajectory error and inference time on the test split at every sampler and step
count, from its best and last checkpoints, beside the blind floor; the details, metrics, plot data and Table 1
written atomically, each finished model journalled beside the details so a killed run resumes."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

import torch

from ..dataset import schema
from ..dataset.splits import load_split
from ..plumbing.atomic import json_text, write_all_atomic
from ..plumbing.errors import AdlError
from ..plumbing.journal import Journal, fingerprint
from ..plumbing.runtime import Placement, host
from ..policy.blind import BLIND
from ..policy.checkpoint import CHECKPOINTS
from .accuracy import blind_rows, evaluate_model, reference_modes
from .accuracy_tables import headline, steps_csv, table1

STEPS = [1, 2, 4, 8, 16]


@dataclass(frozen=True)
class EvaluateConfig:
    """What `adlpipe evaluate` was asked (its options, one field each: `adlpipe evaluate --help` says what each
    does)."""

    models: list[Path]
    data: Path
    split: Path  # the stage defaults it to split.json beside the data
    metrics: Path
    details: Path
    plots: Path
    table: Path
    placement: Placement = field(default_factory=Placement)
    steps: list[int] = field(default_factory=lambda: list(STEPS))
    fm_methods: list[str] = field(default_factory=lambda: ["euler"])
    dp_methods: list[str] = field(default_factory=lambda: ["ddpm", "ddim", "ddpm_trailing"])
    best_of: int = 8
    repeats: int = 20
    seed: int = 0
    threads: int = 0
    workers: int = 1


def _training_metrics(model_dir: Path) -> dict:
    """What training wrote (val px, convergence, optimiser steps); empty if it is not there."""
    try:
        return json.loads((model_dir / "metrics.json").read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def evaluate_models(c: EvaluateConfig, journal: Journal, test: list[str], image_px: int,
                    modes: dict[int, torch.Tensor], placement: Placement) -> tuple[dict[str, dict], dict[str, dict]]:
    """(model -> {"best": rows, "last": rows}, model -> what training wrote); a model the journal holds (a killed
    run had finished it) is taken from it, every other one goes into it once evaluated."""
    results: dict[str, dict] = {}
    training: dict[str, dict] = {}
    methods = {"fm": c.fm_methods, "ddpm": c.dp_methods}
    for d in c.models:
        if str(d) in journal.done:
            done = cast(dict, journal.done[str(d)])
            training[d.name], results[d.name] = done["training"], done["results"]
            continue
        training[d.name] = _training_metrics(d)
        last = evaluate_model(d, c.data, test, c.steps, methods, c.best_of, c.repeats, c.seed, image_px,
                              placement=placement, modes=modes)
        t = training[d.name]
        if t and t.get("best_epoch") == t.get("epochs"):
            best = last  # the best validation epoch was the last: best.pt holds model.pt's weights
        else:
            best = evaluate_model(d, c.data, test, c.steps, methods, c.best_of, c.repeats, c.seed, image_px,
                                  CHECKPOINTS["best"], timings=last, placement=placement, modes=modes)
        results[d.name] = {"best": best, "last": last}
        journal.add(str(d), {"training": training[d.name], "results": results[d.name]})
        top = min(best.values(), key=lambda r: r["px"])
        print(f"{d.name}: best checkpoint {top['px']:.2f} px / {top['cm']:.2f} cm ({top['method']}, "
              f"{top['steps']} steps){'' if training[d.name].get('converged') else ', not converged'}")
    return results, training


def run_evaluation(c: EvaluateConfig) -> None:
    """Evaluate every model of `c` and write the details, metrics, plot data and table."""
    if c.threads:
        torch.set_num_threads(c.threads)
    placement = c.placement
    split = load_split(c.split)
    if not split["test"]:
        raise AdlError("the test split is empty: record more episodes per task")
    with schema.open_dataset(c.data, split["test"]) as f:
        image_px = int(f[schema.EPISODES][split["test"][0]]["rgb"].shape[0])
    modes = reference_modes(c.data, split["test"], c.workers)
    for d in c.models:
        for name in CHECKPOINTS.values():
            if not (d / name).exists():
                raise AdlError(f"{d}: no {name}; train it first (python -m adlpipe.train)")
    journal = Journal(c.details, fingerprint(c, [d / n for d in c.models for n in CHECKPOINTS.values()], c.split,
                                             c.data))
    if journal.done:
        print(f"resuming: {len(journal.done)} model(s) evaluated before ({journal.path})")
    with journal:
        results, training = evaluate_models(c, journal, split["test"], image_px, modes, placement)
    try:
        blind = blind_rows(c.data, split, image_px, c.best_of)
        results[BLIND] = {"best": blind, "last": blind}
    except AdlError as exc:  # a test task without training episodes: no floor to state
        print(f"no blind baseline row: {exc}")
    title = "# Trajectory error and inference time on the test split\n\n"
    write_all_atomic({
        c.details: json_text({"n_test": len(split["test"]), "best_of": c.best_of, "training": training,
                              "mode_scenes": len(modes),
                              "device": str(placement.device), "host": host(placement.device),
                              "precision": placement.precision,
                              "compiled": placement.compile, "models": results}),
        c.metrics: json_text(headline(results, training, len(split["test"]))),
        c.plots: steps_csv(results, c.steps),
        c.table: title + table1(results, c.best_of, training)})
    journal.close()
    print(f"wrote {c.metrics}, {c.details}, {c.plots}, {c.table}")
