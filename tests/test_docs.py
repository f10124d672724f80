"""Every command the documentation shows (README and docs/, in code blocks) parses with its stage's own argparse:
an option renamed or removed fails here, not in a newcomer's terminal."""

from __future__ import annotations

import functools
import importlib
import re
import shlex
from pathlib import Path

import pytest
from conftest import REPO

from adlpipe.console import STAGES

PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
COMMAND = re.compile(r"^(?:python -m adlpipe\.(\w+)|adlpipe (\w+))(\s.*)?$")


def documented_commands() -> list[tuple[str, str, list[str]]]:
    """(where, stage, arguments) of every `python -m adlpipe.X ...` or `adlpipe X ...` line in a code block, cut at
    a comment, a pipe, a redirection or a second command; lines with a placeholder (...) are left out."""
    out = []
    for page in PAGES:
        fence, held = False, ""
        for n, line in enumerate(page.read_text().splitlines(), 1):
            if line.lstrip().startswith("```"):
                fence, held = not fence, ""
                continue
            if fence and line.rstrip().endswith("\\"):  # a command continued on the next line
                held += line.rstrip()[:-1] + " "
                continue
            text, held = (held + line).strip(), ""
            if fence and text.startswith("cd ") and "&&" in text:
                text = text.split("&&", 1)[1].strip()
            m = COMMAND.match(text) if fence else None
            if m is None or "..." in text or m.group(1) == "results" or m.group(2) not in (None, *STAGES):
                continue
            words = shlex.split(m.group(3) or "", comments=True)
            cut = next((i for i, w in enumerate(words) if w in ("&&", "|", ";", ">", "2>", "||")), len(words))
            out.append((f"{page.relative_to(REPO)}:{n}", m.group(1) or m.group(2), words[:cut]))
    return out


COMMANDS = documented_commands()


def test_the_documentation_shows_commands_of_every_kind() -> None:
    stages = {stage for _, stage, _ in COMMANDS}
    assert len(COMMANDS) > 30 and {"ingest", "train", "replay", "doctor", "trials", "export"} <= stages


@pytest.mark.parametrize(("where", "stage", "argv"), COMMANDS, ids=[w for w, _, _ in COMMANDS])
def test_a_documented_command_parses(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, where: str,
                                     stage: str, argv: list[str]) -> None:
    monkeypatch.setenv("ADLPIPE_PARSE_ONLY", "1")
    monkeypatch.chdir(REPO)
    module = importlib.import_module(f"adlpipe.{stage}")
    with pytest.raises(SystemExit) as done:
        module.main(argv)
    assert done.value.code == 0, f"{where}: {stage} {' '.join(argv)}: {capsys.readouterr().err.strip()}"


def test_the_example_topic_map_names_every_key_at_the_codes_default() -> None:
    from dataclasses import fields

    import yaml

    from adlpipe.bags.topics import TopicMap

    example = REPO / "pipelines" / "topics.example.yaml"
    assert set(yaml.safe_load(example.read_text())) == {f.name for f in fields(TopicMap)}
    assert TopicMap.load(example) == TopicMap()


def test_readme_stays_a_front_page() -> None:
    """README is what adlpipe is, how to install and start, one results table and links: the studies' figures live
    in docs/science (findings.md), so the front page does not grow back into a lab notebook."""
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 140
    # the default run's table and the paragraph on its decision, nothing else
    assert sorted(set(re.findall(r"<!-- results:([\w-]+) -->", text))) == ["decision", "default"]
    assert "docs/science/findings.md" in text


PIPELINES = [REPO, *sorted(p.parent for p in (REPO / "pipelines").glob("*/dvc.yaml"))]


@functools.cache
def _stages(where: Path) -> list:
    from dvc.repo import Repo

    return list(Repo(str(where)).index.stages)


def test_every_documented_pipeline_depends_on_what_some_pipeline_makes() -> None:
    """A side pipeline (pipelines/*) reads the default's data and models by path: each of its inputs is a tracked
    file or what a stage of some pipeline writes (so a model the default stopped training is caught here, not by a
    user's dvc repro)."""
    import subprocess

    tracked = set(subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True,
                                 check=True).stdout.split())
    outs = {Path(o.fs_path) for where in PIPELINES for s in _stages(where) for o in s.outs}
    missing = []
    for where in PIPELINES[1:]:
        for stage in _stages(where):
            for dep in stage.deps:
                p = Path(dep.fs_path)
                if p.name == "params.yaml" or not p.is_relative_to(REPO):
                    continue
                rel = p.relative_to(REPO).as_posix()
                made = any(p == o or o in p.parents or p in o.parents for o in outs)
                if not (made or rel in tracked or any(t.startswith(rel + "/") for t in tracked)):
                    missing.append(f"{where.name}:{stage.name}: {rel}")
    assert not missing, missing


STAGE_COMMANDS = [(f"{where.relative_to(REPO).as_posix() or '.'}:{s.name}", where, cmd) for where in PIPELINES
                  for s in _stages(where) for cmd in [s.cmd] if isinstance(cmd, str)
                  and cmd.startswith("python -m adlpipe.") and "&&" not in cmd and "|" not in cmd]


@pytest.mark.parametrize(("where", "folder", "cmd"), STAGE_COMMANDS, ids=[w for w, _, _ in STAGE_COMMANDS])
def test_every_pipeline_stage_command_parses(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture,
                                            where: str, folder: Path, cmd: str) -> None:
    words = shlex.split(cmd)
    stage = words[2].removeprefix("adlpipe.")
    monkeypatch.setenv("ADLPIPE_PARSE_ONLY", "1")
    monkeypatch.chdir(folder)
    module = importlib.import_module(f"adlpipe.{stage}")
    with pytest.raises(SystemExit) as done:
        module.main(words[3:])
    assert done.value.code == 0, f"{where}: {cmd}: {capsys.readouterr().err.strip()}"
