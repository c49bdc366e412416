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
    """How the tile map is made: tileable Voronoi cells, spherical cells, or an array file."""
    resolution: Annotated[int, Field(ge=16, le=256)] = 32
    """Voxels per edge of the tile map."""
    cells: Annotated[int, Field(ge=1, le=64)] = 8
    """Cells per tile (Voronoi sites or spheres)."""
    radius: Annotated[float, Field(gt=0.0, lt=0.5)] = 0.2
    """``spheres``: cell radius, tile units."""
    seed: int = 0
    """Random seed of the cell sites."""
    path: str | None = None
    """``file``: a .npy integer array (cell indices 0..255, 0 empty), required for that type."""

    @model_validator(mode="after")
    def _file_has_path(self):
        if self.type == "file" and self.path is None:
            raise ValueError("a 'file' tile map needs a 'path' to a .npy array")
        return self


class BaseShapeConfig(StrictModel):
    """The basic shape (Sec. 3.1.1) whose inside the cells fill: an analytic ``torus`` (about
    +y) or ``sphere``; a watertight triangle mesh file (read by trimesh) voxelized (``voxel_mesh``:
    ``path``, ``voxels`` along its longest side; fast for big meshes); or the ``object`` section
    of another representation, whose own ``inside`` decides exactly (a mesh file as
    ``{type: mesh, path: ...}``: three BVH casts a point, docs/choices.md#voxel-mesh-voxels;
    a frusta skeleton; an implicit surface)."""

    type: Literal["torus", "sphere", "voxel_mesh", "object"] = "torus"
    """The kind of base shape."""
    center: Vec3 = (0.0, 0.0, 0.0)
    """Centre of a torus or sphere, world units."""
    major: Pos = 1.0
    """Torus: distance from the centre to the tube's centre line."""
    minor: Pos = 0.4
    """Torus: tube radius (below ``major``)."""
    radius: Pos = 1.0
    """Sphere: radius."""
    path: str | None = None
    """``voxel_mesh``: a watertight triangle mesh file."""
    voxels: Annotated[int, Field(ge=16, le=2048)] = 512
    """``voxel_mesh``: voxels along the mesh's longest side in its inside test (the surface's voxels, then
    filled); the fill of the whole grid dominates its time at 512 (docs/choices.md#voxel-mesh-voxels)."""
    object: dict[str, Any] | None = None
    """``object``: another representation's ``object`` section (with its ``type``), whose ``inside`` decides."""

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
    map, ray traced through the tile map's voxels (or by Alg. 3.1's linear + binary search) in
    one of three modes (Alg. 3.1-3.3)."""

    type: Literal["cells"]
    """Selects this representation."""
    base: BaseShapeConfig = BaseShapeConfig()
    """The basic shape whose inside the cells fill (Sec. 3.1.1)."""
    tile_map: TileMapConfig = TileMapConfig()
    """The tile of cells repeated through the shape (Sec. 4.1)."""
    tiles: Annotated[int, Field(ge=1, le=512)] = 32
    """Tiles per axis of the cube around the base shape (its longest side, padded by ``margin``)."""
    margin: Annotated[float, Field(ge=0.0, le=1.0)] = 0.02
    """Padding of that cube on each side, a fraction of the base shape's extent."""
    coarse: Annotated[int, Field(ge=1, le=256)] = 2
    """Samples per tile edge when tiles are classified as empty, full or mixed."""
    mode: Literal["first_hit", "reflection", "refraction"] = "first_hit"
    """First hit only, self-reflection (Alg. 3.2) or refraction (Alg. 3.3)."""
    bounces: Annotated[int, Field(ge=0, le=16)] = 1
    """Reflection or refraction levels in those modes."""
    ior: Pos = 1.5
    """``refraction``: index of refraction."""
    reflectivity: Annotated[float, Field(ge=0.0, le=1.0)] = 0.5
    """``reflection``: weight of the mirrored light."""
    search: Literal["linear", "voxels"] = "voxels"
    """``voxels`` (the default): every voxel of the tile map the ray crosses, in order, to the
    first target (exact: the hit is the crossed face, no part is stepped over;
    ``steps_per_tile`` and ``bisection`` are not used); ``linear``: Alg. 3.1's linear search
    every ``steps_per_tile``-th of a tile, then ``bisection`` halvings of the last step (the
    thesis' method, whose step its Sec. 5.3 studies)."""
    steps_per_tile: Annotated[int, Field(ge=1, le=65536)] = 256
    """``search: linear``'s step, 1/steps_per_tile of a tile (its quality knob)."""
    bisection: Annotated[int, Field(ge=0, le=40)] = 10
    """``search: linear``: bisection iterations refining a step's crossing."""
    max_steps: Annotated[int, Field(ge=1, le=1 << 24)] = 1 << 18
    """Samples (``voxels``: voxels and skipped tiles) per ray segment; a ray that reaches the cap
    is flagged."""
    skip: bool = True
    """Skip empty and full tiles (Alg. 3.2, 3.3)."""
    pyramid: bool = True
    """``search: voxels`` with ``skip``: cross a run of empty tiles (or of full ones, leaving the
    inside) one aligned block of 2^l tiles at a time, from an occupancy pyramid built with the
    membership map; false: one tile at a time."""
    color_map: str = "worley"
    """Cell colours: ``worley``, or a path to a (c, c, c, 3) .npy array in [0, 1]."""
    environment: str = "sky"
    """What reflected and refracted rays see: ``sky``, or a path to an equirectangular image."""
    cache: str | None = "auto"
    """Folder for precomputed objects: ``auto``, the ``cells`` folder of jskel's cache directory
    (``~/.cache/jskel/jax/cells``; ``JSKEL_CACHE_DIR`` moves it, ``JSKEL_CACHE=off`` turns it
    off, as for compiled programs); a path; null: none."""
