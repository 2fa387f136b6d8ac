"""The docs stay true to the code: every reference to a finding or a result (``docs/<page>.md#<anchor>``)
names a heading that exists, and every documented command line is one the CLI accepts."""

import contextlib
import dataclasses
import importlib
import io
import re
from pathlib import Path

import pytest
import tyro

ROOT = Path(__file__).resolve().parents[1]
REF = re.compile(r"docs/([\w-]+\.md)#([\w-]+)")
LINK = re.compile(r"\]\((?:\.\./)?(?:docs/)?([\w-]+\.md)#([\w-]+)\)")


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors: the heading lower-cased, punctuation but hyphens and underscores dropped, spaces
    to hyphens."""
    out = set()
    for line in page.read_text().splitlines():
        m = re.match(r"#+\s+(.*)", line)
        if m:
            out.add(re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-"))
    return out


def test_every_cited_anchor_exists():
    anchors = {p.name: _anchors(p) for p in (ROOT / "docs").glob("*.md")}
    sources = [*ROOT.joinpath("src").rglob("*.py"), *ROOT.joinpath("tests").rglob("*.py"),
               *ROOT.joinpath("docs").glob("*.md"), ROOT / "README.md"]
    missing = []
    for path in sources:
        text = path.read_text()
        for page, anchor in {*REF.findall(text), *LINK.findall(text)}:
            if anchor not in anchors.get(page, set()):
                missing.append(f"{path.relative_to(ROOT)}: {page}#{anchor}")
    assert not missing, "references to missing headings:\n" + "\n".join(sorted(set(missing)))


def test_no_page_ships_a_placeholder():
    """A page a user reads never holds a stand-in for text or figures still to come."""
    marker = re.compile(r"(?<![\w-])[A-Z_]*(PLACEHOLDER|TODO|TBD|FIXME|XXX)\b")
    found = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}"
             for p in [*ROOT.joinpath("docs").glob("*.md"), ROOT / "README.md"]
             for i, line in enumerate(p.read_text().splitlines(), 1) if marker.search(line)]
    assert not found, "placeholders:\n" + "\n".join(found)


def _options(cls: type) -> set[str]:
    """Every option a command's config accepts, read from tyro's help as a user would see it, with each
    choice of a choice field (``--executor fixed``) asked for its own options."""
    from pivla.cli.app import TYRO_CONFIG, _choice_fields

    found = set()
    choices = _choice_fields(cls) if dataclasses.is_dataclass(cls) else {}
    for prefix in [[], *([f"{field}:{kind}"] for field, kinds in choices.items() for kind in kinds)]:
        text = io.StringIO()
        with contextlib.redirect_stdout(text), pytest.raises(SystemExit):
            tyro.cli(cls, args=[*prefix, "--help"], config=TYRO_CONFIG)
        found |= set(re.findall(r"(?<![\w-])--[a-z][\w.-]*", text.getvalue()))
    return found | {f"--{field}" for field in choices}


def _documented_commands() -> list[tuple[str, str]]:
    """(where, command) for every `pivla ...` in backticks (spans may wrap lines) or at the start of a line in a
    code block of the docs and the README."""
    out = []
    for page in [*ROOT.joinpath("docs").glob("*.md"), ROOT / "README.md"]:
        text = page.read_text()
        spans = [(m.start(), m.group(1)) for m in re.finditer(r"`(?:[A-Z_]+=\S+ )*(pivla [^`]+)`", text)]
        fences = [m.span() for m in re.finditer(r"^```.*?^```", text, re.M | re.S)]
        spans += [(m.start(), m.group(1)) for m in re.finditer(r"^(?:\$ )?(?:[A-Z_]+=\S+ )*(pivla .+)$", text, re.M)
                  if any(a <= m.start() < b for a, b in fences)]
        out += [(f"{page.name}:{text.count(chr(10), 0, at) + 1}", " ".join(cmd.split())) for at, cmd in spans]
    return out


def test_documented_commands_use_options_the_cli_has(monkeypatch):
    """A command line in the docs names an existing command and only options it accepts, so a reader can
    paste it (placeholders such as DIR are not checked as values)."""
    monkeypatch.setenv("COLUMNS", "200")  # help lines long enough that no option name is wrapped
    from pivla.cli import COMMANDS
    from pivla.cli.app import Group, command_target

    options: dict[tuple[str, ...], set[str]] = {}
    wrong = []
    for where, cmd in _documented_commands():
        words, node, path = cmd.split()[1:], COMMANDS, []  # node: a group's commands or the command
        while words and isinstance(node, dict) and words[0] in node:
            path.append(words.pop(0))
            node = node[path[-1]].commands if isinstance(node[path[-1]], Group) else node[path[-1]]
        if isinstance(node, dict):  # a group, alone or with alternatives (`bench infer|train`)
            if words and re.fullmatch(r"[a-z][a-z|-]*", words[0]) and not set(words[0].split("|")) <= set(node):
                wrong.append(f"{where}: `{cmd}`: no such command")
            continue
        if tuple(path) not in options:
            options[tuple(path)] = _options(command_target(node)[1])
        known = {o.replace("_", "-") for o in options[tuple(path)]}
        for flag in re.findall(r"(?<![\w-])--[a-z][\w.-]*", " ".join(words)):
            if flag.replace("_", "-") not in known and flag not in ("--help", "--version"):
                wrong.append(f"{where}: `{cmd}`: {' '.join(path)} has no {flag}")
    assert not wrong, "documented commands the CLI would refuse:\n" + "\n".join(wrong)


def test_documented_python_names_and_files_exist():
    """Every `pivla.module.name` the docs cite imports and has that attribute, and every source file they
    name exists: a reader who follows one lands on code."""
    pages = [*ROOT.joinpath("docs").glob("*.md"), ROOT / "README.md"]
    wrong = []
    for page in pages:
        text = page.read_text()
        for dotted in sorted(set(re.findall(r"`(pivla(?:\.\w+)+)", text))):
            parts = dotted.split(".")
            for cut in range(len(parts), 0, -1):
                try:
                    obj = importlib.import_module(".".join(parts[:cut]))
                    break
                except ModuleNotFoundError:
                    continue
            try:
                for name in parts[cut:]:
                    obj = getattr(obj, name)
            except AttributeError:
                wrong.append(f"{page.name}: {dotted}")
        for path in sorted(set(re.findall(r"`((?:src/)?pivla/[\w/]+(?:\.\w+|/))`", text))):
            if not (ROOT / "src" / path.removeprefix("src/")).exists():
                wrong.append(f"{page.name}: {path}")
    assert not wrong, "docs name code that does not exist:\n" + "\n".join(wrong)
