"""jaxfog: a differentiable volumetric path tracer for fog (homogeneous, height and density-grid media), in JAX.

Public surface: scene parts (`Camera`, `Sphere`, `Rectangle`, `Mesh`, `Diffuse`, `Mirror`, `Glass`, `PointLight`,
`SpotLight`, `AreaLight`, `DirectionalLight`, `HenyeyGreenstein`, `Rayleigh`, `TwoTermHG`, `Draine`, `Droplet`,
`HomogeneousMedium`, `HeightFog`, `GridMedium`, `Scene`) and their interfaces
(`AbstractBSDF`, `AbstractLobeBSDF`, `AbstractLight`, `AbstractPointLikeLight`, `AbstractPhaseFunction`,
`AbstractMedium`), `render` with its `SamplingOptions`, scene files
(`load_scene`, `SceneError`), density grids (`load_grid`, `read_vol`, `write_vol`, `GridFileError`), image I/O (`write_exr`, `read_exr`, `write_png`), `check_finite(image)`, the size
limits' `LimitError`, and the same scene in Mitsuba 3 (`to_mitsuba`, and `render_mitsuba` with the optional extra
`compare`).
"""

from ._bsdf import (
    AbstractBSDF as AbstractBSDF,
    AbstractLobeBSDF as AbstractLobeBSDF,
    Diffuse as Diffuse,
    Glass as Glass,
    Mirror as Mirror,
)
from ._camera import Camera as Camera
from ._devices import use_cpu_cores as use_cpu_cores
from ._image import read_exr as read_exr, write_exr as write_exr, write_png as write_png
from ._integrator import SamplingOptions as SamplingOptions
from ._lights import (
    AbstractAreaLight as AbstractAreaLight,
    AbstractLight as AbstractLight,
    AbstractPointLikeLight as AbstractPointLikeLight,
    AreaLight as AreaLight,
    DirectionalLight as DirectionalLight,
    PointLight as PointLight,
    SpotLight as SpotLight,
)
from ._grid import GridMedium as GridMedium
from ._height import HeightFog as HeightFog
from ._mesh import Mesh as Mesh, MeshError as MeshError, read_mesh as read_mesh, write_ply as write_ply
from ._medium import AbstractMedium as AbstractMedium, HomogeneousMedium as HomogeneousMedium
from ._mitsuba import render_mitsuba as render_mitsuba, to_mitsuba as to_mitsuba
from ._mitsuba_xml import MitsubaXmlError as MitsubaXmlError, scene_from_mitsuba_xml as scene_from_mitsuba_xml
from ._phase import (
    AbstractPhaseFunction as AbstractPhaseFunction,
    Draine as Draine,
    Droplet as Droplet,
    HenyeyGreenstein as HenyeyGreenstein,
    Rayleigh as Rayleigh,
    TwoTermHG as TwoTermHG,
)
from ._render import render as render
from ._scene import Scene as Scene
from ._scene_io import SceneError as SceneError, load_scene as load_scene
from ._shapes import AbstractShape as AbstractShape
from ._shapes import Rectangle as Rectangle, Sphere as Sphere
from ._validate import LimitError as LimitError, check_finite as check_finite
from ._volfile import GridFileError as GridFileError, load_grid as load_grid, read_vol as read_vol, write_vol as write_vol

__version__ = "0.1.0"
