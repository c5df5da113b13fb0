"""Inputs that never crash: a valid extxyz file mutated at random (seeded) gives ``emlp
polarizability`` either exit 0 with finite numbers, or one line and exit 2 (a bad input) or
3 (a result that is not at a minimum), never a traceback or a signal.

The mutations: numbers replaced by nan, inf, garbage or huge values, lines dropped or
duplicated, the particle count and the comment line broken, unknown elements. They run in
this process (:func:`tests.cli.helpers.run`), except those with a huge number, which once
made vesin divide by zero (SIGFPE): they run in one subprocess, so that a signal is seen as
one instead of ending the test session. The model is the small trained benchmark model.
"""

from __future__ import annotations

import json
import math
import os
import random
import subprocess
import sys
from pathlib import Path

import pytest

from tests.cli.helpers import run, water_rows, write_xyz

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "benchmarks" / "fixtures" / "eqm7_small_trained.pt"
COMMENT = 'Properties=species:S:1:pos:R:3 pbc="F F F" charge=0 efield="0.0 0.0 0.0"'
N_MUTATIONS = 36
#: a number at least this large is "huge": its file runs in the subprocess
HUGE = 1e5
#: the subprocesses import this checkout's package (src first) and its tests
ENV = dict(os.environ, OMP_NUM_THREADS="1",
           PYTHONPATH=os.pathsep.join([str(ROOT / "src"), str(ROOT)]))

NUMBERS = ["nan", "NaN", "inf", "-inf", "abc", "1e", "--1", "1.2.3", "", "0x10", "1e6",
           "-1e6", "1e300", "-1e308", "3e38", "1e5", "0.0", "1e-300", "5.0"]
COMMENTS = ['Properties=species:S:1:pos:R:3 efield="1 2"', 'pbc="T T"', 'pbc="T F"',
            'Lattice="1 2 3" pbc="T T T"', 'Lattice="0 0 0 0 0 0 0 0 0" pbc="T T T"',
            'Properties=species:S:1:pos:R:3 "unbalanced', 'charge=abc', 'charge=1',
            'charge=nan', 'efield="nan 0 0"', 'efield="1e6 0 0"', 'dipole="1 2"',
            'stress="1 2 3"', 'Properties=species:S:1', 'Properties=pos:R:3:species:S:1',
            'external_field="0 0 1e9"', '', '= = =', 'energy="1 2"']
ELEMENTS = ["Xx", "Si", "Q", "99", "0", "U", "es", "Es", "H"]


def mutate(lines: list[str], rng: random.Random) -> tuple[list[str], str]:
    """One random mutation of the file's ``lines``: (new lines, what was done)."""
    lines = list(lines)
    kind = rng.choice(["number", "number", "number", "drop", "duplicate", "count", "comment",
                       "element"])
    body = range(2, len(lines))
    if kind == "number":
        k = rng.choice(list(body))
        cols = lines[k].split()
        c = rng.randrange(1, 4)
        cols[c] = rng.choice(NUMBERS)
        lines[k] = " ".join(cols)
        return lines, f"line {k} column {c} -> {cols[c]!r}"
    if kind == "drop":
        k = rng.randrange(len(lines))
        del lines[k]
        return lines, f"line {k} dropped"
    if kind == "duplicate":
        k = rng.randrange(len(lines))
        lines.insert(k, lines[k])
        return lines, f"line {k} duplicated"
    if kind == "count":
        lines[0] = rng.choice([str(int(lines[0]) + 1), str(int(lines[0]) - 1), "0", "-3",
                               "seven", "1e3", ""])
        return lines, f"count -> {lines[0]!r}"
    if kind == "comment":
        lines[1] = rng.choice(COMMENTS)
        return lines, f"comment -> {lines[1]!r}"
    k = rng.choice(list(body))
    cols = lines[k].split()
    cols[0] = rng.choice(ELEMENTS)
    lines[k] = " ".join(cols)
    return lines, f"line {k} element -> {cols[0]!r}"


def _is_huge(lines: list[str]) -> bool:
    for line in lines:
        for word in line.replace('"', " ").split():
            try:
                value = float(word)
            except ValueError:
                continue
            if math.isfinite(value) and abs(value) >= HUGE:
                return True
    return False


def _finite(value: object) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    return True


