"""Rendering: the benchmark's observations of posed object meshes, the same bits on every x86-64 CPU.

`raster` is exact triangle rasterisation in numpy (correctly rounded IEEE operations in a fixed order);
`renderer` turns meshes at poses into what the benchmark stores: images (colour, z-depth, visible ids,
world points), the front TSDF, the heightmap and amodal voxels. The generator renders every sequence with
it and the annotator exports its annotated captures with it (and outlines with `raster`): the two are
siblings on this package, neither imports the other. Imports with numpy alone.

`create_renderer` is the one way to make a renderer: it names the cameras (the benchmark's by name, or a
capture's calibrated `dsr_bench.geometry.Camera`s) and the TSDF's camera.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from dsr_bench.constants import IMAGE_SHAPE, TSDF_IMAGE_SHAPE
from dsr_bench.geometry import Camera, make_camera
from dsr_bench.render.renderer import CameraImages, Observation, PosedScene, SceneRenderer

__all__ = ["CameraImages", "Observation", "PosedScene", "SceneRenderer", "create_renderer"]


def create_renderer(objects, cameras: Iterable[str] | Mapping[str, Camera] = ("front",),
                    image_shape: tuple[int, int] = IMAGE_SHAPE,
                    tsdf_image_shape: tuple[int, int] = TSDF_IMAGE_SHAPE) -> SceneRenderer:
    """A renderer of `objects` (ObjectSpec-like items: `.parts`, each with `.vertices` (V,3) m and `.faces`
    (F,3), and `.color` RGB 0..1) seen by `cameras`: names of the benchmark's cameras ('front', 'back') made
    at `image_shape` (`dsr_bench.geometry.make_camera`), or a mapping name -> Camera used as given. The TSDF
    is fused from the benchmark's front camera at `tsdf_image_shape`."""
    if isinstance(cameras, Mapping):
        views = dict(cameras)
    else:
        views = {name: make_camera(name, *image_shape) for name in cameras}
    return SceneRenderer(objects, views, make_camera("front", *tsdf_image_shape))
