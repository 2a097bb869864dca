"""The README stays a front door: short, its links resolve, and its `urd` commands are real.

The command check parses each `urd ...` line of the fenced shell blocks with the real CLI
(typer's click command) without running it: the subcommand must exist, and its options,
arguments and their types must accept the line as written. The docs pages' shell blocks get
the same check. The README writes dataset and file names as plain words (DATASET, raw/,
a.tiff) rather than shell placeholders such as <dataset>, so no line is skipped.
"""

import re
import shlex
from pathlib import Path

import pytest
import typer.main

from urd.cli import app

try:                                   # newer typer releases ship their own copy of click
    from typer._click.exceptions import UsageError
except ImportError:
    from click.exceptions import UsageError

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
MAX_LINES = 200
SHELL_LANGUAGES = {"", "bash", "sh", "shell", "console"}
SEPARATORS = {"&&", "||", ";", "|"}


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of each fenced code block."""
    return [(m.group(1).strip().lower(), m.group(2)) for m in re.finditer(r"^```([^\n`]*)\n(.*?)^```", text, re.M | re.S)]


def prose(text: str) -> str:
    """The text without fenced blocks and inline code, where links are looked for."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)
    return re.sub(r"`[^`\n]*`", "", text)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower()).replace("_", "")
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", path.read_text(encoding="utf-8"), flags=re.M | re.S)
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, re.M):
        base = slug(heading)
        count = seen.get(base, 0)
        out.add(base if count == 0 else f"{base}-{count}")
        seen[base] = count + 1
    return out


def local_links(path: Path) -> list[str]:
    targets = re.findall(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", prose(path.read_text(encoding="utf-8")))
    return [t for t in targets if not re.match(r"^[a-z][a-z0-9+.-]*:", t, re.I)]     # http:, https:, mailto: ...


def urd_commands(path: Path) -> list[list[str]]:
    """The argument lists (after `urd`, or `-m urd.cli`) of every urd command in the page's shell blocks."""
    commands = []
    for language, body in fenced_blocks(path.read_text(encoding="utf-8")):
        if language not in SHELL_LANGUAGES:
            continue
        for line in body.splitlines():
            if "urd" not in line:
                continue
            segment: list[str] = []
            for token in shlex.split(line, comments=True) + [";"]:
                if token in SEPARATORS:
                    if segment and segment[0] == "urd":
                        commands.append(segment[1:])
                    elif "urd.cli" in segment and segment[segment.index("urd.cli") - 1] == "-m":   # torchrun ... -m urd.cli
                        commands.append(segment[segment.index("urd.cli") + 1:])
                    segment = []
                else:
                    segment.append(token)
    return commands


def parse(args: list[str]) -> None:
    """Resolve the (sub)commands of ``args`` and parse the rest with the leaf command, as `urd`
    would before running it; UsageError (bad option, argument, value or choice) propagates."""
    command = typer.main.get_command(app)
    ctx = command.make_context("urd", [], resilient_parsing=True)   # the root group, no command run
    with ctx:
        parent, rest, name = ctx, list(args), "urd"
        while hasattr(command, "get_command"):
            assert rest, f"urd {' '.join(args)}: names no subcommand of {name}"
            sub = command.get_command(parent, rest[0])
            assert sub is not None, f"urd {' '.join(args)}: {name} has no subcommand {rest[0]!r}"
            name, rest, command = rest[0], rest[1:], sub
            if hasattr(command, "get_command"):
                parent = command.make_context(name, [], parent=parent, resilient_parsing=True)
        with command.make_context(name, rest, parent=parent):
            pass


def test_readme_is_at_most_200_lines():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_LINES, f"README.md has {len(lines)} lines; move detail into docs/"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_local_links_resolve(page):
    problems = []
    for link in local_links(page):
        target, _, anchor = link.partition("#")
        path = (page.parent / target).resolve() if target else page
        if not path.exists():
            problems.append(f"{link}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            problems.append(f"{link}: no heading with anchor #{anchor} in {path.relative_to(ROOT)}")
    assert not problems, f"{page.relative_to(ROOT)}: " + "; ".join(problems)


def test_readme_links_the_docs_pages():
    linked = {(ROOT / link.partition("#")[0]).resolve() for link in local_links(README)}
    missing = [p.name for p in PAGES[1:] if p.resolve() not in linked]
    assert not missing, f"README.md does not link {missing}"


def test_the_readme_shows_urd_commands():
    commands = urd_commands(README)
    assert len(commands) >= 8, commands
    assert {c[0] for c in commands} >= {"capture", "ingest", "separate", "report", "demo"}


@pytest.mark.parametrize("args", sorted({tuple(args) for page in PAGES for args in urd_commands(page)}),
                         ids=lambda a: "urd " + " ".join(a))
def test_urd_command_lines_parse(args):
    parse(args)


@pytest.mark.parametrize("args", [["capture", "DATASET", "--stage", "sim", "--bogus"], ["separat", "scene_01"],
                                  ["calibrate", "offsets"], ["separate", "--jobs", "0", "--all"],
                                  ["ingest", "raw/", "dataset", "more"]],
                         ids=lambda a: "urd " + " ".join(a))
def test_the_check_catches_wrong_lines(args):
    with pytest.raises((UsageError, AssertionError)):
        parse(args)
