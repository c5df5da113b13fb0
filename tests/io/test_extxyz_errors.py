"""Malformed or inconsistent extxyz files: one clear error naming file, frame and problem.

Every bad frame is frame 1 of a file whose frame 0 is a valid methane (synthetic coordinates),
so the tests also check that the 0-based frame index is reported.
"""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.io import ExtxyzError, read_structures
from emlpack.structure import StructureError

PROPS = "Properties=species:S:1:pos:R:3:Z:I:1:force:R:3"
H_DIRS = 0.63 * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)


def methane_rows(core_centre=True):
    """Rows (species, x, y, z, Z) of a synthetic CH4 with its Foster-Boys-like centres."""
    rows = [("C", 0.0, 0.0, 0.0, 6)]
    rows += [("H", *h, 1) for h in H_DIRS]
    if core_centre:
        rows.append(("Es", 0.0002, 0.0, 0.0, 99))
    rows += [("Es", *(0.55 * h), 99) for h in H_DIRS]
    return rows


def frame_text(rows, comment=f'{PROPS} energy=-1100.5 efield="0.001 0.0 -0.002"', count=None):
    lines = [str(len(rows) if count is None else count), comment]
    for sym, x, y, z, zz in rows:
        lines.append(f"{sym} {x} {y} {z} {zz} 0.1 -0.2 0.3")
    return "\n".join(lines) + "\n"


def write_file(tmp_path, bad_frame: str, name="bad.xyz"):
    path = tmp_path / name
    path.write_text(frame_text(methane_rows()) + bad_frame)
    return path


def check(path, *patterns, frame=1):
    with pytest.raises(ExtxyzError) as info:  # an ExtxyzError is a StructureError
        read_structures(path)
    message = str(info.value)
    assert str(path) in message
    assert f"frame {frame}" in message
    for pattern in patterns:
        assert pattern in message, message
    return info.value


def test_valid_methane_is_read(tmp_path):
    path = tmp_path / "good.xyz"
    path.write_text(frame_text(methane_rows()) + frame_text(methane_rows(core_centre=False)))
    first, second = read_structures(path)
    assert first.n_pairs == second.n_pairs == 4
    np.testing.assert_array_equal(first.pairs, second.pairs)


def test_truncated_file(tmp_path):
    text = frame_text(methane_rows())
    path = write_file(tmp_path, "\n".join(text.splitlines()[:6]) + "\n")
    err = check(path, "truncated", "declares 10 particles", "after 4 particle lines")
    assert isinstance(err, StructureError)


def test_non_numeric_coordinate(tmp_path):
    rows = methane_rows()
    rows[2] = ("H", 0.63, "abc", -0.63, 1)
    check(write_file(tmp_path, frame_text(rows)), "cannot parse", "abc")


def test_nan_position(tmp_path):
    rows = methane_rows()
    rows[3] = ("H", "nan", 0.63, -0.63, 1)
    check(write_file(tmp_path, frame_text(rows)), "particle row 3 (H)", "non-finite")


def test_unknown_element_symbol(tmp_path):
    props = "Properties=species:S:1:pos:R:3:force:R:3"  # no Z column: symbols decide
    rows = methane_rows()
    rows[1] = ("Qq", *rows[1][1:])
    text = "\n".join(
        [str(len(rows)), f"{props} energy=-1.0"]
        + [f"{r[0]} {r[1]} {r[2]} {r[3]} 0 0 0" for r in rows]
    )
    check(write_file(tmp_path, text + "\n"), "unknown element symbol 'Qq'")


def test_element_outside_supported_range(tmp_path):
    rows = methane_rows(core_centre=False)
    rows[0] = ("Fe", 0.0, 0.0, 0.0, 26)
    check(write_file(tmp_path, frame_text(rows)), "unsupported element", "Z=[26]")


def test_odd_electron_count(tmp_path):
    rows = methane_rows(core_centre=False)
    del rows[4]  # CH3: core charges 4 + 3 = 7
    del rows[-1]
    check(write_file(tmp_path, frame_text(rows)), "odd number of valence electrons")


def test_missing_pairs(tmp_path):
    rows = methane_rows(core_centre=False)[:-1]
    check(write_file(tmp_path, frame_text(rows)), "3 electron pairs (Es rows) given, 4 needed"
          " for a neutral CH4")


def test_extra_pairs(tmp_path):
    rows = methane_rows() + [("Es", 3.0, 3.0, 3.0, 99)]
    check(write_file(tmp_path, frame_text(rows)), "6 electron pairs (Es rows) given, 4 needed",
          "(5 with the 1s core centres)")


def test_efield_with_wrong_number_of_components(tmp_path):
    text = frame_text(methane_rows(), comment=f'{PROPS} energy=-1100.5 efield="0.001 0.002"')
    check(write_file(tmp_path, text), "'efield' must have 3 components, got 2")


def test_heavy_atom_without_core_centre(tmp_path):
    rows = methane_rows()
    rows[5] = ("Es", 0.2, 0.0, 0.0, 99)  # the 1s centre moved 0.2 Å off the carbon
    check(write_file(tmp_path, frame_text(rows)), "atom 0 (Z=6) has no 1s core centre", "0.01 Å")


