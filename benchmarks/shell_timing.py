"""What the shell-timing benchmarks (first_call.py, tricks.py) share: a timed command and a
Markdown report named after the machine."""

import os
import platform
import subprocess
import time
from pathlib import Path


def timed(cmd, env) -> float:
    """Wall seconds of ``cmd`` run to its end (its output dropped; a failure raises)."""
    start = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def report(out, stem: str, title: str, intro: str, columns: list[str], rows: list[tuple]) -> str:
    """Write ``<out>/<stem>-<host>.md``: the title with the machine (cores, pinned or not),
    ``intro``, and a table of ``rows`` under ``columns`` (floats to 2 decimals). Returns it."""
    host = platform.node() or "host"
    pinned = "pinned" if len(os.sched_getaffinity(0)) == 1 else "unpinned"
    cell = lambda v: f"{v:.2f}" if isinstance(v, float) else str(v)  # noqa: E731
    text = (f"# {title} ({host}, {os.cpu_count()} cores, {pinned})\n\n{intro}\n\n"
            f"| {' | '.join(columns)} |\n|{'---|' * len(columns)}\n"
            + "".join(f"| {' | '.join(cell(v) for v in row)} |\n" for row in rows))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}-{host}.md").write_text(text)
    return text


# Example 1's nominal model (the true one: its perturbation is the cubic spring alone).
NOMINAL = "M = [[1.0]]\nC = [[2.0]]\nK = [[1000.0]]\nB = [[0.5]]\n"


def example1_files(folder: Path) -> Path:
    """Example 1 measured for 1 s at 1 kHz, 5% noise on every signal, written as
    ``<folder>/data.csv`` (``t,x1,x2,u1``) with ``<folder>/nominal.toml``; returns the CSV."""
    import jax
    import numpy as np

    from dtwin_jax import measure
    from dtwin_jax.models import systems

    ex = systems.example1()
    sim = systems.simulate_example(ex, jax.random.key(0))
    meas = measure(jax.random.key(1), sim["t"], sim["x"], sim["xdot"], sim["u"], level=0.05)
    rows = np.column_stack([np.asarray(meas.t), np.asarray(meas.x), np.asarray(meas.u)])
    path = Path(folder) / "data.csv"
    path.write_text("t,x1,x2,u1\n" + "\n".join(",".join(f"{v:.10g}" for v in r) for r in rows) + "\n")
    (Path(folder) / "nominal.toml").write_text(NOMINAL)
    return path
