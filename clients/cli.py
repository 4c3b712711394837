"""The `xyzcyl` console script: a thin, lazy dispatcher.

Each subcommand lives in the package whose layer it belongs to and is imported only when it is run, so
`xyzcyl --help` is instant and never imports torch, and a command whose optional dependencies are missing
says which extra to install (see docs/cli.md).

A command module provides:
    add_arguments(parser: argparse.ArgumentParser) -> None
    run(args: argparse.Namespace) -> int          # process exit status
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from dataclasses import dataclass

from xyzcyl.common.poses import is_number

# What looks like a negative number (a value, not an option): "-" then a digit, or "-." then a digit -- the pattern
# of Python 3.14's argparse (gh-124823). Python 3.11-3.13 use '^-\d+$|^-\d*\.\d+$', which takes "-1e-05" (how
# numpy prints poses) for an option: `--cam-to-world ... -1e-05 ...` -> "expected 16 arguments".
NEGATIVE_NUMBER = re.compile(r"-\.?\d")


class Parser(argparse.ArgumentParser):
    """The parser of every xyzcyl command (sub-parsers inherit the class):

    - negative numbers in any float notation are values (``--forward -2e0``, ``--cam-to-world ... -1e-05 ...``);
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


def version() -> str:
    """The installed distribution's version ("unknown" when run from a tree that is not installed)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("xyzcyl")
    except PackageNotFoundError:
        return "unknown"


def model_version() -> str:
    """One line on the default model (runtime.inference.default_model_dir: $XYZCYL_MODEL, else
    models/xyzcyl-cpu-v1 in the working folder, else in the source checkout): ``model: NAME VERSION (FOLDER)``
    from its model.json, ``model: not found (FOLDER)`` without one, ``model: unreadable (...)`` when model.json is
    not a model's. Reads model.json only (no ONNX session, no torch); never raises."""
    try:
        from xyzcyl.runtime.inference import ModelError, default_model_dir, read_model_info
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
    """--version: the package's version and the default model's (model_version), read only when asked."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"xyzcyl {version()}\n{model_version()}")
        parser.exit()


@dataclass(frozen=True)
class Command:
    name: str
    module: str  # dotted module path providing add_arguments() and run()
    help: str
    extra: str | None = None  # pip extra that provides its dependencies, named in the error if missing


# One line per subcommand. Local (non-HTTP) commands live in runtime/ or model_export/.
COMMANDS: tuple[Command, ...] = (
    Command("cylinder", "xyzcyl.runtime.commands.cylinder", "project a rig's images onto the UCCM cylinder"),
    Command("reconstruct", "xyzcyl.runtime.commands.reconstruct",
            "rig.json + images -> scene folder of Gaussians and background (onnxruntime, no torch)"),
    Command("render", "xyzcyl.runtime.commands.render", "render a Gaussian PLY or a scene folder from a camera pose"),
    Command("lidar-eval", "xyzcyl.runtime.commands.lidar_eval",
            "depth of a reconstruction against a LiDAR sweep of the same timestamp (no torch)"),
    Command("eval-real", "xyzcyl.runtime.commands.eval_real", "input / novel views of real rigs (no torch)"),
    Command("data", "xyzcyl.model_export.commands.data", "synthetic training data: synth, gallery", "train"),
    Command("train", "xyzcyl.model_export.commands.train", "train one stage (occ | render | depth) of the network",
            "train"),
    Command("eval", "xyzcyl.model_export.commands.eval", "novel-view metrics of a model or a baseline", "train"),
    Command("export", "xyzcyl.model_export.commands.export", "export a checkpoint to an ONNX model folder", "train"),
    Command("import-model", "xyzcyl.model_export.commands.import_model",
            "a model folder back to a training checkpoint (exact weights)", "train"),
    Command("serve", "xyzcyl.server.commands.serve", "run the HTTP service (FastAPI + uvicorn)", "server"),
    Command("client", "xyzcyl.clients.commands.client",
            "talk to a running server: reconstruct, render, path, gaussians, scenes, delete", "client"),
)


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


def missing_dependency(cmd: Command, exc: ModuleNotFoundError) -> str:
    """The one line for a command whose optional dependency is not installed, naming the extra to install."""
    hint = f" (pip install 'xyzcyl[{cmd.extra}]')" if cmd.extra else ""
    return f"xyzcyl {cmd.name}: missing dependency {exc.name!r}{hint}"


def _is_ours(exc: ModuleNotFoundError) -> bool:
    """A module of xyzcyl itself is missing: a bug or a broken install, shown with its traceback."""
    return not exc.name or exc.name.split(".")[0] == "xyzcyl"


def command_parser(cmd: Command) -> tuple[Parser, object]:
    """The parser of one subcommand and its module (imported here; ModuleNotFoundError if a dependency of the
    module itself is missing)."""
    module = importlib.import_module(cmd.module)
    sub = Parser(prog=f"xyzcyl {cmd.name}", description=cmd.help)
    module.add_arguments(sub)
    return sub, module


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, table = build_parser()
    if not argv or argv[0] not in table:
        parser.parse_args(argv)  # prints help / usage error for unknown commands, --version
        parser.print_help()
        return 2
    cmd = table[argv[0]]
    # A dependency that the command imports lazily (torch for train/eval/export/import-model, fastapi for serve,
    # httpx for client) is missing in this install: one line naming the extra, exit 2, at whichever step the
    # command first imports it (module, parser or run).
    try:
        sub, module = command_parser(cmd)
        args = sub.parse_args(argv[1:])
        return int(module.run(args) or 0)
    except ModuleNotFoundError as exc:
        if _is_ours(exc):
            raise
        print(missing_dependency(cmd, exc), file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
