"""MkDocs hooks: the stage reference is written from each stage's own argparse at build time (it cannot drift from
the code), and the figures the science pages show from pipelines/*/results are published beside them."""

from __future__ import annotations

import contextlib
import importlib
import io
from pathlib import Path

from mkdocs.structure.files import File

REPO = Path(__file__).resolve().parents[1]
MARK = "<!-- stage-options -->"


def stage_help(stage: str) -> str:
    """`python -m adlpipe.<stage> --help`, run in this process."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        importlib.import_module(f"adlpipe.{stage}").main(["--help"])
    return out.getvalue()


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ANN001 - MkDocs' objects
    if MARK not in markdown:
        return markdown
    from adlpipe.console import STAGES

    parts = [f"## {stage}\n\n```\n{stage_help(stage).rstrip()}\n```\n" for stage in STAGES]
    return markdown.replace(MARK, "\n".join(parts))


def on_files(files, config):  # noqa: ANN001, ANN201 - MkDocs' objects
    """The PNG figures of the committed results, at their repository paths (the pages link to them)."""
    for png in sorted((REPO / "pipelines").glob("*/results/*.png")):
        files.append(File(str(png.relative_to(REPO)), str(REPO), config["site_dir"], config["use_directory_urls"]))
    return files
