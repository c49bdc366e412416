"""Acceleration structures shared by the representations (issue 6): a linear BVH built in JAX
per frame (``_lbvh``), traversed stacklessly under vmap (``nearest``: the frusta's nearest hit;
``collect``: every leaf a ray meets, for the implicit representation's culling); and candidate
lists for packets of coherent rays (``_bins``); reverse-mode derivatives of a walk's nearest hit
from its winning primitive (``_tangent``)."""

from ._bins import always as always
from ._bins import bin_groups as bin_groups
from ._bins import fenced as fenced
from ._bins import first_set as first_set
from ._bins import nearest_binned as nearest_binned
from ._bins import pack_bits as pack_bits
from ._bins import packet_meets as packet_meets
from ._collect import collect_packets as collect_packets
from ._groups import map_groups as map_groups
from ._groups import pad_groups as pad_groups
from ._lbvh import BVH as BVH
from ._lbvh import Best as Best
from ._lbvh import build as build
from ._lbvh import collect as collect
from ._lbvh import descend as descend
from ._lbvh import escape as escape
from ._lbvh import leaves_for as leaves_for
from ._lbvh import morton_codes as morton_codes
from ._lbvh import nearest as nearest
from ._lbvh import nearest_packet as nearest_packet
from ._lbvh import ray_box as ray_box
from ._tangent import hold as hold
from ._tangent import nearest_tangent as nearest_tangent

__all__ = ["BVH", "Best", "always", "bin_groups", "build", "collect", "collect_packets", "descend", "escape", "fenced", "first_set", "hold", "leaves_for", "map_groups", "morton_codes", "nearest", "nearest_binned", "nearest_packet", "nearest_tangent", "pack_bits", "packet_meets", "pad_groups", "ray_box"]
