"""Levels of theory for the reference labeler: the paper's level and quick presets.

A level is written ``xc/basis`` (e.g. ``pbe0/aug-cc-pvtz``), optionally ``xc/basis/auxbasis``
or ``xc/basis/nodf`` (no density fitting), then optionally ``/gridN`` (DFT grid level N instead
of 3) and ``/tolX`` (SCF energy tolerance X Hartree instead of 1e-10), e.g.
``pbe0/def2-svpd/grid1``; or given by a preset name from :data:`PRESETS`. :attr:`Level.name`
writes this form without the tolerance (a convergence setting, not part of the level of
theory: the names of data and reference folders stay as they were), so a level at the default
tolerance parses back from its name.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass

DEFAULT_GRID_LEVEL = 3
DEFAULT_CONV_TOL = 1e-10


@dataclass(frozen=True)
class Level:
    """Restricted Kohn-Sham settings.

    Attributes:
        xc: exchange-correlation functional (PySCF name).
        basis: orbital basis set.
        auxbasis: density-fitting basis; ``None`` lets PySCF choose (aug-cc-pVTZ-JKFIT for
            aug-cc-pVTZ, as in the paper's Psi4 data).
        density_fit: use density fitting for J and K (the paper's data were made with it).
        grid_level: DFT integration grid level (PySCF default 3).
        conv_tol: SCF energy convergence (Hartree).
        max_cycle: SCF iterations before the fallback solver is tried.
    """

    xc: str = "pbe0"
    basis: str = "aug-cc-pvtz"
    auxbasis: str | None = None
    density_fit: bool = True
    grid_level: int = DEFAULT_GRID_LEVEL
    conv_tol: float = DEFAULT_CONV_TOL
    max_cycle: int = 100

    @property
    def name(self) -> str:
        """Short label, e.g. ``pbe0/aug-cc-pvtz`` (``/nodf`` appended without fitting)."""
        text = f"{self.xc}/{self.basis}"
        if not self.density_fit:
            text += "/nodf"
        elif self.auxbasis:
            text += f"/{self.auxbasis}"
        if self.grid_level != DEFAULT_GRID_LEVEL:
            text += f"/grid{self.grid_level}"
        return text

    def as_dict(self) -> dict:
        """The settings as a plain dict."""
        return asdict(self)


#: The paper's level: PBE0/aug-cc-pVTZ with density fitting (aug-cc-pVTZ-JKFIT).
PAPER = Level()

#: Named presets. ``quick`` and ``tiny`` are different potential energy surfaces (forces differ
#: from the paper's level by 0.25-0.45 eV/Å and more): for demos and self-consistent tests only.
PRESETS: dict[str, Level] = {
    "paper": PAPER,
    "quick": Level(basis="6-31g*"),
    "tiny": Level(xc="pbe0", basis="sto-3g", conv_tol=1e-9),
}


def parse_level(spec: str | Level | None) -> Level:
    """A :class:`Level` from a preset name or an ``xc/basis[/auxbasis|/nodf][/gridN][/tolX]``
    string (:attr:`Level.name` parses back to its level)."""
    if spec is None:
        return PAPER
    if isinstance(spec, Level):
        return spec
    text = spec.strip().lower()
    if text in PRESETS:
        return PRESETS[text]
    parts = [p for p in text.split("/") if p]
    options: dict = {}
    while len(parts) > 2 and re.fullmatch(r"grid\d+|tol[0-9.e+-]+", parts[-1]):
        last = parts.pop()
        try:
            if last.startswith("grid"):
                options.setdefault("grid_level", int(last[4:]))
            else:
                options.setdefault("conv_tol", float(last[3:]))
        except ValueError:
            raise ValueError(f"level {spec!r}: cannot read {last!r}") from None
    if len(parts) not in (2, 3):
        raise ValueError(
            f"level {spec!r}: expected a preset ({', '.join(PRESETS)}) or"
            " 'xc/basis[/auxbasis][/gridN][/tolX]'"
        )
    xc, basis = parts[0], parts[1]
    if len(parts) == 3 and parts[2] == "nodf":
        return Level(xc=xc, basis=basis, density_fit=False, **options)
    return Level(xc=xc, basis=basis, auxbasis=parts[2] if len(parts) == 3 else None, **options)
