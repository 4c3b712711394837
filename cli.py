"""The `xyzcyl` console script (``xyzcyl.cli:entry``, then ``main``; ``python -m xyzcyl`` too): the subcommands
that each layer declares in its ``commands`` package, gathered in one parser.

    runtime/commands       cylinder, reconstruct, render, lidar-eval, eval-real, export    (base install)
    model_export/commands  data, train, eval, export-model, import-model                    (train extra)
    server/commands        serve                                                            (server extra)
    clients/commands       client                                                           (client extra)

A command's module is imported only when it runs (xyzcyl.common.command: ``Command``, ``Parser``), so
``xyzcyl --help`` is instant and never imports torch or numba, and a command whose optional dependency is missing
says which extra to install. This module sits above the layers (the only one that imports all four); none of them
imports it.
"""

from __future__ import annotations

import argparse
import sys

from xyzcyl.clients.commands import COMMANDS as CLIENT_COMMANDS
from xyzcyl.common.command import Command, Parser, command_parser, run_command
from xyzcyl.model_export.commands import COMMANDS as MODEL_EXPORT_COMMANDS
from xyzcyl.runtime.commands import COMMANDS as RUNTIME_COMMANDS
from xyzcyl.server.commands import COMMANDS as SERVER_COMMANDS

# In the order `xyzcyl --help` lists them: local (non-HTTP) commands first.
COMMANDS: tuple[Command, ...] = RUNTIME_COMMANDS + MODEL_EXPORT_COMMANDS + SERVER_COMMANDS + CLIENT_COMMANDS

# `xyzcyl export --checkpoint ...`, the model's ONNX export before `xyzcyl export` became the export of scenes:
# still run (as `xyzcyl export-model`), with this notice, for one release.
OLD_EXPORT_NOTICE = ("xyzcyl export --checkpoint is now `xyzcyl export-model`; "
                     "the old spelling goes in the next release")


def version() -> str:
    """The package's version (xyzcyl.common.version: the installed distribution's)."""
    from xyzcyl.common.version import __version__

    return __version__


def model_version() -> str:
    """One line on the default model (runtime.model_folder.default_model_dir: $XYZCYL_MODEL, else
    models/xyzcyl-cpu-v1 in the working folder, else in the source checkout): ``model: NAME VERSION (FOLDER)``
    from its model.json, ``model: not found (FOLDER)`` without one, ``model: unreadable (...)`` when model.json is
    not a model's. Reads model.json only (no numpy, numba, onnxruntime or torch); never raises."""
    try:
        from xyzcyl.runtime.model_folder import ModelError, default_model_dir, read_model_info
    except ImportError as e:      # a broken install: still print the package's version
        return f"model: unknown (the runtime does not import: {e})"
    folder = default_model_dir()
    if not (folder / "model.json").is_file():
        return f"model: not found ({folder})"
    try:
        info = read_model_info(folder)
        return f"model: {info.name} {info.version} ({folder})"
    except (ModelError, OSError, ValueError) as e:
        return f"model: unreadable ({e})"


class _Version(argparse.Action):
    """--version: the package's version and, beside it, the default model's own (model_version), read only when
    asked."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"xyzcyl {version()}\n{model_version()}")
        parser.exit()


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, Command]]:
    parser = Parser(
        prog="xyzcyl",
        description="XYZCylinder: feed-forward 3D Gaussian Splatting for any surround-camera rig.",
    )
    parser.add_argument("--version", action=_Version,
                        help="print the version of xyzcyl and of the default model (models/xyzcyl-cpu-v1 or "
                             "$XYZCYL_MODEL), and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    table = {}
    for cmd in COMMANDS:
        table[cmd.name] = cmd
        # add_help=False: the real parser is built lazily, which then handles -h itself.
        sub.add_parser(cmd.name, help=cmd.help, add_help=False)
    return parser, table


def _old_export(argv: list[str]) -> bool:
    """``argv`` is `xyzcyl export --checkpoint ...` (the model's export, before `export-model`)."""
    return argv[:1] == ["export"] and any(a == "--checkpoint" or a.startswith("--checkpoint=") for a in argv[1:])


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, table = build_parser()
    if not argv or argv[0] not in table:
        parser.parse_args(argv)  # prints help / usage error for unknown commands, --version
        parser.print_help()
        return 2
    if _old_export(argv):
        print(OLD_EXPORT_NOTICE, file=sys.stderr)
        argv = ["export-model", *argv[1:]]
    return run_command(table[argv[0]], argv[1:])


def entry() -> None:
    """The `xyzcyl` console script (and ``python -m xyzcyl``): the C heap set to keep freed memory for reuse
    (runtime.heap.keep_freed_memory: first thing, before numpy starts its threads, and for the processes this one
    starts), then ``main``. Tests call ``main`` in their own process, which keeps its heap as it is."""
    from xyzcyl.runtime.heap import keep_freed_memory

    keep_freed_memory()
    sys.exit(main())


__all__ = ["COMMANDS", "OLD_EXPORT_NOTICE", "Command", "Parser", "build_parser", "command_parser", "entry", "main",
           "model_version", "version"]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
