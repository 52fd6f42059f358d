"""Every command explains itself: a description per subcommand, help text on every option
and argument, the default shown wherever there is one, and -v taken after the subcommand."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from service.commands.cli import build_parser
from tests.support.paths import ROOT

PARSER = build_parser()
SUBPARSERS: dict[str, argparse.ArgumentParser] = next(
    a.choices for a in PARSER._actions if isinstance(a, argparse._SubParsersAction)
)


def _options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in parser._actions if not isinstance(a, argparse._HelpAction)]


@pytest.mark.parametrize("name", sorted(SUBPARSERS))
def test_every_option_has_help_and_its_default(name):
    parser = SUBPARSERS[name]
    assert parser.description and len(parser.description) > 40, name
    formatter = parser._get_formatter()
    for action in _options(parser):
        text = formatter._expand_help(action) if action.help else ""
        label = action.option_strings or action.dest
        assert text.strip(), (name, label)
        has_default = action.default not in (None, False, argparse.SUPPRESS) and action.nargs != 0
        if has_default:
            assert "(default" in text, (name, label, text)


@pytest.mark.parametrize("name", sorted(SUBPARSERS))
def test_help_of_the_console_script(name):
    """The real console script prints the help, with the description, and exits 0."""
    out = subprocess.run(
        [sys.executable, "-m", "service", name, "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0
    first_words = " ".join(SUBPARSERS[name].description.split()[:4])
    assert first_words in " ".join(out.stdout.split())


def test_verbose_after_the_subcommand():
    args = PARSER.parse_args(["solve", "-v", "-v", "obs", "nav"])
    assert args.verbose == 2
    assert PARSER.parse_args(["-v", "solve", "obs", "nav"]).verbose == 1
    assert PARSER.parse_args(["solve", "obs", "nav"]).verbose == 0
