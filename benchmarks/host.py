"""What a benchmark prints beside its figures about the host it ran on.

Kept apart from the benchmarks so that one which needs only torch (a GPU machine without
the renderer's packages) can import it.
"""

from __future__ import annotations

import resource
from pathlib import Path

SHIPPED_CONFIG = Path(__file__).resolve().parents[1] / "config" / "config.yaml"


def cpu_simd() -> str:
    """The widest x86 vector extension the CPU reports (Linux), which sets drjit's lane
    count and Embree's packet size: figures from hosts that differ here do not compare."""
    try:
        with open("/proc/cpuinfo") as fh:
            flags = next((ln.split(":", 1)[1].split() for ln in fh if ln.startswith("flags")), [])
    except OSError:
        return "unknown"
    return next((f for f in ("avx512f", "avx2", "avx", "sse4_2") if f in flags), "unknown")


def rss_mb() -> float:
    """Current resident set size in MiB (Linux /proc)."""
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * resource.getpagesize() / 2**20


def shipped_noise_with_depth() -> bool:
    """The shipped experiment's ``update.change.noise_with_depth`` (``config/config.yaml``,
    the setting's one home; the library's default is off), for benchmarks that time the
    update as the workflow runs it."""
    import yaml  # here: the torch-only benchmarks never call this

    cfg = yaml.safe_load(SHIPPED_CONFIG.read_text())
    return bool(cfg.get("update", {}).get("change", {}).get("noise_with_depth", False))
