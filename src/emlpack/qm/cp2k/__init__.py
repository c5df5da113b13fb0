"""Periodic reference labels with CP2K (energy, forces, stress, Wannier pairs, Berry-phase field).

* :mod:`emlpack.qm.cp2k.input`: settings, data files and the input text of one structure;
* :mod:`emlpack.qm.cp2k.output`: energy, forces, stress and Wannier centres from CP2K's files;
* :mod:`emlpack.qm.cp2k.runner`: one CP2K process group per run (timeout, interrupt, orphans);
* :mod:`emlpack.qm.cp2k.labeler`: :class:`CP2KLabeler` (units and signs in its docstring), the
  per-task entry point and :func:`label_into_store`.
"""

from emlpack.qm.cp2k.input import (
    CP2KInputError,
    CP2KSettings,
    build_input,
    cp2k_available,
    find_data_dir,
)
from emlpack.qm.cp2k.labeler import CP2KLabeler, field_force_check, label_into_store, label_task
from emlpack.qm.cp2k.output import (
    CP2KError,
    map_centres_to_cores,
    parse_output,
    read_wannier_xyz,
)

__all__ = [
    "CP2KError",
    "CP2KInputError",
    "CP2KLabeler",
    "CP2KSettings",
    "build_input",
    "cp2k_available",
    "field_force_check",
    "find_data_dir",
    "label_into_store",
    "label_task",
    "map_centres_to_cores",
    "parse_output",
    "read_wannier_xyz",
]