def test_two_heavy_atoms_claim_the_same_centre(tmp_path):
    rows = [("C", 0.0, 0.0, 0.0, 6), ("C", 0.004, 0.0, 0.0, 6)]
    rows += [("Es", 0.002, 0.0, 0.0, 99), ("Es", 2.0, 0.0, 0.0, 99)]
    rows += [("Es", 0.5 * i, 1.0, 0.0, 99) for i in range(4)]  # 6 rows; C2 needs 4 (+2 cores)
    check(write_file(tmp_path, frame_text(rows)), "atoms 0 and 1 both claim")


def test_frame_with_no_atoms(tmp_path):
    check(write_file(tmp_path, f"0\n{PROPS}\n"), "declares 0 particles")


def test_frame_with_only_electron_pairs(tmp_path):
    rows = [("Es", 0.0, 0.0, 0.0, 99)]
    check(write_file(tmp_path, frame_text(rows)), "no atomic cores")


def test_field_that_looks_like_volt_per_angstrom(tmp_path):
    text = frame_text(methane_rows(), comment=f'{PROPS} energy=-1100.5 efield="0.5 2.5 0.0"')
    check(write_file(tmp_path, text), "looks like a field in V/Å stored under 'efield'")


def test_header_is_not_a_count(tmp_path):
    text = frame_text(methane_rows()).replace("10\n", "ten\n", 1)
    check(write_file(tmp_path, text), "expected the particle count", "'ten'")


def test_mixed_periodicity(tmp_path):
    comment = f'Lattice="10 0 0 0 10 0 0 0 10" {PROPS} pbc="T T F" efield="0 0 0"'
    check(write_file(tmp_path, frame_text(methane_rows(), comment=comment)), "mixed periodicity")


def test_non_numeric_energy(tmp_path):
    comment = f'{PROPS} energy=abc efield="0 0 0"'
    check(write_file(tmp_path, frame_text(methane_rows(), comment=comment)), "'energy' must be")


def test_native_field_with_wrong_number_of_components(tmp_path):
    comment = f'{PROPS} energy=-1.0 external_field="0.1 0.2 0.3 0.4"'
    check(
        write_file(tmp_path, frame_text(methane_rows(), comment=comment)),
        "'external_field' must have 3 components, got 4",
    )


def test_blank_line_between_frames(tmp_path):
    text = "\n" + frame_text(methane_rows())
    check(write_file(tmp_path, text), "blank line")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.xyz"
    path.write_text("")
    with pytest.raises(ExtxyzError, match="contains no frames"):
        read_structures(path)


def test_bad_arguments(tmp_path):
    path = write_file(tmp_path, "")
    with pytest.raises(ValueError, match="convention"):
        read_structures(path, convention="legacy-ish")
    with pytest.raises(FileNotFoundError):
        read_structures(tmp_path / "missing.xyz")
    with pytest.raises(ExtxyzError, match="file has 1 frames"):
        read_structures(path, index=-2)
    with pytest.raises(ExtxyzError, match="frame 3 requested but the file has 1 frames"):
        read_structures(path, index=3)
    assert read_structures(path, index="1:") == []


@pytest.mark.parametrize(("key_value", "expected"), [
    ('efield="0.001 0.002"', "'efield' must have 3 components, got 2"),
    ('field="1 2"', "'field' must have 3 components, got 2"),
    ('external_field="0.1 0.2"', "'external_field' must have 3 components, got 2"),
    ('dipole="1 2"', "'dipole' must have 3 components, got 2"),
    ('dipole=x', "'dipole' must be 3 numbers"),
    ('Lattice="10 0 0 0 10 0" pbc="T T T"', "'Lattice' must be 9 numbers (the three cell"
     " vectors, Å), got 6: '10 0 0 0 10 0'"),
    ('stress="1 2 3 4 5 6"', "'stress' must be 9 numbers (a 3x3 matrix, eV/Å^3), got 6"),
    ('pbc="T T"', "'pbc' must be 3 flags T or F, got 2: 'T T'"),
    ('pbc="T T X"', "'pbc' must be 3 flags T or F, got 3: 'T T X'"),
])
def test_every_shaped_key_of_the_wrong_shape_is_one_line_naming_key_and_shape(
        tmp_path, key_value, expected):
    """Each vector or matrix key the reader takes, with another number of values, is refused
    with one line naming the key and the shape it needs (not ASE's or numpy's message)."""
    text = frame_text(methane_rows(), comment=f"{PROPS} energy=-1100.5 {key_value}")
    err = check(write_file(tmp_path, text), expected)
    assert "\n" not in str(err)


def test_raw_frames_are_checked_too(tmp_path):
    """The commands read a raw frame (``read_frame_atoms``) and its field
    (``frame_field``, V/Å) before the structure: the same one-line errors there."""
    from emlpack.io.extxyz import frame_field, read_frame_atoms
    from emlpack.units import FIELD_AU_IN_V_PER_A

    path = tmp_path / "one.xyz"
    path.write_text(frame_text(methane_rows(), comment=f'{PROPS} efield="0.001 0.002"'))
    with pytest.raises(ExtxyzError, match=r"one.xyz, frame 0: 'efield' must have 3 components"):
        read_frame_atoms(path, 0)
    path.write_text(frame_text(methane_rows()))
    atoms = read_frame_atoms(path, 0)
    np.testing.assert_allclose(frame_field(atoms, "x"),
                               np.array([0.001, 0.0, -0.002]) * FIELD_AU_IN_V_PER_A)
    atoms.info.pop("efield")
    assert frame_field(atoms, "x") is None
