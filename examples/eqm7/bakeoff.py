"""The bake-off of mini-eQM7 v2 (issue 51): training recipes at equal CPU time, judged on the
card's validation molecules.

Each candidate of ``bakeoff.yaml`` is a list of training overrides (train.yaml's recipe, another
family, a pretrained start, a loss term) and the epochs per halving of its learning rate. Per
candidate, one model (seed 0, augmented) is trained for exactly ``cpu_minutes`` CPU minutes
(``training.max_cpu_minutes``: the training process's CPU time summed over resumes, no step
schedule, no early stopping) and judged by ``run_study.py``'s stages with ``split: val`` in its
own workdir ``runs/bakeoff/NAME``: train, evaluate (the shards' validation configurations),
polarizability (at the validation references of ``validation_references.py``), md (500 fs at
300 K per validation molecule, ``md_molecules`` of them). Nothing here looks at a test
molecule. Every stage is resumable: a finished output is skipped, an unfinished training goes
on from its last.pt with the CPU budget it has left.

``table`` writes ``RESULTS_DIR/bakeoff.md`` and ``bakeoff.json``, one row per candidate, from
``run_study``'s summaries (eval_summary, polarizability_summary, md_summary): CPU minutes
spent, epochs, validation core-force and pair-force MAE (static, meV/Å), pair-field slope,
isotropic polarizability error (median |Δα_iso|/α_iso,DFT and how many molecules within 10 %),
median component error (bohr³), dynamic error rate (failed pair relaxations, %), MD stable runs
of all and runs whose bonding changed; a stage not finished shows "pending".

Usage (from the project root)::

    OMP_NUM_THREADS=1 python examples/eqm7/bakeoff.py run [--only NAME ...] [--commit]
    python examples/eqm7/bakeoff.py table [--only NAME ...]
    python examples/eqm7/bakeoff.py done      # exit status 0 when every candidate is complete

``run`` writes the table after each candidate (``--commit``: and commits it); ``key=value``
arguments override bakeoff.yaml (e.g. ``cpu_minutes=30 md_molecules=3``).
"""

from __future__ import annotations

import argparse
import copy
import datetime as dt
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
import run_study  # noqa: E402  (examples/eqm7/run_study.py)

#: run_study's stages of every candidate, in order
STAGES = ("train", "evaluate", "polarizability", "md")
SET = "val"  # the bake-off's molecules: the card's validation split, never the test one


# ---------------------------------------------------------------------- config
def load_bakeoff(path: str | Path = HERE / "bakeoff.yaml", overrides: list[str] = ()) -> dict:
    """bakeoff.yaml with ``key=value`` overrides, checked: one clear line for a bad entry."""
    from emlpack.overrides import OverrideError, apply_overrides, load_yaml

    path = Path(path)
    if not path.is_file():
        raise SystemExit(f"{path}: no such file")
    cfg = load_yaml(path.read_text()) or {}
    try:
        apply_overrides(cfg, overrides)
    except OverrideError as exc:
        raise SystemExit(str(exc)) from None
    cfg.setdefault("study", "config.yaml")
    cfg.setdefault("workdir", "runs/bakeoff")
    cfg.setdefault("results_dir", str(HERE))
    cfg.setdefault("cpu_minutes", 120)
    cfg.setdefault("seed", 0)
    cfg.setdefault("group", "aug")
    cfg.setdefault("lr", 1e-3)
    cfg.setdefault("decay_cpu_minutes", None)
    for key in ("train_overrides", "study_overrides"):
        cfg[key] = list(cfg.get(key) or [])
    where = f"{path.name}"
    if not _positive(cfg["cpu_minutes"]):
        raise SystemExit(f"{where}: cpu_minutes must be a positive number, got"
                         f" {cfg['cpu_minutes']!r}")
    if cfg.get("md_molecules") is not None and not (
            isinstance(cfg["md_molecules"], int) and cfg["md_molecules"] > 0):
        raise SystemExit(f"{where}: md_molecules must be null or a positive integer, got"
                         f" {cfg['md_molecules']!r}")
    candidates = cfg.get("candidates")
    if not isinstance(candidates, dict) or not candidates:
        raise SystemExit(f"{where}: candidates must map names to {{decay_epochs, overrides}}")
    for name, c in candidates.items():
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", str(name)):
            raise SystemExit(f"{where}: candidate name {name!r}: letters, digits, . _ - only"
                             " (it names a folder)")
        if not isinstance(c, dict) or not (
                _positive(c.get("decay_epochs")) or (c.get("decay_epochs") is None
                                                     and _positive(cfg["decay_cpu_minutes"]))):
            raise SystemExit(f"{where}: candidate {name}: decay_epochs (a positive number of"
                             " epochs per halving of the learning rate) is required unless"
                             " decay_cpu_minutes (every candidate's) is set")
        over = c.get("overrides") or []
        if not isinstance(over, list) or not all(isinstance(o, str) and "=" in o for o in over):
            raise SystemExit(f"{where}: candidate {name}: overrides must be a list of"
                             " 'key=value' strings")
        c["overrides"] = over
    return cfg


