"""Arguments and set-up shared by the torch subcommands (train, eval)."""

from __future__ import annotations

import argparse


def add_runtime_arguments(parser: argparse.ArgumentParser) -> None:
    """--lpips-backbone/--lpips-lin/--lpips-net (local LPIPS weights), --threads, --quiet."""
    parser.add_argument("--lpips-backbone", default=None, help="local VGG16/AlexNet features state dict")
    parser.add_argument("--lpips-lin", default=None, help="local LPIPS v0.1 linear-layer weights")
    parser.add_argument("--lpips-net", default="vgg", choices=("vgg", "alex"),
                        help="LPIPS backbone: vgg (default) or alex")
    parser.add_argument("--threads", type=int, default=None,
                        help="CPU threads of torch and of the numba renderer (default: all cores)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def set_threads(threads: int | None) -> None:
    """Apply --threads to torch and to numba (the splatting kernels; at most numba's pool size, the core count
    unless NUMBA_NUM_THREADS says otherwise); ValueError naming the field when it is < 1."""
    if threads is None:
        return
    if threads < 1:
        raise ValueError(f"threads: must be >= 1, got {threads}")
    import numba
    import torch

    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
