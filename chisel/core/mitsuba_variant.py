"""Choosing and loading the Mitsuba variant (the simulator's renderer, the updater's ray caster).

A broken LLVM makes drjit abort the whole process (``LLVM ERROR: Cannot select ...``) the
first time a real integrator compiles, so a variant is first *probed* in a subprocess
that renders a tiny mesh with the ``direct`` integrator. Order for ``auto``:
``cuda_ad_rgb`` (only where an NVIDIA driver is present), ``llvm_ad_rgb``, then
``scalar_rgb`` with a warning (slow, but it needs no JIT compiler).

drjit 1.5 with the system LLVM 15 aborts; LLVM 19 works. :func:`configure_llvm_env` points
``DRJIT_LIBLLVM_PATH`` at a libLLVM 19 when one is installed, before mitsuba is imported.
"""

from __future__ import annotations

import contextlib
import functools
import glob
import logging
import os
import shutil
import subprocess
import sys
import warnings
from collections.abc import Iterator
from types import ModuleType

from chisel.core.errors import VariantError

log = logging.getLogger(__name__)

VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
"""Variants the project knows, fastest first."""

_LLVM19_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so.1",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19.1",
)

_PROBE_CODE = r"""
import sys
import numpy as np
import mitsuba as mi
mi.set_variant(sys.argv[1])
v = np.array([[-5, -5, 10], [5, -5, 10], [0, 5, 10]], dtype=np.float32)
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "direct"},
    "sensor": {"type": "perspective", "fov": 60,
               "film": {"type": "hdrfilm", "width": 8, "height": 8}},
    "light": {"type": "point", "position": [0, 0, 0], "intensity": {"type": "rgb", "value": 10.0}},
    "tri": {"type": "sphere", "center": [0, 0, 10], "radius": 2.0,
            "bsdf": {"type": "principled", "roughness": 0.3}},
})
img = np.array(mi.render(scene, spp=2))
assert img.shape == (8, 8, 3) and np.isfinite(img).all() and img.max() > 0, img
print("SIM_PROBE_OK")
"""


def configure_llvm_env() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` to a libLLVM 19 if present and not already set.

    Must run before ``import mitsuba``. Returns the path in effect (or None).
    """
    current = os.environ.get("DRJIT_LIBLLVM_PATH")
    if current:
        return current
    candidates = list(_LLVM19_CANDIDATES) + sorted(glob.glob("/usr/lib/*/libLLVM*19*.so*"))
    for path in candidates:
        if os.path.isfile(path):
            os.environ["DRJIT_LIBLLVM_PATH"] = path
            return path
    return None


def _gpu_present() -> bool:
    return shutil.which("nvidia-smi") is not None or os.path.exists("/dev/nvidia0")


@functools.cache
def probe_variant(variant: str, timeout_s: float = 180.0) -> tuple[bool, str]:
    """Render a tiny scene with ``variant`` in a subprocess; (works, diagnostic text)."""
    if variant not in VARIANTS:
        raise VariantError("variant", f"expected one of {list(VARIANTS)}, got {variant!r}")
    env = dict(os.environ)
    configure_llvm_env()
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        env["DRJIT_LIBLLVM_PATH"] = os.environ["DRJIT_LIBLLVM_PATH"]
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE_CODE, variant],
            capture_output=True,
            text=True,
            timeout=timeout_s,
            env=env,
        )
    except subprocess.TimeoutExpired:
        return False, f"probe timed out after {timeout_s:.0f} s"
    ok = proc.returncode == 0 and "SIM_PROBE_OK" in proc.stdout
    detail = (proc.stderr or proc.stdout).strip().splitlines()
    return ok, ("ok" if ok else f"exit {proc.returncode}: " + " | ".join(detail[-3:]))


@functools.cache
def choose_variant(requested: str = "auto") -> str:
    """The Mitsuba variant to use: ``requested`` if it works, else the first that does.

    ``auto`` tries cuda (where a GPU is present), llvm, then scalar with a warning. An
    explicitly requested variant that fails its probe raises :class:`VariantError`.
    The env var ``SIM_MITSUBA_VARIANT`` overrides ``auto``.
    """
    if requested == "auto":
        requested = os.environ.get("SIM_MITSUBA_VARIANT", "auto")
    if requested != "auto":
        ok, detail = probe_variant(requested)
        if not ok:
            raise VariantError(
                "variant", f"Mitsuba variant {requested!r} does not work here: {detail}"
            )
        return requested
    order = ["llvm_ad_rgb"]
    if _gpu_present():
        order.insert(0, "cuda_ad_rgb")
    failures = []
    for v in order:
        ok, detail = probe_variant(v)
        if ok:
            return v
        failures.append(f"{v}: {detail}")
    ok, detail = probe_variant("scalar_rgb")
    if not ok:
        raise VariantError(
            "variant",
            "no Mitsuba variant works: " + "; ".join(failures + [f"scalar_rgb: {detail}"]),
        )
    warnings.warn(
        "Mitsuba JIT variants failed (" + "; ".join(failures) + "); falling back to the slow "
        "scalar_rgb variant",
        RuntimeWarning,
        stacklevel=2,
    )
    return "scalar_rgb"


def load_mitsuba(variant: str = "auto") -> tuple[ModuleType, str]:
    """Import mitsuba with the chosen variant set; returns ``(mi, variant)``."""
    configure_llvm_env()
    chosen = choose_variant(variant)
    import mitsuba as mi  # noqa: PLC0415 - imported only after DRJIT_LIBLLVM_PATH is set

    if mi.variant() != chosen:
        mi.set_variant(chosen)
    return mi, chosen


def jit_mitsuba() -> ModuleType | None:
    """Mitsuba on a JIT variant for vectorised ray queries, or None where there is none.

    A variant already set in this process (by the simulator, possibly on request) is kept:
    switching it would change the types under every live Mitsuba object. Otherwise the
    ``auto`` choice is set. None when that is ``scalar_rgb`` (no vectorised ray queries)
    or no variant works; callers then fall back to another ray caster.
    """
    configure_llvm_env()
    try:
        import mitsuba as mi  # noqa: PLC0415 - imported only after DRJIT_LIBLLVM_PATH is set
    except ImportError:
        return None
    current = mi.variant()
    if current is None:
        try:
            current = choose_variant("auto")
        except VariantError:
            return None
        if current == "scalar_rgb":
            return None
        mi.set_variant(current)
    return mi if current in ("cuda_ad_rgb", "llvm_ad_rgb") else None


@contextlib.contextmanager
def deterministic_build() -> Iterator[None]:
    """Build or rebuild Mitsuba scenes (their ray-tracing acceleration structure) on one
    drjit thread; the thread count is restored afterwards.

    Built on several threads, the structure differs from build to build, and a ray through
    the shared edge of two triangles can hit either: a phantom's frames rendered 1 level
    apart at 1-2 pixels between runs, which a network fine-tuned on them turned into other
    weights (docs/results.md, twenty-seventh session). Built on one thread the same scene
    gives the same bytes in every process; a phantom's scene builds as quickly (0.1-0.4 s
    either way, measured).
    """
    import drjit as dr  # noqa: PLC0415 - only where Mitsuba is in use

    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        yield
    finally:
        dr.set_thread_count(threads)
