"""The virtual camera's imaging: planar objects rendered exactly through a camera model, then
lighting, lens and sensor defects and 8-bit encoding.

Modules: ``renderer`` (``render``, ``render_scene``: inverse mapping, supersampled edges),
``sensor`` (``Imaging``, ``to_grey``: from reflectance to grey levels), and the renderer's private
helpers ``field`` (the ray field per camera), ``kernels`` and ``patterns`` (compiled loops, numba;
imported on first use), ``pool`` (threads and scratch memory). The sim camera
(``drivers/camera/sim.py``), the benchmarks and the tests use it; ``calibration`` does not (it
works on images, wherever they come from). Everything public is exported here:
``from drivers.sim.imaging import X`` is the interface.
"""

from drivers.sim.imaging.field import ray_field
from drivers.sim.imaging.renderer import (
    PlanarObject,
    RenderError,
    prepare,
    render,
    render_reflectance,
    render_scene,
)
from drivers.sim.imaging.sensor import (
    Imaging,
    ImagingError,
    defocus_sigma_px,
    motion_kernel,
    to_grey,
    vignetting_factor,
)

__all__ = [
    "Imaging", "ImagingError", "PlanarObject", "RenderError", "defocus_sigma_px", "motion_kernel",
    "prepare", "ray_field", "render", "render_reflectance", "render_scene", "to_grey", "vignetting_factor",
]
