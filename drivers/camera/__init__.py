"""Camera adapters: the virtual cell's rendered camera (``sim``), OpenCV devices and files
(``opencv``), GigE Vision / USB3 Vision through Aravis (``aravis``). Each is a ``drivers.base.CameraBase``;
``drivers.registry`` opens them by kind. Public names are imported on first use (optional
libraries such as Aravis load only when asked for).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.lazy import lazy_getattr

if TYPE_CHECKING:
    from drivers.camera.aravis import AravisCamera
    from drivers.camera.aravis_formats import AravisCameraSettings
    from drivers.camera.opencv import OpenCVCamera, OpenCVCameraSettings
    from drivers.camera.sim import SimCamera, SimCameraSettings

__all__ = [
    "AravisCamera",
    "AravisCameraSettings",
    "OpenCVCamera",
    "OpenCVCameraSettings",
    "SimCamera",
    "SimCameraSettings",
]

__getattr__ = lazy_getattr(__name__, {
    "SimCamera": "drivers.camera.sim",
    "SimCameraSettings": "drivers.camera.sim",
    "OpenCVCamera": "drivers.camera.opencv",
    "OpenCVCameraSettings": "drivers.camera.opencv",
    "AravisCamera": "drivers.camera.aravis",
    "AravisCameraSettings": "drivers.camera.aravis_formats",
})
"""Public names imported on first use (PEP 562): importing the package stays cheap and free of cycles."""