def _check(what: str, rc: int, out: str, err: str, json_path: Path) -> None:
    assert "Traceback" not in out + err, f"{what}: a traceback\n{err}"
    assert rc in (0, 2, 3), f"{what}: exit {rc}\n{err}"
    if rc == 0:
        data = json.loads(json_path.read_text())
        main = {k: v for k, v in data.items() if k not in ("settings", "warnings")}
        assert _finite(main), f"{what}: exit 0 with non-finite numbers"
        assert math.isfinite(data["polarizability_isotropic_bohr3"]), what
    else:
        lines = [line for line in err.splitlines() if line.strip()]
        assert len(lines) >= 1 and lines[-1].startswith(
            ("emlp polarizability: error: ", "emlp polarizability: failed: ")), f"{what}: {err}"
        if rc == 2:  # a bad input is refused before any work: its line is all there is
            assert len(lines) == 1, f"{what}: {err}"


def _mutations(tmp_path: Path) -> list[tuple[str, Path]]:
    base = write_xyz(tmp_path / "water.xyz", water_rows(4), comment=COMMENT)
    lines = base.read_text().splitlines()
    rng = random.Random(53)
    out = []
    for k in range(N_MUTATIONS):
        new, what = mutate(lines, rng)
        if rng.random() < 0.25:  # some files get two mutations
            new, more = mutate(new, rng)
            what += "; " + more
        path = tmp_path / f"m{k:02d}.xyz"
        path.write_text("\n".join(new) + "\n")
        out.append((f"mutation {k} ({what})", path))
    return out


def test_mutated_water_files_never_crash(tmp_path):
    files = _mutations(tmp_path)
    huge = [(what, p) for what, p in files if _is_huge(p.read_text().splitlines())]
    normal = [(what, p) for what, p in files if (what, p) not in huge]
    assert len(normal) > 20 and len(huge) >= 3  # the seed covers both kinds
    for what, path in normal:
        out_json = path.with_suffix(".json")
        rc, out, err = run(["polarizability", str(MODEL), str(path), "-o", str(out_json),
                            "--quiet", "--threads", "1"])
        _check(what, rc, out, err, out_json)
    # the huge ones in one subprocess: it prints each file before running it, and each
    # result as JSON after, so a signal names the file that raised it
    script = (
        "import json, sys\n"
        "from tests.cli.helpers import run\n"
        "for path in sys.argv[2:]:\n"
        "    print('start', path, flush=True)\n"
        "    rc, out, err = run(['polarizability', sys.argv[1], path, '-o', path[:-4] + '.json',"
        " '--quiet', '--threads', '1'])\n"
        "    print('done', json.dumps([rc, out, err]), flush=True)\n")
    proc = subprocess.run([sys.executable, "-c", script, str(MODEL),
                           *[str(p) for _, p in huge]], capture_output=True, text=True,
                          cwd=ROOT, env=ENV, timeout=300)
    started = [line.split(" ", 1)[1] for line in proc.stdout.splitlines()
               if line.startswith("start ")]
    assert proc.returncode == 0, (f"the subprocess ended with {proc.returncode} (a signal is"
                                  f" negative) in {started[-1] if started else '?'}:"
                                  f" {proc.stderr[-2000:]}")
    results = [json.loads(line.split(" ", 1)[1]) for line in proc.stdout.splitlines()
               if line.startswith("done ")]
    assert len(results) == len(huge)
    for (what, path), (rc, out, err) in zip(huge, results, strict=True):
        _check(what, rc, out, err, path.with_suffix(".json"))


@pytest.mark.parametrize("row, value", [(4, 1e6), (0, -1e6)])
def test_a_coordinate_of_1e6_angstrom_is_exit_2_not_a_signal(tmp_path, row, value):
    """The reported crash (exit 136, SIGFPE in vesin), in a subprocess of its own: now exit 2
    and one line naming the file, the frame and the particle row."""
    rows = water_rows(4)
    rows[row] = (rows[row][0], value, rows[row][2], rows[row][3])
    path = write_xyz(tmp_path / "far.xyz", rows, comment=COMMENT)
    proc = subprocess.run([sys.executable, "-m", "emlpack.cli", "polarizability", str(MODEL),
                           str(path), "-o", str(tmp_path / "p.json"), "--threads", "1"],
                          capture_output=True, text=True, cwd=ROOT, env=ENV, timeout=300)
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1, proc.stderr
    assert err[0].startswith(f"emlp polarizability: error: {path}, frame 0: ")
    assert f"particle row {row} " in err[0]
