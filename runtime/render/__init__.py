"""CPU Gaussian splatting renderer (numpy + numba): forward, backward, reference, PLY / .splat I/O.

    from xyzcyl.runtime.camera import Camera
    from xyzcyl.runtime.render import Gaussians, render
    result = render(Gaussians.load_ply("scene.ply"), Camera(K=K, cam_to_ego=T, width=1600, height=900))

See docs/renderer.md for conventions, options and the algorithm."""

from ..compile_notice import install as _install_compile_notice
from .core import render, render_backward
from .gaussians import DEFAULT_MAX_POINTS, FIELDS, GaussianError, Gaussians
from .projection import RenderOptions
from .reference import render_reference
from .result import GaussianGrads, RenderResult

_install_compile_notice()      # one stderr line when a kernel compiles (not when it loads from the cache)

__all__ = [
           "DEFAULT_MAX_POINTS",
           "FIELDS",
           "GaussianError",
           "GaussianGrads",
           "Gaussians",
           "RenderOptions",
           "RenderResult",
           "render",
           "render_backward",
           "render_reference",
]
