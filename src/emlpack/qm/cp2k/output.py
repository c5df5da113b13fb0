"""CP2K output of the periodic labeler: energy, forces and stress from the log, Wannier centres
from their xyz file, each moved to the image nearest its closest core (Hartree, Hartree/bohr,
GPa and Å as CP2K writes them; the labeler converts).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from emlpack.geometry import minimum_image
from emlpack.qm.pyscf_labeler import LabelingError

#: CP2K's printed stress ("STRESS| Analytical stress tensor [GPa]") is -1 x the ASE stress
STRESS_SIGN = -1.0

TAIL_LINES = 40


class CP2KError(LabelingError):
    """CP2K crashed, timed out, did not converge, or its output could not be parsed."""


_FLOAT = r"[-+]?\d+\.\d*(?:[EeDd][-+]?\d+)?"


def output_tail(text: str, n: int = TAIL_LINES) -> str:
    """The last ``n`` lines of ``text`` (for error messages)."""
    return "\n".join(text.rstrip().splitlines()[-n:])


def parse_output(text: str, n_atoms: int, stress: bool) -> dict:
    """Energy (Ha), forces (Ha/bohr), stress (GPa, CP2K sign), version and SCF status."""
    out: dict = {}
    m = re.search(r"CP2K version (\S+)", text)
    out["cp2k_version"] = m.group(1) if m else ""
    if re.search(r"SCF run NOT converged|outer SCF loop FAILED to converge", text):
        raise CP2KError("SCF not converged")
    m = re.search(r"[Ll]ocali[sz]ation not converged after\s+(\d+)", text)
    if m:
        raise CP2KError(f"Wannier localization not converged after {m.group(1)} iterations")
    m = re.findall(rf"ENERGY\| Total FORCE_EVAL \( QS \) energy \[a\.u\.\]:\s+({_FLOAT})", text)
    if not m:
        raise CP2KError("no total energy in the CP2K output")
    out["energy"] = float(m[-1])
    outer = re.findall(r"outer SCF loop converged in\s+\d+ iterations or\s+(\d+) steps", text)
    steps = re.findall(r"SCF run converged in\s+(\d+) steps", text)
    out["scf_steps"] = int(outer[-1]) if outer else sum(int(x) for x in steps)
    block = text[text.rfind("ATOMIC FORCES in [a.u.]"):]
    if not block.startswith("ATOMIC FORCES"):
        raise CP2KError("no ATOMIC FORCES block in the CP2K output")
    rows = re.findall(rf"^\s+\d+\s+\d+\s+\S+\s+({_FLOAT})\s+({_FLOAT})\s+({_FLOAT})\s*$",
                      block.split("SUM OF ATOMIC FORCES")[0], re.MULTILINE)
    if len(rows) != n_atoms:
        raise CP2KError(f"parsed {len(rows)} force rows for {n_atoms} atoms")
    out["forces"] = np.array(rows, dtype=float)
    if stress:
        i = text.rfind("STRESS| Analytical stress tensor [GPa]")
        if i < 0:
            raise CP2KError("no analytical stress tensor in the CP2K output")
        rows = re.findall(rf"^ STRESS\|\s+[xyz]\s+({_FLOAT})\s+({_FLOAT})\s+({_FLOAT})\s*$",
                          text[i:], re.MULTILINE)[:3]
        if len(rows) != 3:
            raise CP2KError("could not parse the stress tensor in the CP2K output")
        out["stress_gpa"] = np.array(rows, dtype=float)
    m = re.findall(rf"Total Spread \(Berry\) :\s+({_FLOAT})", text)
    if m:
        out["spread"] = float(m[-1])  # sum_i -ln|z_i|^2 (dimensionless, Resta)
    return out


def read_wannier_xyz(path: Path, n_atoms: int) -> np.ndarray:
    """Wannier centres (Å) from CP2K's IONS+CENTERS xyz file (the last frame)."""
    lines = path.read_text().splitlines()
    frames = []
    i = 0
    while i < len(lines):
        if not lines[i].strip():
            i += 1
            continue
        n = int(lines[i].split()[0])
        rows = [ln.split() for ln in lines[i + 2:i + 2 + n]]
        frames.append(rows)
        i += 2 + n
    if not frames:
        raise CP2KError(f"{path.name}: no Wannier centres")
    rows = frames[-1]
    centres = [r[1:4] for r in rows[n_atoms:] if r[0] == "X"]
    if len(rows) - n_atoms != len(centres):
        raise CP2KError(f"{path.name}: unexpected rows after the {n_atoms} ions")
    return np.array(centres, dtype=float).reshape(-1, 3)


def map_centres_to_cores(centres: np.ndarray, positions: np.ndarray,
                         cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move each centre to the periodic image nearest to its closest core (Å).

    Returns ``(mapped, nearest_core)``; the distance to the closest core is minimum-image
    (:func:`emlpack.geometry.minimum_image`, exact for any triclinic cell).
    """
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    vec = minimum_image(centres[:, None, :] - positions[None, :, :], cell)  # (n_c, n_a, 3)
    core = np.linalg.norm(vec, axis=-1).argmin(axis=1)
    return positions[core] + vec[np.arange(len(centres)), core], core
