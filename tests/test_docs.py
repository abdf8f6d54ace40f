"""The documentation holds together: every relative link and image in the Markdown pages at the
root and in ``docs/`` names a file (and a heading, where it names one) that exists, and every
``jamnav`` command line shown in a fenced code block of the README, ARCHITECTURE.md and
``docs/`` is one the command line's parser accepts. The commands are parsed, never run."""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import NamedTuple

import pytest

from jamnav.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
LINKED_PAGES = sorted([*ROOT.glob("*.md"), *(ROOT / "docs").glob("*.md")])
COMMAND_PAGES = [ROOT / "README.md", ROOT / "ARCHITECTURE.md",
                 *sorted((ROOT / "docs").glob("*.md"))]

_FENCE = re.compile(r"^```.*?^```[^\n]*$", re.MULTILINE | re.DOTALL)
_CODE_SPAN = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[[^\]]*\]\(\s*([^)\s]+)(?:\s+\"[^\"]*\")?\s*\)")
_HTML_IMAGE = re.compile(r"<img\s[^>]*src=\"([^\"]+)\"")
_HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.MULTILINE)
_JAMNAV_LINE = re.compile(r"^(\w+=\S*\s+)*(\S*/)?jamnav(\s|$)")
_SHELL_FENCES = ("", "sh", "bash", "shell", "console")
_ELISION = "..."  # a command shown with options left out: `jamnav up --web HOST:PORT ...`


def _prose(text: str) -> str:
    """``text`` without its fenced code blocks and code spans, where brackets are not links."""
    return _CODE_SPAN.sub("", _FENCE.sub("", text))


def heading_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: its text as shown, lower case, with every character
    but letters, digits, spaces, hyphens and underscores left out and spaces made hyphens."""
    shown = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "")
    return re.sub(r"[^\w\- ]", "", shown.lower()).replace(" ", "-")


def anchors_of(page: Path) -> set[str]:
    """Every heading anchor of ``page``; a repeated heading's n-th repeat gets ``-n``."""
    seen: dict[str, int] = {}
    anchors = set()
    for heading in _HEADING.findall(_FENCE.sub("", page.read_text(encoding="utf-8"))):
        anchor = heading_anchor(heading)
        anchors.add(f"{anchor}-{seen[anchor]}" if anchor in seen else anchor)
        seen[anchor] = seen.get(anchor, 0) + 1
    return anchors


def relative_links(page: Path) -> list[str]:
    """The targets of the links and images in ``page`` that point inside the repository."""
    prose = _prose(page.read_text(encoding="utf-8"))
    targets = _LINK.findall(prose) + _HTML_IMAGE.findall(prose)
    return [target for target in targets if not re.match(r"[a-z][a-z0-9+.-]*:", target)]


def broken(page: Path, target: str) -> str | None:
    """Why ``target``, linked from ``page``, does not resolve; None if it does."""
    path, _, anchor = target.partition("#")
    linked = (page.parent / path).resolve() if path else page
    where = page.relative_to(ROOT) if page.is_relative_to(ROOT) else page.name
    if not linked.exists():
        return f"{where}: {target}: no such file"
    if anchor and linked.suffix == ".md" and anchor not in anchors_of(linked):
        return f"{where}: {target}: no heading with that anchor"
    return None


@pytest.mark.parametrize("page", LINKED_PAGES, ids=lambda page: str(page.relative_to(ROOT)))
def test_every_relative_link_and_image_resolves(page):
    problems = [problem for target in relative_links(page) if (problem := broken(page, target))]
    assert not problems, "\n".join(problems)


