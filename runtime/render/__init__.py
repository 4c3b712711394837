"""CPU Gaussian splatting renderer (numpy + numba): forward, backward, reference, PLY / .splat I/O.

    from xyzcyl.runtime.render import Gaussians, PinholeCamera, render
    result = render(Gaussians.load_ply("scene.ply"), PinholeCamera(K, cam_to_world, 1600, 900))

See docs/renderer.md for conventions, options and the algorithm."""

from ..compile_notice import install as _install_compile_notice
from .cameras import CameraError, EquirectCamera, PinholeCamera
from .core import render, render_backward
from .gaussians import DEFAULT_MAX_POINTS, GaussianError, Gaussians
from .projection import RenderOptions
from .reference import render_reference
from .result import GaussianGrads, RenderResult

_install_compile_notice()      # one stderr line when a kernel compiles (not when it loads from the cache)

__all__ = [
           "DEFAULT_MAX_POINTS",
           "CameraError",
           "EquirectCamera",
           "GaussianError",
           "GaussianGrads",
           "Gaussians",
           "PinholeCamera",
           "RenderOptions",
           "RenderResult",
           "render",
           "render_backward",
           "render_reference",
]
