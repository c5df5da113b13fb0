"""``emlp md``, ``md-analysis`` and ``md-ir``: Born-Oppenheimer MD and its analysis."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

from emlpack.cli.common import (
    Log,
    Subparsers,
    add_field_arguments,
    add_model_argument,
    add_parser,
    add_quiet_argument,
    add_structure_arguments,
    apply_field,
    energy_record,
    load_member,
    positive,
    read_structure,
    requested_field,
    set_threads,
    settings,
    write_json,
)
from emlpack.errors import InputError

if TYPE_CHECKING:
    from pathlib import Path

    from emlpack.calculators.ensemble import ModelMember
    from emlpack.structure import Structure


def add_md(sub: Subparsers) -> None:
    """Register ``emlp md``: Born-Oppenheimer MD with relaxed electron pairs (NVT/NVE, optional
    field); resumable."""
    p = add_parser(sub, "md", "Born-Oppenheimer MD with relaxed electron pairs (NVT/NVE,"
                   " optional field); resumable", threads_default=1,
                   description="Born-Oppenheimer MD with relaxed electron pairs (NVT/NVE,"
                   " optional field); resumable. Energies (trajectory, md.log, summary.json)"
                   " are on the DFT scale when the checkpoint holds its DFT hydride references"
                   " and the molecule is neutral, as the property commands report them (a"
                   " constant shift of the model's own energy: summary.json gives both);"
                   " progress: a bar with rate and time left on a terminal, a line every tenth"
                   " of the run otherwise, the step log in md.log.")
    add_model_argument(p, ensemble=False)
    add_structure_arguments(p)
    p.add_argument("--frame", dest="index", help=argparse.SUPPRESS)  # the old name of --index
    p.add_argument("-o", "--output", default="md_run",
                   help="output folder (trajectory.xyz, checkpoint, md.log, summary.json,"
                   " settings.json)")
    p.add_argument("--steps", type=int, default=1000, help="total MD steps")
    p.add_argument("--dt", type=float, default=0.5, help="time step, fs")
    p.add_argument("--temperature", type=float, default=300.0,
                   help="K: NVT target and initial velocities")
    p.add_argument("--nve", action="store_true", help="NVE (velocity Verlet) instead of NVT")
    add_field_arguments(p)
    p.add_argument("--relax", default="corrected", choices=["corrected", "warm", "paper"],
                   help="pair relaxation: warm-started quasi-Newton with a final Newton"
                   " correction (corrected, default), the same without it (warm) or the"
                   " paper's boxed L-BFGS-B")
    p.add_argument("--fmax", type=float, default=1e-5, help="pair-force tolerance, eV/Å")
    p.add_argument("--tdamp", type=float, default=100.0, help="thermostat time constant, fs")
    p.add_argument("--record-every", type=int, default=1, help="a frame every N steps")
    p.add_argument("--checkpoint-every", type=int, default=10, help="flush every N steps")
    p.add_argument("--curvature-every", type=int, default=50,
                   help="exact pair Hessian (curvature check) every N steps")
    p.add_argument("--max-energy-mismatch", type=float, default=1e-3,
                   help="largest |dU + (F0+F1)/2.dR| of a step per core, eV: a larger one means"
                   " the pairs left their minimum (redone from other starts; 0: not checked)")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial velocities")
    p.add_argument("--no-resume", action="store_true", help="start over (deletes the old run)")
    p.add_argument("--no-pairs", action="store_true",
                   help="also write trajectory_atoms.xyz: the atoms without the Es rows of the"
                   " electron pairs (ASE masses, centre of mass, viewers)")
    add_quiet_argument(p)

    def run(args: argparse.Namespace):
        from pathlib import Path

        from emlpack.bonding import bonding_changes
        from emlpack.dynamics.md import MDWatchdogError, Watchdog, run_md

        positive(args.steps, "--steps")
        positive(args.dt, "--dt")
        positive(args.temperature, "--temperature", allow_zero=True)
        if not args.nve and args.temperature == 0:
            raise InputError("--temperature must be positive for NVT (the thermostat mass is"
                             " proportional to T); use --nve for a run from rest")
        positive(args.fmax, "--fmax")
        positive(args.tdamp, "--tdamp")
        positive(args.max_energy_mismatch, "--max-energy-mismatch", allow_zero=True)
        for name in ("record_every", "checkpoint_every", "curvature_every"):
            positive(getattr(args, name), "--" + name.replace("_", "-"))
        set_threads(args.threads)
        log = Log(args.quiet)
        member = load_member(args.model, "emlp md")
        model = member.model
        s, where = read_structure(args, model, log, periodic=False, command="emlp md")
        s, field_info = apply_field(s, args, where, log)
        out = Path(args.output)
        out.mkdir(parents=True, exist_ok=True)
        resolved = {**settings(args), **field_info, "structure": where}
        if args.no_resume or not (out / "settings.json").exists():
            write_json(out / "settings.json", resolved)
        handlers = _md_log_handlers(out)
        try:
            result = run_md(
                member, s, args.steps, out, dt_fs=args.dt, temperature_K=args.temperature,
                ensemble="nve" if args.nve else "nvt",
                field=s.field if requested_field(args) is not None else None,
                seed=args.seed, tdamp_fs=args.tdamp, relax=args.relax, fmax=args.fmax,
                record_every=args.record_every, checkpoint_every=args.checkpoint_every,
                resume=not args.no_resume,
                watchdog=Watchdog(curvature_every=args.curvature_every,
                                  max_energy_mismatch=args.max_energy_mismatch),
                progress=not args.quiet,
            )
        except MDWatchdogError as exc:  # a failed computation, not a user error: exit 3
            print(f"emlp md: watchdog: {exc}", file=sys.stderr)
            return 3
        except ValueError as exc:  # e.g. the output folder holds another run's checkpoint
            raise InputError(str(exc)) from exc
        finally:
            handlers()
        write_json(out / "settings.json", resolved)
        from emlpack.io import read_structures

        last = read_structures(out / "trajectory.xyz", "-1")[0]
        warnings = [f"bonding changed: {c}" for c in
                    bonding_changes(s.numbers, s.positions, last.positions)]
        energies = _final_energies(member, s, last, result.energy_scale)
        write_json(out / "summary.json", {**json.loads((out / "summary.json").read_text()),
                                          **energies})
        if result.watchdog_events:
            warnings.append(f"{result.watchdog_events} watchdog events (see md.log)")
        for w in warnings:
            log(f"warning: {w}")
        write_json(out / "warnings.json", {"warnings": warnings})
        if args.no_pairs:
            _write_atoms_only(out / "trajectory.xyz", out / "trajectory_atoms.xyz")
            log(f"wrote {out / 'trajectory_atoms.xyz'} (atoms only)")
        log(f"{result.steps} steps, {result.watchdog_events} watchdog events,"
            f" {result.evaluations_per_step:.2f} evaluations/step, final potential energy"
            f" {energies['energy_eV']:.6f} eV ({energies['energy_scale']} scale)"
            f" -> {result.output}")
        log("done with warnings" if warnings else "done")
        return 0

    p.set_defaults(func=run, resumable=True)


def _final_energies(member: ModelMember, structure: Structure, last: Structure,
                    scale: str) -> dict:
    """The last frame's potential and conserved energies for summary.json, as the trajectory
    holds them (on the DFT scale when ``scale`` is ``"dft"``), with the model's own and the
    relative energy beside them (:func:`energy_record`; the DFT shift is a constant of the
    composition)."""
    shift = member.dft_shift(structure.numbers) if scale == "dft" else 0.0
    record = energy_record(member, structure, last.info["potential_energy"] - shift)
    record["energy_scale"] = scale
    return {**record, "final_conserved_energy_eV": float(last.info["conserved_energy"])}


def _write_atoms_only(trajectory: Path, path: Path) -> None:
    """The frames of ``trajectory`` without their ``Es`` rows (:func:`emlpack.io.split_pairs`)."""
    import ase.io

    from emlpack._files import atomic_write
    from emlpack.io import split_pairs

    frames = []
    for atoms in ase.io.read(trajectory, ":", format="extxyz"):
        cores = split_pairs(atoms)
        cores.info.pop("electron_pairs", None)
        frames.append(cores)
    atomic_write(path, lambda fh: ase.io.write(fh, frames, format="extxyz"))


def _add_settings(json_path: str | None, args: argparse.Namespace) -> None:
    """Add the resolved settings to the JSON output an analysis function wrote."""
    import json
    from pathlib import Path

    if json_path and Path(json_path).is_file():
        data = json.loads(Path(json_path).read_text())
        data["settings"] = settings(args)
        write_json(json_path, data)


def _md_log_handlers(folder: Path):
    """Send the package's log (the MD driver's step lines and watchdog events, the solvers'
    warnings) to ``md.log``, and its warnings to stderr, where the progress bar shows the
    steps (none with --quiet), for the run; returns the function that removes the handlers
    again."""
    import logging

    from emlpack.dynamics.md import LOG

    log = logging.getLogger("emlpack")
    level = log.level
    log.setLevel(logging.INFO)
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(message)s")
    handlers = [logging.FileHandler((folder / LOG).resolve()), logging.StreamHandler()]
    handlers[1].setLevel(logging.WARNING)
    for handler in handlers:
        handler.setFormatter(fmt)
        log.addHandler(handler)

    def remove() -> None:
        for handler in handlers:
            log.removeHandler(handler)
            handler.close()
        log.setLevel(level)

    return remove


def add_md_analysis(sub: Subparsers) -> None:
    """Register ``emlp md-analysis``: conserved-quantity stability of MD trajectories (slope,
    max jump per atom; the paper's scatter plot)."""
    p = add_parser(sub, "md-analysis", "conserved-quantity stability of MD trajectories"
                   " (slope, max jump per atom; the paper's scatter plot)")
    p.add_argument("trajectories", nargs="+", help="extxyz trajectories written by 'emlp md'")
    p.add_argument("-o", "--output", help="JSON file with one entry per run")
    p.add_argument("--json", dest="output", help=argparse.SUPPRESS)
    p.add_argument("--plot", metavar="FILE.png",
                   help="scatter plot PNG (|slope| vs max jump, log-log)")
    p.add_argument("--series", metavar="FILE.png", help="PNG of E_cons(t) per atom of every run")
    p.add_argument("--discard", type=int, default=10, help="initial steps discarded")
    p.add_argument("--groups", nargs="+", help="one group name per trajectory (plot colours)")

    def run(args: argparse.Namespace):
        from emlpack.dynamics.analysis import run_analysis

        positive(args.discard, "--discard", allow_zero=True)
        try:
            run_analysis(args.trajectories, args.plot, args.output, args.discard, args.groups,
                         args.series, log=print)
        except ValueError as exc:  # the message names the file and frame
            raise InputError(str(exc)) from exc
        _add_settings(args.output, args)
        return 0

    p.set_defaults(func=run)


def add_md_ir(sub: Subparsers) -> None:
    """Register ``emlp md-ir``: IR spectrum from the dipole autocorrelation of an MD trajectory
    (JSON, optional PNG)."""
    p = add_parser(sub, "md-ir", "IR spectrum from the dipole autocorrelation of an MD"
                   " trajectory (JSON, optional PNG)")
    p.add_argument("trajectory", help="extxyz trajectory written by 'emlp md'")
    p.add_argument("-o", "--output", default="md_ir.json", help="JSON file of the spectrum")
    p.add_argument("--plot", metavar="FILE.png", help="PNG plot")
    p.add_argument("--png", dest="plot", help=argparse.SUPPRESS)
    p.add_argument("--harmonic", help="'emlp ir' JSON to overlay (harmonic spectrum)")
    p.add_argument("--temperature", type=float, help="K (default: mean of the frames)")
    p.add_argument("--discard", type=int, default=0, help="initial steps discarded")
    p.add_argument("--window", default="hann", choices=["hann", "gaussian", "none"],
                   help="lag window")
    p.add_argument("--correction", default="harmonic",
                   choices=["harmonic", "schofield", "standard", "none"],
                   help="quantum correction factor")
    p.add_argument("--padding", type=int, default=8, help="zero-padding factor")

    def run(args: argparse.Namespace):
        from emlpack.dynamics.analysis import run_md_ir

        positive(args.temperature, "--temperature")
        positive(args.discard, "--discard", allow_zero=True)
        positive(args.padding, "--padding")
        try:
            run_md_ir(args.trajectory, args.output, args.plot, args.harmonic,
                      args.temperature, args.discard, window=args.window,
                      correction=args.correction, padding=args.padding, log=print)
        except ValueError as exc:  # too few frames, no dipoles: the message names the file
            raise InputError(str(exc)) from exc
        _add_settings(args.output, args)
        return 0

    p.set_defaults(func=run)


COMMANDS = [add_md, add_md_analysis, add_md_ir]
