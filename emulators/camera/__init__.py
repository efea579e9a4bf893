"""The emulated overhead camera: the world drawn from above and served as an MJPEG stream.

`render.py` is the pure part (a camera model and a renderer: scene -> picture, no I/O) and
`mjpeg.py` serves it over HTTP on the shared `EmulatorServer` loop, with its fault backdoor. A bench
adds a camera by handing over a function that returns the scene at the instant it is called:

    camera_model = CameraModel.overhead((0, 0, 400, 400), tilt_deg=5)
    camera = serve_camera(server, bench_scene, Renderer(camera_model, seed=1), fps=60)
    CameraDriver(camera.url, stamped=True)          # the driver reads it like any IP camera
    camera.occlude(1); camera.restore()             # faults, from any thread
"""

from rigctl.emulators.camera.mjpeg import CameraFaults, MjpegCamera, SceneSource, serve_camera
from rigctl.emulators.camera.render import (
    PAPER_FPS,
    PAPER_RESOLUTION,
    Appearance,
    CameraModel,
    Renderer,
    Scene,
)

__all__ = [
    "PAPER_FPS",
    "PAPER_RESOLUTION",
    "Appearance",
    "CameraFaults",
    "CameraModel",
    "MjpegCamera",
    "Renderer",
    "Scene",
    "SceneSource",
    "serve_camera",
]
