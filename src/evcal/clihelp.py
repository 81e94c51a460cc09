"""The help formatter of every ``evcal`` command: descriptions and epilogs as written, and
each option's default after its help text unless the text gives it already."""

from __future__ import annotations

import argparse

# actions whose default says nothing (a flag is off, a counter at zero, help and version)
_NO_DEFAULT = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._CountAction,
               argparse._HelpAction, argparse._VersionAction, argparse._StoreConstAction,
               argparse._AppendConstAction)


def shows_default(action: argparse.Action) -> bool:
    """Whether ``action``'s help gets ``(default: ...)`` appended: an option (not a
    positional) with a default worth saying whose help does not say it already."""
    text = action.help or ""
    if not action.option_strings or action.help == argparse.SUPPRESS:
        return False
    if isinstance(action, _NO_DEFAULT) or action.nargs == 0:
        return False
    if action.default is None or action.default is argparse.SUPPRESS or action.default == []:
        return False
    return "%(default)" not in text and "default" not in text.lower()


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Raw descriptions, and each option's default (:func:`shows_default`)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if shows_default(action):
            text += " (default: %(default)s)"
        return text