def _positive(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and x > 0


def chosen(bake: dict, only: list[str] | None) -> list[str]:
    """The candidates named by ``--only`` (all when none), in bakeoff.yaml's order."""
    names = list(bake["candidates"])
    unknown = sorted(set(only or ()) - set(names))
    if unknown:
        raise SystemExit(f"--only: unknown candidate(s) {unknown} (known: {names})")
    return [n for n in names if not only or n in only]


def training_overrides(bake: dict, name: str) -> list[str]:
    """The training overrides of candidate ``name``'s model: the CPU budget and no other
    stop (no wall-time limit, no early stopping, epochs unbounded), lr halved every
    ``decay_epochs`` (the candidate's) or else every ``decay_cpu_minutes`` of CPU time, then
    ``train_overrides`` and the candidate's own."""
    c = bake["candidates"][name]
    schedule = ([f"training.decay_epochs={c['decay_epochs']}"] if c.get("decay_epochs")
                else [f"training.decay_cpu_minutes={bake['decay_cpu_minutes']}"])
    return [f"training.max_cpu_minutes={bake['cpu_minutes']}", "training.max_time_minutes=null",
            "training.max_epochs=100000000", "training.patience=null",
            f"training.lr={bake['lr']}", *schedule, *bake["train_overrides"], *c["overrides"]]


def schedule_text(bake: dict, name: str) -> str:
    """How candidate ``name``'s learning rate halves, in words."""
    c = bake["candidates"][name]
    if c.get("decay_epochs"):
        return f"every {c['decay_epochs']:g} epochs"
    return f"every {bake['decay_cpu_minutes']:g} CPU minutes"


def candidate_config(bake: dict, name: str) -> dict:
    """run_study's config of candidate ``name``: split val, workdir WORKDIR/NAME, one model
    (``seed``, ``group``), no step schedule, its training overrides, ``md_molecules``."""
    study = Path(bake["study"])
    cfg = run_study.load_config(study if study.is_absolute() else HERE / study,
                                bake["study_overrides"])
    cfg.update(workdir=str(Path(bake["workdir"]) / name), split=SET,
               seeds=[int(bake["seed"])], groups=[str(bake["group"])])
    t = cfg.setdefault("training", {})
    t.update(steps=None, overrides=[*(t.get("overrides") or []),
                                    *training_overrides(bake, name)])
    t["snapshots"] = str(Path(bake["snapshots"]) / name) if bake.get("snapshots") else None
    if bake.get("md_molecules"):
        cfg.setdefault("md", {})["max_molecules"] = int(bake["md_molecules"])
    return cfg


def check_candidate(cfg: dict, name: str) -> None:
    """Stop with one line when candidate ``name``'s training config is wrong (before any
    candidate trains)."""
    from emlpack.errors import EmlpackError
    from emlpack.train.config import load_config as load_train_config

    t = cfg["training"]
    group, seed = cfg["groups"][0], cfg["seeds"][0]
    try:
        load_train_config(run_study._resolve(t.get("config", "train.yaml")),
                          run_study.model_overrides(t, group, seed))
    except (EmlpackError, ValueError) as exc:
        raise SystemExit(f"bakeoff: candidate {name}: {exc}") from None


# ---------------------------------------------------------------------- status
def model_name(bake: dict) -> str:
    return f"{bake['group']}-s{bake['seed']}"


def pending_stages(study: run_study.Study, bake: dict) -> list[str]:
    """The stages of a candidate whose outputs are not all there yet (a polarizability file
    that lacks a reference molecule, e.g. a validation reference that came later, is
    pending)."""
    name = model_name(bake)
    run = study.model_dir(bake["group"], bake["seed"])
    done = {"train": (run / "done.json").exists() and (run / "best.pt").exists(),
            "evaluate": run_study.stage_file(study, "eval", name, SET).exists()}
    refs = run_study.dft_results(study)
    pol = run_study._read_json(run_study.stage_file(study, "polarizability", name))
    done["polarizability"] = bool(refs) and pol is not None and set(pol["molecules"]) >= set(refs)
    done["md"] = all((study.workdir / "md" / name / row["name"] / "analysis.json").exists()
                     for row in study.md_molecules())
    return [s for s in STAGES if not done[s]]


# ---------------------------------------------------------------------- rows
def _group(summary: dict | None, group: str) -> dict:
    return ((summary or {}).get("groups") or {}).get(group) or {}


def _mean(entry: dict | None, scale: float = 1.0) -> float | None:
    v = (entry or {}).get("mean")
    return None if v is None else scale * v


def candidate_row(bake: dict, name: str) -> dict:
    """One candidate's row of the table (bakeoff.json), None where not measured yet."""
    cfg = candidate_config(bake, name)
    study = run_study.Study(copy.deepcopy(cfg), log=lambda m: None)
    group, model = bake["group"], model_name(bake)
    run = study.model_dir(group, bake["seed"])
    pending = pending_stages(study, bake)
    done = run_study._read_json(run / "done.json") or {}
    progress = run_study.training_progress(run) or {}
    cpu = done.get("cpu_seconds") or progress.get("cpu_seconds")
    ev = _group(run_study.eval_summary(study, SET), group)
    static, dynamic = ev.get("static") or {}, ev.get("dynamic") or {}
    pol = run_study.polarizability_summary(study)
    per = (_group(pol, group).get("per_model") or {}).get(model) or {}
    md = _group(run_study.md_summary(study), group)
    return {
        "name": name, "overrides": bake["candidates"][name]["overrides"],
        "decay_epochs": bake["candidates"][name].get("decay_epochs"),
        "schedule": schedule_text(bake, name),
        "cpu_budget_minutes": bake["cpu_minutes"], "workdir": str(study.workdir),
        "complete": not pending, "pending": pending,
        "training": {"cpu_minutes": None if cpu is None else cpu / 60.0,
                     "epochs": done.get("epochs") or progress.get("epochs"),
                     "best_epoch": done.get("best_epoch"), "finished": "train" not in pending},
        "validation": {
            "configurations": ev.get("n_structures"),
            "forces_mae_meV_per_A": _mean((static.get("mae") or {}).get("forces"), 1000.0),
            "pair_forces_mae_meV_per_A": _mean((static.get("mae") or {}).get("pair_forces"),
                                               1000.0),
            "pair_field_slope": _mean(static.get("pair_field_slope")),
            "dynamic_error_rate_pct": _mean(dynamic.get("error_rate"), 100.0)},
        "polarizability": {
            "molecules": (pol or {}).get("n_molecules"),
            "isotropic_median_relative_error": per.get("isotropic_median"),
            "isotropic_within_10pct": per.get("isotropic_within_10pct"),
            "isotropic_compared": per.get("isotropic_compared"),
            "component_median_bohr3": per.get("median"),
            "failure_rate": per.get("error_rate")},
        "md": {"molecules": len(study.md_molecules()),
               **{k: md.get(k) for k in ("runs", "stable", "transition", "unstable",
                                         "bonding_changed", "stopped", "max_jump_max")}},
    }


# ---------------------------------------------------------------------- table
def _cell(value, stage: str, row: dict, fmt: str = "{:.1f}") -> str:
    if value is None:
        return "pending" if stage in row["pending"] else "–"
    return fmt.format(value)


def markdown(result: dict) -> str:
    """bakeoff.md: the rows of ``result`` (bakeoff.json) as one table, with the setup."""
    b = result["setup"]
    lines = [
        "# mini-eQM7 v2 bake-off (issue 51): recipes at equal CPU time", "",
        f"Generated by `examples/eqm7/bakeoff.py table` on {result['generated']}. Judged on"
        f" the card's {b['validation_molecules']} validation molecules only (never the test"
        f" ones): static errors on {b['validation_configurations'] or 'the'} validation"
        " configurations of the shards, polarizabilities at"
        f" {b['references']} of {b['validation_molecules']} DFT validation references"
        f" (PBE0/aug-cc-pVTZ, `{b['references_dir']}`), MD {b['md']}.", "",
        f"One model per candidate: seed {b['seed']}, {run_study.GROUP_LABEL[b['group']]},"
        f" {b['cpu_minutes']:g} CPU minutes of training each (`training.max_cpu_minutes`, over"
        f" all resumes; no step schedule, no early stopping), lr {b['lr']:g} halved as each"
        " candidate says below. A stage not finished yet: pending.", "",
        "| candidate | CPU min | epochs | core-force MAE [meV/Å] | pair-force MAE [meV/Å] |"
        " pair-field slope | α_iso median \\|Δ\\|/DFT | α_iso within 10 % |"
        " α components median [bohr³] | dynamic error rate [%] | MD stable / runs |"
        " MD bonding changed |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        t, v, p, m = r["training"], r["validation"], r["polarizability"], r["md"]
        cpu = _cell(t["cpu_minutes"], "train", r)
        epochs = "–" if t["epochs"] is None else str(t["epochs"])
        if "train" in r["pending"]:  # under way (or not started): its progress so far
            cpu = "pending" if t["cpu_minutes"] is None else f"{t['cpu_minutes']:.1f} (training)"
            epochs = "pending" if t["epochs"] is None else f"{t['epochs']} (training)"
        iso = _cell(p["isotropic_median_relative_error"], "polarizability", r, "{:.1%}")
        within = ("pending" if "polarizability" in r["pending"] or p["isotropic_compared"] is None
                  else f"{p['isotropic_within_10pct']} of {p['molecules']}")
        runs = ("pending" if "md" in r["pending"] or m["runs"] is None
                else f"{m['stable']} / {m['runs']}")
        bonding = "pending" if runs == "pending" else str(m["bonding_changed"])
        lines.append(
            f"| {r['name']} | {cpu} | {epochs} |"
            f" {_cell(v['forces_mae_meV_per_A'], 'evaluate', r)} |"
            f" {_cell(v['pair_forces_mae_meV_per_A'], 'evaluate', r)} |"
            f" {_cell(v['pair_field_slope'], 'evaluate', r, '{:.2f}')} | {iso} | {within} |"
            f" {_cell(p['component_median_bohr3'], 'polarizability', r, '{:.2f}')} |"
            f" {_cell(v['dynamic_error_rate_pct'], 'evaluate', r, '{:.2f}')} | {runs} |"
            f" {bonding} |")
    lines += ["", "Columns: CPU minutes the training took (all resumes) and its epochs; static"
              " errors with the pairs at the DFT centres; pair-field slope: of the pair-force"
              " error on the field force qE (0: the pairs respond to a field as the DFT centres"
              " do, 0.5: about twice too soft); isotropic polarizability at the reference"
              " geometry (pairs relaxed from the DFT centres, cores clamped) against DFT, a"
              " failed relaxation counted outside 10 %; dynamic error rate: failed pair"
              " relaxations of the validation configurations; MD: stable runs of those done and"
              " runs whose bonding changed.", "", "Candidates (training overrides of"
              " `examples/eqm7/train.yaml`):", ""]
    for r in result["rows"]:
        over = ", ".join(f"`{o}`" for o in r["overrides"]) or "train.yaml as is"
        lines.append(f"- **{r['name']}**: {over}; lr halved {r['schedule']}"
                     f"{'' if r['complete'] else '; pending: ' + ', '.join(r['pending'])}.")
    return "\n".join(lines) + "\n"


def table(bake: dict, names: list[str], log=print) -> dict:
    """bakeoff.json and bakeoff.md in ``results_dir`` with the rows of ``names``."""
    rows = [candidate_row(bake, name) for name in names]
    study = run_study.Study(candidate_config(bake, names[0]), log=lambda m: None)
    c = study.cfg.get("md", {})
    md = (f"{c.get('time_fs', 500.0):g} fs NVT at {c.get('temperature_K', 300.0):g} K on"
          f" {len(study.md_molecules())} of them")
    val = study.shards().split_indices()[SET]
    result = {
        "generated": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "setup": {"cpu_minutes": bake["cpu_minutes"], "seed": bake["seed"],
                  "group": bake["group"], "lr": bake["lr"], "md": md,
                  "validation_molecules": len(study.split_molecules()),
                  "validation_configurations": len(run_study._subsample(
                      list(val), study.cfg.get("evaluate", {}).get("max_structures"))),
                  "references": len(run_study.dft_results(study)),
                  "references_dir": str(study.dft_dir),
                  "train_overrides": bake["train_overrides"],
                  "study_overrides": bake["study_overrides"]},
        "complete": all(r["complete"] for r in rows),
        "rows": rows,
    }
    out = Path(bake["results_dir"])
    run_study._write_json(out / "bakeoff.json", result)
    run_study._write_text(out / "bakeoff.md", markdown(result))
    log(f"bakeoff: {out / 'bakeoff.md'} ({sum(r['complete'] for r in rows)} of {len(rows)}"
        " candidates complete)")
    return result


def commit(bake: dict, message: str) -> None:
    from emlpack.commits import git_commit

    out = Path(bake["results_dir"])
    git_commit([out / "bakeoff.md", out / "bakeoff.json"], message)


# ---------------------------------------------------------------------- run
def run(bake: dict, names: list[str], log=print, commit_table: bool = False) -> dict:
    """run_study's stages of each candidate in ``names`` (split val, its own workdir), the
    table (every candidate's rows) after each; ``commit_table``: and commit it. Returns each
    candidate's ``Study.work`` (the work actually done)."""
    configs = {name: candidate_config(bake, name) for name in names}
    for name, cfg in configs.items():
        check_candidate(cfg, name)
    work = {}
    for name, cfg in configs.items():
        log(f"bakeoff: {name} ({', '.join(bake['candidates'][name]['overrides']) or 'train.yaml'}"
            f"; {bake['cpu_minutes']:g} CPU min) in {cfg['workdir']}")
        study = run_study.run(list(STAGES), cfg, log=log)
        work[name] = dict(study.work)
        table(bake, list(bake["candidates"]), log=log)
        if commit_table:
            commit(bake, f"bake-off: {name} ({', '.join(STAGES)}), table")
    return work


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("action", choices=("run", "table", "done"))
    p.add_argument("overrides", nargs="*", help="key=value overrides of bakeoff.yaml")
    p.add_argument("--only", nargs="+", metavar="NAME", help="these candidates only")
    p.add_argument("--config", default=str(HERE / "bakeoff.yaml"))
    p.add_argument("--commit", action="store_true", help="commit bakeoff.md/json as they change")
    args = p.parse_args(argv)
    bake = load_bakeoff(args.config, args.overrides)
    names = chosen(bake, args.only)

    def log(m: str) -> None:
        print(f"[{dt.datetime.now(dt.timezone.utc):%H:%M:%S}] {m}", flush=True)

    if args.action == "run":
        run(bake, names, log, commit_table=args.commit)
    elif args.action == "table":
        table(bake, names, log)
        if args.commit:
            commit(bake, "bake-off: table")
    else:
        left = {n: pending_stages(run_study.Study(candidate_config(bake, n),
                                                  log=lambda m: None), bake) for n in names}
        for n, stages in left.items():
            print(f"{n}: {'complete' if not stages else 'pending: ' + ', '.join(stages)}")
        return 0 if not any(left.values()) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
