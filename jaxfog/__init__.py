"""jaxfog: a differentiable volumetric path tracer for homogeneous fog, in JAX.

Public surface: scene parts (`Camera`, `Sphere`, `Rectangle`, `Diffuse`, `Mirror`, `Glass`, `PointLight`,
`SpotLight`, `AreaLight`, `HenyeyGreenstein`, `HomogeneousMedium`, `Scene`), `render`, scene files
(`load_scene`, `SceneError`), image I/O (`write_exr`, `read_exr`, `write_png`), `check_finite(image)` and the
size limits' `LimitError`.
"""

from ._bsdf import AbstractBSDF as AbstractBSDF, Diffuse as Diffuse, Glass as Glass, Mirror as Mirror
from ._camera import Camera as Camera
from ._devices import use_cpu_cores as use_cpu_cores
from ._image import read_exr as read_exr, write_exr as write_exr, write_png as write_png
from ._lights import (
    AbstractLight as AbstractLight,
    AreaLight as AreaLight,
    PointLight as PointLight,
    SpotLight as SpotLight,
)
from ._medium import HomogeneousMedium as HomogeneousMedium
from ._phase import HenyeyGreenstein as HenyeyGreenstein
from ._render import render as render
from ._scene import Scene as Scene
from ._scene_io import SceneError as SceneError, load_scene as load_scene
from ._shapes import Rectangle as Rectangle, Sphere as Sphere
from ._validate import LimitError as LimitError, check_finite as check_finite

__version__ = "0.1.0"
