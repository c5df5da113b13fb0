"""Round trips of the shared data files and agreement with the reference's core filtering."""

from __future__ import annotations

import os

import ase.io
import numpy as np
import pytest

from emlpack.io import iread_structures, read_structures, write_structures
from emlpack.structure import Structure
from emlpack.units import FIELD_AU_IN_V_PER_A
from tests.conftest import shared_path

EQM7 = "data/eqm7_pbe0_subset.xyz"
GLYCINE = "data/beta_glycine_pbe_wannier.xyz"
MOLECULES = "fixtures/reference_tf/molecules_small.npz"


@pytest.fixture(scope="module")
def eqm7() -> list[Structure]:
    return read_structures(shared_path(EQM7))


@pytest.fixture(scope="module")
def glycine() -> Structure:
    (structure,) = read_structures(shared_path(GLYCINE))
    return structure


def assert_same(a: Structure, b: Structure, pos_decimals: int | None = None) -> None:
    """Equal numbers; positions/forces compared after rounding ``a`` to ASE's 8 decimals."""

    def rounded(x):
        return x if pos_decimals is None else np.round(x, pos_decimals)

    np.testing.assert_array_equal(a.numbers, b.numbers)
    np.testing.assert_allclose(b.positions, rounded(a.positions), rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.pairs, rounded(a.pairs), rtol=0, atol=1e-10)
    np.testing.assert_array_equal(a.cell, b.cell)
    assert a.pbc == b.pbc
    np.testing.assert_allclose(b.field, a.field, rtol=1e-14, atol=0)
    assert a.charge == b.charge
    assert a.energy == b.energy
    if a.forces is None:
        assert b.forces is None
    else:
        np.testing.assert_allclose(b.forces, rounded(a.forces), rtol=0, atol=1e-10)


def test_eqm7_counts_and_units(eqm7):
    assert len(eqm7) == 600
    first = eqm7[0]
    assert first.source.endswith("eqm7_pbe0_subset.xyz, frame 0")
    assert first.energy == -1101.0905991080365
    # efield="-0.000858 -0.002183 0.003142" (atomic units) -> V/Å
    np.testing.assert_allclose(
        first.field, np.array([-0.000858, -0.002183, 0.003142]) * FIELD_AU_IN_V_PER_A, rtol=1e-15
    )
    assert not first.pbc and first.n_pairs == 4 and first.pair_forces is None
    for s in eqm7:
        assert s.n_pairs == (s.core_charges.sum() - s.charge) / 2
        assert len(s.info["core_centres"]) == np.sum(s.numbers > 1)


def test_eqm7_pairs_equal_reference_fixture(eqm7):
    fixture = np.load(shared_path(MOLECULES))
    slots = sorted({k.split("_")[0] for k in fixture.files if k.startswith("c")})
    assert len(slots) == 12
    for slot in slots:
        s = eqm7[int(fixture[f"{slot}_source_frame"])]
        np.testing.assert_array_equal(s.pairs, fixture[f"{slot}_pair_positions"])
        np.testing.assert_array_equal(s.positions, fixture[f"{slot}_core_positions"])
        np.testing.assert_array_equal(s.numbers, fixture[f"{slot}_core_numbers"])
        np.testing.assert_array_equal(
            s.info["core_centre_rows"], fixture[f"{slot}_removed_center_rows"]
        )
        np.testing.assert_array_equal(s.all_positions, fixture[f"{slot}_all_positions"])
        np.testing.assert_allclose(
            s.field / FIELD_AU_IN_V_PER_A, fixture[f"{slot}_efield"], rtol=1e-15
        )


def test_glycine_keeps_all_valence_pairs(glycine):
    raw = ase.io.read(shared_path(GLYCINE))
    assert glycine.pbc
    assert glycine.n_pairs == 30 and glycine.n_cores == 20
    assert "core_centres" not in glycine.info
    np.testing.assert_array_equal(glycine.pairs, raw.positions[raw.numbers == 99])
    np.testing.assert_array_equal(glycine.cell, raw.cell.array)
    assert np.all(glycine.field == 0)
    assert glycine.energy == -3161.012449830798


