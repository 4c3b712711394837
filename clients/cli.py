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
import sys
from dataclasses import dataclass


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
    Command("train", "xyzcyl.model_export.commands.train", "train one stage (occ | render) of the network", "train"),
    Command("eval", "xyzcyl.model_export.commands.eval", "novel-view metrics of a model or a baseline", "train"),
    Command("export", "xyzcyl.model_export.commands.export", "export a checkpoint to an ONNX model folder", "train"),
    Command("import-model", "xyzcyl.model_export.commands.import_model",
            "a model folder back to a training checkpoint (exact weights)", "train"),
    Command("serve", "xyzcyl.server.commands.serve", "run the HTTP service (FastAPI + uvicorn)", "server"),
    Command("client", "xyzcyl.clients.commands.client",
            "talk to a running server: reconstruct, render, path, gaussians, scenes, delete", "client"),
)


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, Command]]:
    parser = argparse.ArgumentParser(
        prog="xyzcyl",
        description="XYZCylinder: feed-forward 3D Gaussian Splatting for any surround-camera rig.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    table = {}
    for cmd in COMMANDS:
        table[cmd.name] = cmd
        # add_help=False: the real parser is built lazily, which then handles -h itself.
        sub.add_parser(cmd.name, help=cmd.help, add_help=False)
    return parser, table


def _load(cmd: Command):
    try:
        return importlib.import_module(cmd.module)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("xyzcyl"):
            raise
        hint = f" (pip install 'xyzcyl[{cmd.extra}]')" if cmd.extra else ""
        raise SystemExit(f"xyzcyl {cmd.name}: missing dependency {exc.name!r}{hint}") from exc


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, table = build_parser()
    if not argv or argv[0] not in table:
        parser.parse_args(argv)  # prints help / usage error for unknown commands
        parser.print_help()
        return 2
    cmd = table[argv[0]]
    module = _load(cmd)
    sub = argparse.ArgumentParser(prog=f"xyzcyl {cmd.name}", description=cmd.help)
    module.add_arguments(sub)
    args = sub.parse_args(argv[1:])
    return int(module.run(args) or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