def test_the_link_check_reads_links_as_github_does(tmp_path):
    (tmp_path / "a.png").write_bytes(b"")
    page = tmp_path / "page.md"
    page.write_text("# Table I, as produced (`jamnav table`, [file](a.png))\n\n"
                    "![a](a.png) [b](missing.md) `[c](in-code.md)` [d](https://x.org/e)\n"
                    "[f](#table-i-as-produced-jamnav-table-file) [g](#nowhere)\n"
                    "```\n[h](in-a-fence.md)\n```\n", encoding="utf-8")
    targets = relative_links(page)
    assert targets == ["a.png", "a.png", "missing.md", "#table-i-as-produced-jamnav-table-file",
                       "#nowhere"]
    assert [target for target in targets if broken(page, target)] == ["missing.md", "#nowhere"]


class Command(NamedTuple):
    where: str
    argv: list[str]


def _loop_values(block: str) -> dict[str, str]:
    """Each shell loop variable of a code block and the first value it takes: the commands are
    parsed as the loop's first pass runs them."""
    return {name: values.split()[0]
            for name, values in re.findall(r"\bfor\s+(\w+)\s+in\s+([^;\n]+);", block)}


def _jamnav_argv(line: str, loops: dict[str, str]) -> list[str] | None:
    """The arguments after ``jamnav`` on one shell command line (environment assignments
    before it, a comment and a trailing ``&`` after it left out); None for any other line."""
    if not _JAMNAV_LINE.match(line):
        return None
    line = re.sub(r"\$(\w+)", lambda found: loops.get(found.group(1), found.group(0)), line)
    words = shlex.split(line, comments=True)
    argv = words[[Path(word).name for word in words].index("jamnav") + 1:]
    while argv and argv[-1] in ("&", _ELISION):
        argv.pop()
    return argv


def commands_in(text: str, where: str) -> list[Command]:
    """Every ``jamnav`` command line in the shell (or unlabelled) fenced code blocks of
    ``text``, lines continued with a backslash joined."""
    commands = []
    for block in _FENCE.finditer(text):
        info, body = block.group(0).split("\n", 1)
        if info.strip("`").strip() not in _SHELL_FENCES:
            continue
        body = body.rsplit("\n", 1)[0]
        first_line = text.count("\n", 0, block.start()) + 2
        loops = _loop_values(body)
        lines = body.replace("\\\n", " ").split("\n")
        numbers = [first_line + index for index, line in enumerate(body.split("\n"))
                   if index == 0 or not body.split("\n")[index - 1].endswith("\\")]
        for number, line in zip(numbers, lines, strict=True):
            argv = _jamnav_argv(line.strip(), loops)
            if argv is not None:
                commands.append(Command(f"{where}:{number}", argv))
    return commands


DOCUMENTED = [command for page in COMMAND_PAGES if page.exists()
              for command in commands_in(page.read_text(encoding="utf-8"),
                                         str(page.relative_to(ROOT)))]


@pytest.mark.parametrize("command", DOCUMENTED, ids=[command.where for command in DOCUMENTED])
def test_a_documented_command_line_parses(command, capsys):
    try:
        build_parser().parse_args(command.argv)
    except SystemExit:
        pytest.fail(f"{command.where}: jamnav {shlex.join(command.argv)}: "
                    f"{capsys.readouterr().err.strip()}")


def test_the_command_lines_are_read_as_a_shell_reads_them():
    text = ("Run:\n\n```sh\njamnav up --uavs 4 \\\n    --run-dir runs/up   # a comment\n"
            "for seed in 0 1; do\n  OMP_NUM_THREADS=1 .venv/bin/jamnav eval --seed $seed &\ndone\n"
            "jamnav up --web 127.0.0.1:9000 ...\nzenoh get -s 'jamnav/**'\n```\n\n"
            "```mermaid\nflowchart LR\n    jamnav --> shared\n```\n")
    assert commands_in(text, "page.md") == [
        Command("page.md:4", ["up", "--uavs", "4", "--run-dir", "runs/up"]),
        Command("page.md:7", ["eval", "--seed", "0"]),
        Command("page.md:9", ["up", "--web", "127.0.0.1:9000"]),
    ]
