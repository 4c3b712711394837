"""The detail layer's command-line flags, shared by `xyzcyl reconstruct`, `eval-real` and `lidar-eval`:
``--detail-stride N`` and ``--no-detail`` (mutually exclusive), turned into the ``detail=`` argument of
`Reconstructor.reconstruct` (runtime.detail.DetailOptions, or None for no detail layer)."""

from __future__ import annotations

import argparse

from xyzcyl.common.wire import DETAIL_STRIDE_MAX, DETAIL_STRIDE_MIN


def add_detail_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--detail-stride", type=int, default=None, metavar="N",
                       help="detail layer: one pixel-aligned Gaussian per N x N block of each input camera's pixels, "
                            f"{DETAIL_STRIDE_MIN}..{DETAIL_STRIDE_MAX} (default: the runtime's default, 2; docs/inference.md, \"Detail Gaussians\"). "
                            "Smaller = sharper renders, more Gaussians, slower")
    group.add_argument("--no-detail", action="store_true",
                       help="no detail layer: the model's Gaussians only (the cylinder's resolution)")


def detail_options(args: argparse.Namespace):
    """The DetailOptions the flags ask for (None: --no-detail); FieldError naming the flag (--detail-stride)."""
    from dataclasses import replace

    from ..detail import DetailError
    from ..errors import FieldError
    from ..inference import DEFAULT_DETAIL

    if args.no_detail:
        return None
    if args.detail_stride is None:
        return DEFAULT_DETAIL
    try:
        return replace(DEFAULT_DETAIL, stride=args.detail_stride)
    except DetailError as e:        # its field is detail.stride, set by this flag
        raise FieldError("--detail-stride", e.message) from None
