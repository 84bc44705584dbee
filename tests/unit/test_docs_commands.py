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


def _named():
    for place in PLACES:
        for n, snippet in _snippets((ROOT / place).read_text()):
            m = _CALL.match(snippet)
            if m:
                yield place, n, [w for w in m.groups() if w]


def test_every_command_the_docs_name_exists():
    commands = _commands()
    missing = []
    seen = 0
    for place, n, words in _named():
        command = words[0]
        seen += 1
        if command not in commands or (
                commands[command] and len(words) > 1
                and words[1] not in commands[command]):
            missing.append(f"{place}:{n}: flowloop {' '.join(words)}")
    assert seen > 20          # the scan finds the docs' commands
    assert missing == []


def test_the_scan_finds_a_missing_action():
    commands = _commands()
    assert "activate" in commands["profile"]
    assert "frobnicate" not in commands["profile"]
