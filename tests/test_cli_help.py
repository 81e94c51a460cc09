"""Every option of every ``evcal`` command has help text, and the help of every option with
a default says it (issue 40: a newcomer reads ``-h`` before anything else)."""

from __future__ import annotations

import argparse

import pytest

from evcal import cli
from evcal.clihelp import HelpFormatter, shows_default


class _Stop(Exception):
    pass


def _parser_of(command: str, monkeypatch: pytest.MonkeyPatch) -> argparse.ArgumentParser:
    """The parser ``evcal COMMAND`` parses its arguments with (caught as it parses)."""
    caught: list[argparse.ArgumentParser] = []

    def grab(self: argparse.ArgumentParser, *a: object, **k: object) -> None:
        caught.append(self)
        raise _Stop

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", grab)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", grab)
    with pytest.raises(_Stop):
        cli.main([command])
    return caught[0]


def _builtin() -> dict[str, argparse.ArgumentParser]:
    top = cli.build_parser()
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
    return {k: v for k, v in sub.choices.items() if k not in cli.DELEGATED}


def _problems(parser: argparse.ArgumentParser) -> list[str]:
    out = []
    fmt = HelpFormatter(parser.prog)
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._VersionAction |
                      argparse._SubParsersAction):
            continue
        name = "/".join(action.option_strings) or action.dest
        if action.help == argparse.SUPPRESS:
            continue  # an internal option, hidden on purpose (a worker's --supervised)
        if not action.help:
            out.append(f"{parser.prog} {name}: no help")
            continue
        text = fmt._get_help_string(action)
        if shows_default(action) and "(default:" not in text:
            out.append(f"{parser.prog} {name}: default not shown")
        if action.option_strings and action.default not in (None, False, 0, [],
                                                             argparse.SUPPRESS) \
                and action.nargs != 0 and "default" not in text.lower() \
                and not isinstance(action, argparse._CountAction):
            out.append(f"{parser.prog} {name}: default {action.default!r} not in its help")
    return out


@pytest.mark.parametrize("command", sorted(cli.DELEGATED))
def test_delegated_commands_have_help_and_defaults(command: str,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    assert _problems(_parser_of(command, monkeypatch)) == []


def test_builtin_commands_have_help_and_defaults() -> None:
    problems = [p for parser in _builtin().values() for p in _problems(parser)]
    assert problems == []


def test_the_default_is_appended_once() -> None:
    p = argparse.ArgumentParser(prog="x", formatter_class=HelpFormatter)
    p.add_argument("--rate", type=float, default=2.5, help="a rate")
    p.add_argument("--said", type=int, default=3, help="a count (default 3)")
    p.add_argument("--flag", action="store_true", help="a flag")
    text = p.format_help()
    assert "a rate (default: 2.5)" in text
    assert "(default 3)" in text
    assert "(default: 3)" not in text
    assert "a flag\n" in text
