"""`xyzcyl export`: a scene folder in the formats other tools open (USDZ, glTF, SPZ). Not available yet: the command
says so and exits 2.

The model's ONNX export, which `xyzcyl export --checkpoint` ran before, is `xyzcyl export-model` (the old spelling
still runs it, with a notice, until the next release: xyzcyl.cli)."""

from __future__ import annotations

import argparse
import sys

NOT_YET = ("xyzcyl export: scene export (USDZ, glTF, SPZ) is not available yet; "
           "a model's ONNX export is `xyzcyl export-model`")


def _not_yet(message: str = "") -> None:
    print(NOT_YET, file=sys.stderr)
    sys.exit(2)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("args", nargs="*", metavar="ARG",
                        help="(scene export is not available yet: any arguments are refused)")
    parser.error = _not_yet        # flags it does not know (there are none yet) get the same one line, exit 2


def run(args: argparse.Namespace) -> int:
    print(NOT_YET, file=sys.stderr)
    return 2
