"""Local `xyzcyl` subcommands backed by the runtime (no torch): ``COMMANDS``, gathered by the `xyzcyl` console script
(xyzcyl.cli). Each module is imported only when its command runs."""

from __future__ import annotations

from xyzcyl.common.command import Command


def _cylinder():
    from . import cylinder
    return cylinder


def _reconstruct():
    from . import reconstruct
    return reconstruct


def _render():
    from . import render
    return render


def _lidar_eval():
    from . import lidar_eval
    return lidar_eval


def _eval_real():
    from . import eval_real
    return eval_real


def _actors():
    from . import actors
    return actors


def _export():
    from . import export
    return export


COMMANDS: tuple[Command, ...] = (
    Command("cylinder", "project a rig's images onto the UCCM cylinder", _cylinder),
    Command("reconstruct", "rig.json + images -> scene folder of Gaussians and background (onnxruntime, no torch)",
            _reconstruct),
    Command("render", "render a Gaussian PLY or a scene folder from a camera pose", _render),
    Command("lidar-eval", "depth of a reconstruction against a LiDAR sweep of the same timestamp (no torch)",
            _lidar_eval),
    Command("eval-real", "input / novel views of real rigs (no torch)", _eval_real),
    Command("actors", "list a drive scene folder's actors (the moving objects a render can move, hide, insert)", _actors),
    Command("export", "export a scene folder for other tools: an AlpaSim scene artifact (USDZ)", _export),
)

__all__ = ["COMMANDS"]
