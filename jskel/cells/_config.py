"""The ``object`` section of a cell-based experiment (``type: cells``)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, model_validator

from ..config import StrictModel, Vec3

Pos = Annotated[float, Field(gt=0.0)]


class TileMapConfig(StrictModel):
    """Sec. 4.1: ``voronoi`` (tileable, periodic distance), ``spheres`` (spherical cells of
    ``radius`` tile units with empty space, Fig. 4.1) or ``file`` (a user's integer .npy array)."""

    type: Literal["voronoi", "spheres", "file"] = "voronoi"
    resolution: Annotated[int, Field(ge=16, le=256)] = 32
    cells: Annotated[int, Field(ge=1, le=64)] = 8
    radius: Annotated[float, Field(gt=0.0, lt=0.5)] = 0.2
    seed: int = 0
    path: str | None = None

    @model_validator(mode="after")
    def _file_has_path(self):
        if self.type == "file" and self.path is None:
            raise ValueError("a 'file' tile map needs a 'path' to a .npy array")
        return self


class BaseShapeConfig(StrictModel):
    """The basic shape (Sec. 3.1.1) whose inside the cells fill: an analytic ``torus`` (about
    +y) or ``sphere``; a watertight triangle mesh file voxelized by trimesh (``voxel_mesh``:
    ``path``, ``voxels`` along its longest side; fast for big meshes); or the ``object`` section
    of another representation, whose own ``inside`` decides exactly (a mesh file as
    ``{type: mesh, path: ...}``: three BVH casts a point, about 30 us a point for 20,480
    triangles on the 2-core CPU; a frusta skeleton; an implicit surface)."""

    type: Literal["torus", "sphere", "voxel_mesh", "object"] = "torus"
    center: Vec3 = (0.0, 0.0, 0.0)
    major: Pos = 1.0
    minor: Pos = 0.4
    radius: Pos = 1.0
    path: str | None = None
    # voxel_mesh: voxels along the mesh's longest side in its inside test (trimesh's
    # voxelization, then filled); 512 took 30 s for a 20,480-face icosphere on the 2-core CPU,
    # 256 about 4x less
    voxels: Annotated[int, Field(ge=16, le=2048)] = 512
    object: dict[str, Any] | None = None

    @model_validator(mode="after")
    def _needs(self):
        if self.type == "voxel_mesh" and self.path is None:
            raise ValueError("a 'voxel_mesh' base shape needs a 'path'")
        if self.type == "object" and self.object is None:
            raise ValueError("an 'object' base shape needs an 'object' section (another representation's, with its type)")
        if self.type == "torus" and not self.minor < self.major:
            raise ValueError(f"torus: minor ({self.minor}) must be below major ({self.major})")
        return self


class CellsConfig(StrictModel):
    """Cell-based object (Nürnberg 2011): a base shape tiled ``tiles`` times per axis by a tile
    map, ray traced by linear + binary search (Alg. 3.1-3.3) in one of three modes."""

    type: Literal["cells"]
    base: BaseShapeConfig = BaseShapeConfig()
    tile_map: TileMapConfig = TileMapConfig()
    tiles: Annotated[int, Field(ge=1, le=512)] = 32
    margin: Annotated[float, Field(ge=0.0, le=1.0)] = 0.02  # of the base shape's extent
    coarse: Annotated[int, Field(ge=1, le=256)] = 2  # classification samples per tile edge
    mode: Literal["first_hit", "reflection", "refraction"] = "first_hit"
    bounces: Annotated[int, Field(ge=0, le=16)] = 1
    ior: Pos = 1.5
    reflectivity: Annotated[float, Field(ge=0.0, le=1.0)] = 0.5
    steps_per_tile: Annotated[int, Field(ge=1, le=65536)] = 256  # linear step = 1/steps_per_tile of a tile
    bisection: Annotated[int, Field(ge=0, le=40)] = 10
    max_steps: Annotated[int, Field(ge=1, le=1 << 24)] = 1 << 18  # samples per ray segment (a capped ray is flagged)
    skip: bool = True  # empty / full tile skipping (Alg. 3.2, 3.3)
    color_map: str = "worley"  # worley | path to an (c,c,c,3) .npy in [0, 1]
    environment: str = "sky"  # sky | path to an equirectangular image
    cache: str | None = ".jskel_cache/cells"  # folder for precomputed objects; null: none
