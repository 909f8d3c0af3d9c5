"""Every subcommand's `--help` shows every option's default (issue 16, item 9)."""

import argparse

import pytest

from jaxcal.cli import build_parser

PARSER = build_parser()
SUBCOMMANDS = next(a for a in PARSER._actions if isinstance(a, argparse._SubParsersAction)).choices


@pytest.mark.parametrize("name", sorted(SUBCOMMANDS))
def test_help_shows_every_default(name):
    sub = SUBCOMMANDS[name]
    for action in sub._actions:
        if not action.option_strings or action.required or isinstance(action, argparse._HelpAction):
            continue  # positional arguments and required options have no default
        entry = " ".join(sub._get_formatter()._format_action(action).split())  # the option's --help entry
        assert "default" in entry.lower(), (
            f"jaxcal {name} --help: the entry does not show its default: {entry!r}"
        )
        if action.default not in (None, argparse.SUPPRESS) and "(default: " in entry:
            assert f"(default: {action.default})" in entry, entry