@pytest.mark.parametrize("convention", ["native", "reference"])
def test_eqm7_round_trip(eqm7, tmp_path, convention):
    path = tmp_path / f"eqm7_{convention}.xyz"
    write_structures(path, eqm7, convention=convention)
    again = read_structures(path)
    assert len(again) == len(eqm7)
    for a, b in zip(eqm7, again, strict=True):
        assert_same(a, b, pos_decimals=8)
        assert "core_centres" not in b.info  # only valence pairs were written


@pytest.mark.parametrize("convention", ["native", "reference"])
def test_glycine_round_trip(glycine, tmp_path, convention):
    path = tmp_path / f"glycine_{convention}.xyz"
    write_structures(path, glycine, convention=convention)
    (again,) = read_structures(path)
    assert_same(glycine, again, pos_decimals=8)
    for key in ("hf_estimate", "electronic_dipole", "ionic_dipole", "field_type"):
        np.testing.assert_array_equal(again.info[key], glycine.info[key])


def test_eqm7_reference_with_cores_reproduces_file_values(eqm7, tmp_path):
    """Writing the removed 1s centres back gives the original file, value for value."""
    path = tmp_path / "eqm7_cores.xyz"
    write_structures(path, eqm7, convention="reference", core_centres=True)
    original = ase.io.read(shared_path(EQM7), index=":")
    written = ase.io.read(path, index=":")
    assert len(written) == len(original)
    for a, b in zip(original, written, strict=True):
        np.testing.assert_array_equal(a.numbers, b.numbers)
        np.testing.assert_allclose(b.positions, a.positions, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.arrays["force"], a.arrays["force"], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(b.info["efield"], a.info["efield"])
        assert b.get_potential_energy() == a.get_potential_energy()
    again = read_structures(path)
    for a, b in zip(eqm7, again, strict=True):
        assert_same(a, b)
        np.testing.assert_array_equal(a.info["core_centre_rows"], b.info["core_centre_rows"])


def test_native_keys_and_auto_detection(glycine, tmp_path):
    s = glycine.copy(
        field=np.array([0.1, -0.2, 0.3]),
        stress=np.diag([0.01, 0.02, 0.03]) + 0.001 * (np.ones((3, 3)) - np.eye(3)),
        pair_forces=np.linspace(-1, 1, 90).reshape(30, 3),
    )
    path = tmp_path / "native.xyz"
    write_structures(path, s, convention="native")
    raw = ase.io.read(path)
    np.testing.assert_array_equal(raw.info["external_field"], [0.1, -0.2, 0.3])
    assert "efield" not in raw.info
    (auto,) = read_structures(path)  # auto: external_field present -> native
    (native,) = read_structures(path, convention="native")
    for b in (auto, native):
        np.testing.assert_array_equal(b.field, s.field)
        np.testing.assert_allclose(b.stress, s.stress, rtol=0, atol=1e-15)
        np.testing.assert_allclose(b.pair_forces, np.round(s.pair_forces, 8), atol=1e-10)
    # the same frame written in the reference convention stores atomic units
    ref = tmp_path / "reference.xyz"
    write_structures(ref, s, convention="reference")
    raw = ase.io.read(ref)
    np.testing.assert_allclose(raw.info["efield"], s.field / FIELD_AU_IN_V_PER_A, rtol=1e-14)
    (back,) = read_structures(ref)
    np.testing.assert_allclose(back.field, s.field, rtol=1e-14)


def test_charged_structure_round_trip(tmp_path):
    # OH-: cores O(+6), H(+1); charge -1 -> 4 pairs
    s = Structure(
        numbers=[8, 1],
        positions=[[0, 0, 0], [0.97, 0, 0]],
        pairs=[[0.3, 0, 0], [-0.1, 0.3, 0], [-0.1, -0.15, 0.26], [-0.1, -0.15, -0.26]],
        charge=-1.0,
        energy=-2.5,
    )
    for convention in ("native", "reference"):
        path = tmp_path / f"oh_{convention}.xyz"
        write_structures(path, s, convention=convention, core_centres=convention == "reference")
        (back,) = read_structures(path)
        assert back.charge == -1.0 and back.n_pairs == 4
        np.testing.assert_allclose(back.pairs, s.pairs, atol=1e-12)


def test_index_selection_and_streaming(eqm7):
    path = shared_path(EQM7)
    it = iread_structures(path, index="10:40:10")
    assert not isinstance(it, list)
    picked = list(it)
    assert [s.source.rsplit(" ", 1)[1] for s in picked] == ["10", "20", "30"]
    for s in picked:
        idx = int(s.source.rsplit(" ", 1)[1])
        np.testing.assert_array_equal(s.pairs, eqm7[idx].pairs)
    (last,) = read_structures(path, index=-1)
    assert last.source.endswith("frame 599")
    assert len(read_structures(path, index=slice(-3, None))) == 3
    (fifth,) = read_structures(path, index=5)
    np.testing.assert_array_equal(fifth.positions, eqm7[5].positions)
    assert len(read_structures(path, index="::-100")) == 6


def test_write_is_atomic(eqm7, tmp_path):
    path = tmp_path / "data.xyz"
    write_structures(path, eqm7[:3])
    before = path.read_bytes()

    def interrupted():
        yield eqm7[3]
        yield eqm7[4]
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_structures(path, interrupted())
    with pytest.raises(TypeError, match="item 1"):
        write_structures(path, [eqm7[0], "not a structure"])
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["data.xyz"]


def test_write_keeps_permissions(eqm7, tmp_path):
    path = tmp_path / "perm.xyz"
    path.write_text("")
    os.chmod(path, 0o640)
    write_structures(path, eqm7[:1])
    assert (path.stat().st_mode & 0o777) == 0o640


@pytest.mark.parametrize("convention", ["native", "reference"])
def test_writing_is_idempotent(glycine, tmp_path, convention):
    first, second = tmp_path / "a.xyz", tmp_path / "b.xyz"
    write_structures(first, glycine, convention=convention)
    write_structures(second, read_structures(first), convention=convention)
    assert first.read_bytes() == second.read_bytes()


def test_reference_frames_keep_every_row_and_recorded_cores_round_trip(eqm7, tmp_path):
    """read_reference_frames (the labeler's input: all Es rows in file order, field in V/Å)
    agrees with read_structures; core_centres="recorded" writes back the centres a frame has."""
    from emlpack.io.extxyz import read_reference_frames

    frames = read_reference_frames(shared_path(EQM7), "0:3")
    for frame, s in zip(frames, eqm7[:3], strict=True):
        np.testing.assert_array_equal(frame.numbers, s.numbers)
        np.testing.assert_array_equal(frame.field, s.field)
        assert frame.energy == s.energy and frame.source == s.source
        np.testing.assert_array_equal(frame.forces, s.forces)
        rows = s.info["core_centre_rows"]
        np.testing.assert_array_equal(frame.centres[rows], s.info["core_centres"])
        assert len(frame.centres) == s.n_pairs + len(rows)
    without = eqm7[0].copy(info={})  # a structure read without core centres
    path = tmp_path / "mixed.xyz"
    write_structures(path, [eqm7[0], without], convention="reference", core_centres="recorded")
    a, b = read_reference_frames(path)
    np.testing.assert_allclose(a.centres, frames[0].centres, rtol=0, atol=1e-12)
    assert len(b.centres) == eqm7[0].n_pairs


def test_polarizability_label_round_trip_and_errors(eqm7, tmp_path):
    """Native extxyz carries the optional ``polarizability`` label (9 numbers row by row,
    e·Å²/V); the reference convention leaves it out; a wrong length is one clear error."""
    from emlpack.io.extxyz import ExtxyzError

    alpha = np.arange(9.0).reshape(3, 3) / 8 + np.eye(3)
    frames = [eqm7[0].copy(polarizability=alpha), eqm7[1]]
    path = tmp_path / "alpha.xyz"
    write_structures(path, frames)
    assert 'polarizability="1.0 0.125 0.25 0.375 1.5 0.625 0.75 0.875 2.0"' in path.read_text()
    back = read_structures(path)
    np.testing.assert_array_equal(back[0].polarizability, alpha)
    assert back[1].polarizability is None and "polarizability" not in back[0].info
    write_structures(tmp_path / "ref.xyz", frames, convention="reference")
    assert "polarizability" not in (tmp_path / "ref.xyz").read_text()
    bad = tmp_path / "bad.xyz"
    bad.write_text(path.read_text().replace('polarizability="1.0 ', 'polarizability="'))
    with pytest.raises(ExtxyzError, match=r"bad.xyz, frame 0: 'polarizability' must be 9"):
        read_structures(bad)
