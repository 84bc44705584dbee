"""Every `flowloop COMMAND [ACTION]` that a doc, an example config, a macro or
the live page tells a user to run is a command the CLI has."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from flowloop.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "flowloop" / "host" / "page"
PLACES = (["README.md"]
          + [str(p.relative_to(ROOT)) for p in
             sorted((ROOT / "docs").glob("*.md"))
             + sorted((ROOT / "config").glob("*.cfg"))
             + sorted((ROOT / "macros").glob("*.cfg"))
             + sorted(PAGE.glob("*.js")) + sorted(PAGE.glob("*.html"))])
# A command as a user would type it: in a code span or block of a doc, after
# "$ ", or in parentheses or quotes in a config comment or the page.
_CALL = re.compile(r"^(?:\$ )?flowloop ([a-z][a-z-]*)(?: ([a-z][a-z-]*))?")
_SPAN = re.compile(r'`([^`]+)`|\(([^()]+)|"([^"]+)')


def _commands():
    """{command: set of its actions (empty: it has none)}."""
    parser = build_parser()
    sub = next(a for a in parser._actions
               if isinstance(a, argparse._SubParsersAction))
    out = {}
    for name, p in sub.choices.items():
        actions = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        out[name] = set(actions[0].choices) if actions else set()
    return out


def _snippets(text: str):
    fenced = False
    for n, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced or line.startswith("    "):
            yield n, line.strip()
        for m in _SPAN.finditer(line):
            yield n, (m[1] or m[2] or m[3]).strip()


def _named(text: str):
    for n, snippet in _snippets(text):
        m = _CALL.match(snippet)
        if m:
            yield n, [w for w in m.groups() if w]


def _missing(place: str, text: str, commands):
    """(commands named, the ones the CLI does not have) of one text."""
    named, missing = 0, []
    for n, words in _named(text):
        named += 1
        command = words[0]
        if command not in commands or (
                commands[command] and len(words) > 1
                and words[1] not in commands[command]):
            missing.append(f"{place}:{n}: flowloop {' '.join(words)}")
    return named, missing


def test_every_command_the_docs_name_exists():
    commands = _commands()
    seen, missing = 0, []
    for place in PLACES:
        named, bad = _missing(place, (ROOT / place).read_text(), commands)
        seen += named
        missing += bad
    assert seen > 20          # the scan finds the docs' commands
    assert missing == []


def test_the_scan_reports_a_command_or_action_the_cli_lacks():
    text = ("Run `flowloop profile frobnicate NAME` then\n"
            "    $ flowloop annotate part.gcode\n"
            "# (flowloop bake part.gcode) in a config comment\n"
            "prose: flowloop is a package, `flowloop profile activate NAME`\n")
    named, missing = _missing("x.md", text, _commands())
    assert named == 4
    assert missing == ["x.md:1: flowloop profile frobnicate",
                       "x.md:3: flowloop bake part"]
