"""`xyzcyl` subcommands that need the train extra (torch): ``COMMANDS``, gathered by the `xyzcyl` console script
(xyzcyl.cli). Each module is imported only when its command runs (torch inside their functions)."""

from __future__ import annotations

from xyzcyl.common.command import Command


def _data():
    from . import data
    return data


def _train():
    from . import train
    return train


def _eval():
    from . import eval
    return eval


def _export_model():
    from . import export_model
    return export_model


def _import_model():
    from . import import_model
    return import_model


COMMANDS: tuple[Command, ...] = (
    Command("data", "synthetic training data: synth, gallery, synth-drive", _data, "train"),
    Command("train", "train one stage (occ | render | depth) of the network", _train, "train"),
    Command("eval", "novel-view metrics of a model or a baseline", _eval, "train"),
    Command("export-model", "export a training checkpoint to an ONNX model folder", _export_model, "train"),
    Command("import-model", "a model folder back to a training checkpoint (exact weights)", _import_model, "train"),
)

__all__ = ["COMMANDS"]
