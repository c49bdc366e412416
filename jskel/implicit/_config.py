"""The ``object`` section of an implicit experiment (``type: implicit``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from ..config import RGB, StrictModel, Vec3

Pos = Annotated[float, Field(gt=0.0)]


class BallConfig(StrictModel):
    """A metaball: centre and effective radius R (Rouiller 2011, Sec. 2.1.1 and 3)."""

    center: Vec3
    radius: Pos


class TubeConfig(StrictModel):
    """A metatube: segment a-b with effective radius interpolated from radius_a to radius_b."""

    a: Vec3
    b: Vec3
    radius_a: Annotated[float, Field(ge=0.0)]
    radius_b: Annotated[float, Field(ge=0.0)]

    @model_validator(mode="after")
    def _not_both_zero(self):
        if self.radius_a == 0 and self.radius_b == 0:
            raise ValueError("a tube needs a positive radius at one end at least (both radii are 0)")
        return self


class ImplicitConfig(StrictModel):
    """Skeletal implicit surface F = T (Rouiller 2011) and how it is ray traced."""

    type: Literal["implicit"]
    threshold: Pos = 0.5
    balls: list[BallConfig] = []
    tubes: list[TubeConfig] = []
    procedural: Literal["gecko", "blob_grid"] | None = None
    seed: int = 0
    options: dict[str, float] = {}
    scale: Pos = 1.0
    offset: Vec3 = (0.0, 0.0, 0.0)
    method: Literal["naive", "bisection", "lipschitz"] = "lipschitz"
    step: Pos = 0.02
    eps: Pos = 1e-3
    steps: Annotated[int, Field(ge=1, le=1 << 20)] = 2048
    bisection: Annotated[int, Field(ge=0, le=64)] = 12
    capacity: Annotated[int, Field(ge=1, le=4096)] = 32
    early_exit: bool = True
    color: RGB = (0.75, 0.45, 0.3)

    @model_validator(mode="after")
    def _has_primitives(self):
        if self.procedural is None and not (self.balls or self.tubes):
            raise ValueError("give balls and/or tubes, or a procedural model")
        return self
