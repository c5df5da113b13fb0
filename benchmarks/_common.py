"""Shared helpers of the benchmarks (not part of the package or its tests)."""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("EMLP_SHARED", ROOT.parent / "shared"))
DATA = SHARED / "data" / "eqm7_pbe0_subset.xyz"
FIXTURES = SHARED / "fixtures" / "reference_tf"


def paper_model(dtype: torch.dtype):
    """The paper-size model with the fixture weights (random, seeded by the fixture author)."""
    from emlpack.legacy.reference_weights import model_from_reference

    weights = dict(np.load(FIXTURES / "weights_paper.npz"))
    hparams = json.loads((FIXTURES / "hparams_paper.json").read_text())["constructor_kwargs"]
    model = model_from_reference(weights, hparams, dtype)
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


TRAINED = ROOT / "benchmarks" / "fixtures" / "eqm7_small_trained.pt"


def trained_model(dtype: torch.dtype = torch.float64):
    """The small model trained once on the shared eqm7 subset (see fixtures/README.md)."""
    from emlpack.nn.checkpoint import load_model

    model = load_model(TRAINED, dtype=dtype)
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


def benchmark_model(name: str, dtype: torch.dtype = torch.float64):
    """``fixture`` (paper size, random weights), ``trained`` or a checkpoint path."""
    if name == "fixture":
        return paper_model(dtype)
    if name == "trained":
        return trained_model(dtype)
    from emlpack.nn.checkpoint import load_model

    model = load_model(name, dtype=dtype)
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


class CpuClock:
    """CPU time of this process (user + system, all threads) since construction."""

    def __init__(self) -> None:
        self.start = time.process_time()

    def elapsed(self) -> float:
        return time.process_time() - self.start


def load_structures():
    from emlpack.io import read_structures

    return read_structures(DATA)


def machine_info() -> dict:
    info = {
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_num_threads": torch.get_num_threads(),
        "torch_num_interop_threads": torch.get_num_interop_threads(),
        "numpy": np.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": _cpu_model(),
    }
    info["omp_num_threads"] = os.environ.get("OMP_NUM_THREADS")
    info["omp_wait_policy"] = os.environ.get("OMP_WAIT_POLICY")
    try:
        info["load_average"] = list(os.getloadavg())
    except OSError:
        pass
    return info


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def write_json(path: str | os.PathLike, data: dict) -> None:
    """Write ``data`` atomically (temporary file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2, default=_jsonable)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _jsonable(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")
