"""Skeleton files: SWC, CSV node tables and QSM cylinder tables in, SWC out, and an explicit repair policy.

* :func:`read_swc`, :func:`read_node_table`, :func:`read_qsm` (TreeQSM cylinder tables) read a file into a :class:`Skeleton` (file order,
  original ids, SWC types as labels), repairing nothing;
* :func:`repair` applies a :class:`RepairPolicy` and reports every repair, or raises one
  ValueError that lists every problem;
* :func:`load` reads by format (``auto``: by extension) and repairs;
* :func:`write_swc` writes any skeleton (:func:`from_arrays` wraps index arrays, e.g. a fit's)
  as SWC; :func:`label_colors` colours SWC types by ``TYPE_COLORS``;
* :func:`name_nodes` names the file's node id and line in an error about a joint index.
"""

from ._load import format_of as format_of
from ._load import load as load
from ._names import name_nodes as name_nodes
from ._names import node_name as node_name
from ._nodes import read_node_table as read_node_table
from ._qsm import read_qsm as read_qsm
from ._repair import RepairPolicy as RepairPolicy
from ._repair import problems as problems
from ._repair import repair as repair
from ._swc import read_swc as read_swc
from ._swc import write_swc as write_swc
from ._types import CUSTOM_COLOR as CUSTOM_COLOR
from ._types import MISSING as MISSING
from ._types import TYPE_COLORS as TYPE_COLORS
from ._types import Skeleton as Skeleton
from ._types import from_arrays as from_arrays
from ._types import label_colors as label_colors

__all__ = ["CUSTOM_COLOR", "MISSING", "RepairPolicy", "Skeleton", "TYPE_COLORS", "format_of", "from_arrays", "label_colors",
           "load", "name_nodes", "node_name", "problems", "read_node_table", "read_qsm", "read_swc", "repair", "write_swc"]
