"""Readers and writers for external file formats.

* :mod:`emlpack.io.extxyz`: extxyz files (reference ``Es``/``efield`` and native conventions);
* :mod:`emlpack.io.cores`: removal of inner-shell centres (minimum image under PBC);
* :mod:`emlpack.io.ase_convert`: :class:`~emlpack.structure.Structure` <-> :class:`ase.Atoms`;
* :mod:`emlpack.legacy.tf_checkpoint`: TensorFlow checkpoints of the reference (import it directly).
"""

from emlpack.io.ase_convert import atoms_to_structure, split_pairs, structure_to_atoms
from emlpack.io.cores import (
    CORE_TOLERANCE,
    find_core_centres,
    split_core_centres,
)
from emlpack.io.extxyz import (
    ExtxyzError,
    iread_structures,
    read_frame_atoms,
    read_structures,
    write_structures,
)

__all__ = [
    "CORE_TOLERANCE",
    "ExtxyzError",
    "atoms_to_structure",
    "find_core_centres",
    "iread_structures",
    "read_frame_atoms",
    "read_structures",
    "split_core_centres",
    "split_pairs",
    "structure_to_atoms",
    "write_structures",
]
