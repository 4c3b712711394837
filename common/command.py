"""What every layer's `xyzcyl` subcommands share: their declaration (``Command``) and their parser (``Parser``).

Each layer declares its subcommands in its ``commands`` package (``runtime/commands``, ``model_export/commands``,
``server/commands``, ``clients/commands``: ``COMMANDS``, a tuple of ``Command``); the ``xyzcyl`` console script
(``xyzcyl.cli``, cli.py at the top of the repository) gathers them. A command's ``load`` imports its module only
when the command runs (a function with a plain ``from . import module``), so ``xyzcyl --help`` is instant and
imports no torch. The module provides:

    add_arguments(parser: argparse.ArgumentParser) -> None
    run(args: argparse.Namespace) -> int          # process exit status

Light on purpose: argparse, re and dataclasses, and xyzcyl.common.poses (its number test, numpy inside its
functions), like the rest of xyzcyl.common.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

from .poses import is_number


@dataclass(frozen=True)
class Command:
    """One `xyzcyl` subcommand: ``name`` on the command line, one line of ``help``, ``load`` (imports and returns
    the module with add_arguments and run), ``extra`` the pip extra that provides its dependencies (named in the
    one-line error when one is missing; None: the base install has them)."""

    name: str
    help: str
    load: Callable[[], ModuleType]
    extra: str | None = None


# What looks like a negative number (a value, not an option): "-" then a digit, or "-." then a digit -- the pattern
# of Python 3.14's argparse (gh-124823). Python 3.11-3.13 use '^-\d+$|^-\d*\.\d+$', which takes "-1e-05" (how
# numpy prints poses) for an option: `--cam-to-world ... -1e-05 ...` -> "expected 16 arguments".
NEGATIVE_NUMBER = re.compile(r"-\.?\d")
# A scene id that starts with "-" (22 URL-safe characters: 1 id in 64 did, before the service stopped making them;
# `xyzcyl batch` keys still may) is a value too: `xyzcyl client render -Ab3... --camera X` read it as an unknown
# option ("the following arguments are required: SCENE_ID"), and "-hAb3..." as -h with an argument. No option of
# ours has that form (a test holds it).
SCENE_ID_LIKE = re.compile(r"-[A-Za-z0-9_-]{21}$")


class Parser(argparse.ArgumentParser):
    """The parser of every xyzcyl command (sub-parsers inherit the class):

    - negative numbers in any float notation are values (``--forward -2e0``, ``--cam-to-world ... -1e-05 ...``),
      and so is a scene id that starts with "-" (SCENE_ID_LIKE);
    - ``--opt=V1 V2 ...`` for an option taking several values is read as ``--opt V1 V2 ...`` (argparse gives the
      ``=`` form one value only), so ``--cam-to-world=0 0 1 5 ...`` works as written;
    - an option whose action has ``numbers = N`` (a matrix flag, common/poses.py) takes N numbers
      in a row, or one value that is not a number (a JSON list, a file), as its one value and nothing after it,
      so positional arguments may follow as they could with ``nargs=N`` (fewer numbers are all given to the
      action, which names the count in its error);
    - the parsers of its sub-commands (``xyzcyl client render``) refuse an argument they do not know themselves,
      with their own usage, exit status 2 (argparse hands it to the parent, whose usage,
      ``xyzcyl client [-h] ACTION``, said nothing about the action's flags).
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_NUMBER     # the attribute argparse consults (no public API)

    def parse_known_args(self, args=None, namespace=None):
        args = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(self._prepare(args), namespace)

    def _parse_optional(self, arg_string):
        # a scene id that starts with "-" is a positional value, before argparse tries it as a short option with
        # its argument attached (-h, -q) or as an unknown option (argparse's own method; no public API)
        if SCENE_ID_LIKE.match(arg_string) and arg_string not in self._option_string_actions:
            return None
        return super()._parse_optional(arg_string)

    def add_subparsers(self, **kwargs):
        kwargs.setdefault("parser_class", SubParser)
        return super().add_subparsers(**kwargs)

    def _prepare(self, args: list[str]) -> list[str]:
        out: list[str] = []
        i = 0
        while i < len(args):
            a = args[i]
            if a == "--":
                return out + args[i:]
            flag, eq, value = a.partition("=") if a.startswith("--") else (a, "", "")
            action = self._option_string_actions.get(flag)
            if action is None or not _several(action):
                out.append(a)
                i += 1
                continue
            rest = ([value] if eq else []) + args[i + 1:]
            n = getattr(action, "numbers", None)
            if n and len(rest) >= n and all(is_number(t) for t in rest[:n]):      # N numbers: one value
                out.append(f"{flag}={' '.join(rest[:n])}")
                i += 1 + n - (1 if eq else 0)
                continue
            if n and rest and not is_number(rest[0]) and (eq or not rest[0].startswith("-")):  # a file, a list
                out.append(f"{flag}={rest[0]}")
                i += 1 if eq else 2
                continue
            out += [flag, value] if eq else [a]
            i += 1
        return out


class SubParser(Parser):
    """The parser of a sub-command (an action of ``xyzcyl client``): an argument it does not know is its error, with
    its usage, not its parent's."""

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace, extras


def _several(action: argparse.Action) -> bool:
    return action.nargs in ("+", "*") or (isinstance(action.nargs, int) and action.nargs > 1)


def command_parser(cmd: Command) -> tuple[Parser, ModuleType]:
    """The parser of one subcommand and its module (imported here; ModuleNotFoundError if a dependency of the
    module itself is missing)."""
    module = cmd.load()
    sub = Parser(prog=f"xyzcyl {cmd.name}", description=cmd.help)
    module.add_arguments(sub)
    return sub, module


def missing_dependency(cmd: Command, exc: ModuleNotFoundError) -> str:
    """The one line for a command whose optional dependency is not installed, naming the extra to install."""
    hint = f" (pip install 'xyzcyl[{cmd.extra}]')" if cmd.extra else ""
    return f"xyzcyl {cmd.name}: missing dependency {exc.name!r}{hint}"


def is_ours(exc: ModuleNotFoundError) -> bool:
    """A module of xyzcyl itself is missing: a bug or a broken install, shown with its traceback."""
    return not exc.name or exc.name.split(".")[0] == "xyzcyl"


def run_command(cmd: Command, argv: list[str]) -> int:
    """Parse ``argv`` (the arguments after the command's name) with the command's parser and run it; its exit
    status. A dependency that the command imports lazily (torch for train/eval/export-model/import-model, fastapi
    for serve, httpx for client) is missing in this install: one line naming the extra, exit 2, at whichever step
    the command first imports it (module, parser or run)."""
    try:
        sub, module = command_parser(cmd)
        args = sub.parse_args(argv)
        return int(module.run(args) or 0)
    except ModuleNotFoundError as exc:
        if is_ours(exc):
            raise
        print(missing_dependency(cmd, exc), file=sys.stderr)
        return 2


__all__ = ["NEGATIVE_NUMBER", "SCENE_ID_LIKE", "Command", "Parser", "SubParser", "command_parser",
           "is_ours", "missing_dependency", "run_command"]
