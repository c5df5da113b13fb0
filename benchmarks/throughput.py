"""Throughput benchmark: energy + forces of the 600 shared eqm7 configurations (1s core centres
removed) in batches of 64, paper-size hyperparameters, float32, CPU.

Codes, alternated run by run in one process (the machine is shared, so only ratios measured
this way are meaningful):

* emlpack, with the fixture weights: "graph" = batching and half neighbour lists (vesin)
  included, i.e. ``model.graph(batch)`` + ``model(g)``; "model" = graphs built beforehand.
* SchNetPack 2.1.1 SchNet at the same hyperparameters (512 features, 128 filters, 32 Gaussians,
  4 interactions, cosine cutoff 4 Å, default Atomwise head 512 -> 256 -> 1, forces by autograd),
  electron pairs as species Z = 99 (its embedding has 100 rows). "precomputed" = neighbour
  lists (MatScipyNeighborList, full lists) and collated batches built beforehand; "included" =
  neighbour lists and collation (``_atoms_collate_fn``) inside the timed loop.
  Note SchNetPack's SchNet is not the same network: its interaction output is 128->512->512
  where the eMLP's is 128->128->512, and its filters are computed per directed edge.

Usage: python benchmarks/throughput.py --json benchmarks/results/throughput.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import typing
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import load_structures, machine_info, paper_model, write_json  # noqa: E402

PAIR_Z = 99


def import_schnetpack():
    """Import SchNetPack 2.1.1 under torch >= 2.x, which no longer exports ``T_co``."""
    import torch.utils.data.dataloader as dataloader

    if not hasattr(dataloader, "T_co"):
        dataloader.T_co = typing.TypeVar("T_co", covariant=True)
    import schnetpack

    return schnetpack


def build_schnetpack(spk, cutoff: float = 4.0):
    torch.manual_seed(0)
    representation = spk.representation.SchNet(
        n_atom_basis=512,
        n_interactions=4,
        radial_basis=spk.nn.GaussianRBF(n_rbf=32, cutoff=cutoff),
        cutoff_fn=spk.nn.CosineCutoff(cutoff),
        n_filters=128,
    )
    model = spk.model.NeuralNetworkPotential(
        representation=representation,
        input_modules=[spk.atomistic.PairwiseDistances()],
        output_modules=[
            spk.atomistic.Atomwise(n_in=512, output_key="energy"),
            spk.atomistic.Forces(energy_key="energy", force_key="forces"),
        ],
    )
    model.eval()
    return model.to(torch.float32)


def spk_inputs(spk, s, idx: int) -> dict:
    p = spk.properties
    z = np.concatenate([s.numbers, np.full(s.n_pairs, PAIR_Z)])
    return {
        p.idx: torch.tensor([idx]),
        p.Z: torch.as_tensor(z, dtype=torch.long),
        p.R: torch.as_tensor(s.all_positions, dtype=torch.float32),
        p.cell: torch.zeros(1, 3, 3),
        p.pbc: torch.zeros(1, 3, dtype=torch.bool),
        p.n_atoms: torch.tensor([len(z)]),
    }


def batches(seq, size):
    return [seq[k : k + size] for k in range(0, len(seq), size)]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", help="write the results to this file (atomically)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per code (median)")
    ap.add_argument("--limit", type=int, default=600, help="number of configurations")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    ap.add_argument("--no-schnetpack", action="store_true", help="time emlpack only")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    structures = load_structures()[: args.limit]
    n = len(structures)
    groups = batches(structures, args.batch_size)
    model = paper_model(torch.float32)
    graphs = [model.graph(b, dtype=torch.float32) for b in groups]

    def ours_model_only():
        for g in graphs:
            out = model(g, forces=True, create_graph=False)
            out["forces"].sum().item()

    def ours_with_graph():
        for b in groups:
            g = model.graph(b, dtype=torch.float32)
            out = model(g, forces=True, create_graph=False)
            out["forces"].sum().item()

    runners = {"emlpack_model_only": ours_model_only, "emlpack_graph_included": ours_with_graph}

    spk_info = None
    if not args.no_schnetpack:
        spk = import_schnetpack()
        from schnetpack.data.loader import _atoms_collate_fn

        spk_model = build_schnetpack(spk)
        nl = spk.transform.MatScipyNeighborList(cutoff=4.0)
        raw = [spk_inputs(spk, s, k) for k, s in enumerate(structures)]
        pre = [_atoms_collate_fn([nl(dict(d)) for d in b]) for b in batches(raw, args.batch_size)]

        def spk_precomputed():
            for batch in pre:
                out = spk_model(dict(batch))
                out["forces"].sum().item()

        def spk_included():
            for b in batches(raw, args.batch_size):
                batch = _atoms_collate_fn([nl(dict(d)) for d in b])
                out = spk_model(batch)
                out["forces"].sum().item()

        runners["schnetpack_nl_precomputed"] = spk_precomputed
        runners["schnetpack_nl_included"] = spk_included
        n_edges = sum(len(b[spk.properties.idx_i]) for b in pre)
        spk_info = {
            "version": spk.__version__,
            "neighbor_list": "MatScipyNeighborList (full list)",
            "parameters": sum(p.numel() for p in spk_model.parameters()),
            "directed_edges_per_config": n_edges / n,
            "pair_species_Z": PAIR_Z,
            "embedding_rows": spk_model.representation.embedding.num_embeddings,
            "output_head": "Atomwise default: 512 -> 256 -> 1",
            "difference": "interaction output 128->512->512 (eMLP: 128->128->512), filters per"
            " directed edge, default head 512->256->1 (eMLP: 512->512->256->1)",
        }
        # sanity: both codes see the same neighbours (directed vs undirected edges)
        n_half = sum(len(g.edge_i) for g in graphs)
        spk_info["edge_check"] = {"emlpack_half_edges": n_half, "spk_directed": n_edges}

    # warm-up (allocator, thread pools, lazy imports)
    for run in runners.values():
        run()
    times: dict[str, list[float]] = {k: [] for k in runners}
    for rep in range(args.repeats):
        order = list(runners) if rep % 2 == 0 else list(reversed(list(runners)))
        for key in order:
            t0 = time.perf_counter()
            runners[key]()
            times[key].append(time.perf_counter() - t0)
        summary = ", ".join(f"{k} {n / statistics.median(v):.0f}" for k, v in times.items())
        print(f"run {rep + 1}/{args.repeats}: configs/s {summary}", flush=True)

    def stats(ts):
        return {
            "configs_per_s_median": n / statistics.median(ts),
            "configs_per_s_min": n / max(ts),
            "configs_per_s_max": n / min(ts),
            "seconds": ts,
        }

    results = {k: stats(v) for k, v in times.items()}
    # batch-1 latency: one energy + forces call on one configuration, graph building included
    # (what a calculator call costs once its pairs are relaxed); median of 50 after a warm-up
    one = structures[min(400, n - 1)]  # ethanol in the full set
    for _ in range(3):
        model(model.graph([one], dtype=torch.float32), forces=True)["forces"].sum().item()
    wall, cpu = [], []
    for _ in range(50):
        t0, c0 = time.perf_counter(), time.process_time()
        model(model.graph([one], dtype=torch.float32), forces=True)["forces"].sum().item()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    latency = {"structure": one.source, "particles": one.n_cores + one.n_pairs,
               "wall_ms_median": 1e3 * statistics.median(wall),
               "cpu_ms_median": 1e3 * statistics.median(cpu)}
    print(f"batch-1 latency (energy + forces, graph included): {latency['wall_ms_median']:.1f}"
          f" ms wall, {latency['cpu_ms_median']:.1f} ms CPU", flush=True)
    # per-run ratios of neighbouring runs (alternated), median
    out = {
        "benchmark": "throughput",
        "n_configs": n,
        "batch_size": args.batch_size,
        "n_batches": len(groups),
        "repeats": args.repeats,
        "dtype": "float32",
        "device": "cpu",
        "particles_per_config": sum(s.n_cores + s.n_pairs for s in structures) / n,
        "emlpack_parameters": model.n_parameters(),
        "results": results,
        "batch1_latency": latency,
        "schnetpack": spk_info,
        "machine": machine_info(),
    }
    if spk_info is not None:
        def ratio(a, b):
            per_run = [tb / ta for ta, tb in zip(times[a], times[b], strict=False)]
            return {
                "median_of_per_run_ratios": statistics.median(per_run),
                "ratio_of_medians": statistics.median(times[b]) / statistics.median(times[a]),
                "per_run": per_run,
            }

        out["ratios"] = {
            "model_only_vs_nl_precomputed": ratio(
                "emlpack_model_only", "schnetpack_nl_precomputed"
            ),
            "graph_included_vs_nl_included": ratio(
                "emlpack_graph_included", "schnetpack_nl_included"
            ),
        }
        out["ratio_vs_schnetpack"] = out["ratios"]["model_only_vs_nl_precomputed"][
            "median_of_per_run_ratios"
        ]
        out["ratio_vs_schnetpack_comparison"] = (
            "like for like: emlpack model only (graphs built beforehand) vs SchNetPack with"
            " neighbour lists precomputed and batches collated beforehand; median over runs of"
            " the per-run ratio (runs alternated)"
        )
    if args.json:
        write_json(args.json, out)
    print({k: round(v["configs_per_s_median"], 1) for k, v in results.items()})
    if "ratios" in out:
        print({k: round(v["median_of_per_run_ratios"], 3) for k, v in out["ratios"].items()})
    return out


if __name__ == "__main__":
    main()
