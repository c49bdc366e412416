"""Experiment files -> validated, frozen pydantic models; every bad key reported at once.

An experiment is YAML with the sections ``object`` (its ``type`` picks a representation from
the registry, which owns the model of the rest of that section) or ``objects`` (a scene of
several, each a ``shape`` placed with a material), ``camera``, ``lights``, ``shading`` and
``render`` (:class:`ExperimentFile`). :func:`load` returns one value, :class:`Experiment`: a
scene, of one object where the file wrote ``object:``. Unknown keys, wrong types, out-of-range and non-finite values are
errors. :func:`load` raises :class:`ConfigError` (a ``ValueError``) whose message has one line
per problem, ``<dotted.path[index]>: <what is wrong> (got <value>)``.

``--set key.path=value`` overrides (:func:`apply_overrides`) are parsed as YAML scalars and
applied before validation, so an override is checked like the file itself.

The package holds one idea a module: the schema (``_schema``), the error lines (``_errors``),
reading, overriding, validating and resolving an experiment (``_load``), and the configuration
reference read off the models (``_reference``: every key's type, default, range and
description, which docs/config.md shows); every public name
is importable from ``jskel.config``.
"""

from __future__ import annotations

from ._errors import ConfigError as ConfigError
from ._errors import _format as _format
from ._load import DEFAULT_EXPERIMENT as DEFAULT_EXPERIMENT
from ._load import apply_overrides as apply_overrides
from ._load import set_path as set_path
from ._load import load as load
from ._load import read_yaml as read_yaml
from ._load import resolved as resolved
from ._load import validate as validate
from ._schema import StrictModel as StrictModel
from ._schema import Vec3 as Vec3
from ._schema import RGB as RGB
from ._schema import CameraConfig as CameraConfig
from ._schema import LightConfig as LightConfig
from ._schema import ShadingConfig as ShadingConfig
from ._schema import AUTO_CHUNK_CPU as AUTO_CHUNK_CPU
from ._schema import AUTO_CHUNK_ACCELERATOR as AUTO_CHUNK_ACCELERATOR
from ._schema import chunk_of as chunk_of
from ._schema import AUTO_CHUNKS_PER_CALL_CPU as AUTO_CHUNKS_PER_CALL_CPU
from ._schema import chunks_per_call_of as chunks_per_call_of
from ._schema import RenderConfig as RenderConfig
from ._schema import Unit as Unit
from ._schema import TransformConfig as TransformConfig
from ._schema import MotionConfig as MotionConfig
from ._schema import MaterialConfig as MaterialConfig
from ._schema import SceneObjectConfig as SceneObjectConfig
from ._schema import EnvironmentConfig as EnvironmentConfig
from ._schema import Experiment as Experiment
from ._schema import ExperimentFile as ExperimentFile
from ._schema import Shape as Shape
from ._reference import Row as Row
from ._reference import reference_rows as reference_rows
from ._reference import undocumented as undocumented

# (_format: the error lines of a pydantic ValidationError, for loaders of other files)
__all__ = ["apply_overrides", "AUTO_CHUNK_ACCELERATOR", "AUTO_CHUNK_CPU", "AUTO_CHUNKS_PER_CALL_CPU", "CameraConfig", "chunk_of", "chunks_per_call_of", "ConfigError", "DEFAULT_EXPERIMENT", "EnvironmentConfig", "Experiment", "ExperimentFile", "_format", "LightConfig", "load", "MaterialConfig", "MotionConfig", "read_yaml", "reference_rows", "RenderConfig", "resolved", "RGB", "set_path", "Row", "SceneObjectConfig", "Shape", "ShadingConfig", "StrictModel", "TransformConfig", "undocumented", "Unit", "validate", "Vec3"]
