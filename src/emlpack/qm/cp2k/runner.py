"""Running CP2K: one process group per run (``mpirun`` and its ranks), stopped on timeout or
interrupt, and terminated with its parent so a killed job leaves no orphaned CP2K."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

from emlpack.qm.cp2k.output import CP2KError, output_tail


def run_cp2k(command: list[str], run_dir: Path, omp_threads: int, timeout_s: float,
             where: str) -> str:
    """Run ``command`` in ``run_dir`` (input ``emlp.inp``, output ``emlp.out``) and return the
    output text; :class:`CP2KError` when CP2K fails, times out or does not finish."""
    env = dict(os.environ, OMP_NUM_THREADS=str(int(omp_threads)))
    with open(run_dir / "stdout.txt", "w") as out:
        proc = subprocess.Popen(command, cwd=run_dir, env=env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True,
                                preexec_fn=terminate_with_parent)
        try:
            rc = proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            stop_group(proc)
            output = read_text(run_dir / "emlp.out")
            raise CP2KError(f"{where}: CP2K timed out after {timeout_s} s; output tail:\n"
                            f"{output_tail(output)}") from None
        except BaseException:
            # interrupted (Ctrl-C, SystemExit, a Dask cancellation): never leave CP2K running
            stop_group(proc)
            raise
    output = read_text(run_dir / "emlp.out")
    if rc != 0 or "PROGRAM ENDED AT" not in output:
        raise CP2KError(
            f"{where}: CP2K failed (exit code {rc}); output tail:\n{output_tail(output)}\n"
            f"launcher output tail:\n{output_tail(read_text(run_dir / 'stdout.txt'), 15)}"
        )
    return output


def stop_group(proc: subprocess.Popen) -> None:
    """Terminate CP2K's process group (mpirun and its ranks), then kill it if it lingers."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    except ProcessLookupError:
        pass


def terminate_with_parent() -> None:
    """In the child before exec: ask Linux to send SIGTERM when the labeling process dies
    (even by SIGKILL), so a killed job leaves no orphaned CP2K behind. No-op elsewhere."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def read_text(path: Path) -> str:
    """The text of ``path`` (undecodable bytes replaced), or "" when it does not exist."""
    return path.read_text(errors="replace") if path.exists() else ""
