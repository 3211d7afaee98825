"""Loading Mitsuba/drjit with a working backend.

drjit's CPU backend (``llvm_*`` variants) needs libLLVM >= 17. A libLLVM-15 found first
aborts the whole process at the first kernel ("Cannot select: fminimum"), so the library
is chosen here, before drjit is imported, and never left to chance.
"""

from __future__ import annotations

import glob
import logging
import os
import re

log = logging.getLogger(__name__)

MIN_LLVM = 17
_SEARCH = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM-*.so*",
    "/usr/lib/*/libLLVM.so.*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)
_variant: str | None = None


def _llvm_major(path: str) -> int | None:
    m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path)) or re.search(
        r"llvm-(\d+)", path
    )
    return int(m.group(1)) if m else None


def find_libllvm(min_major: int = MIN_LLVM) -> str | None:
    """Path of the newest libLLVM with major version >= ``min_major``, or None."""
    best: tuple[int, str] | None = None
    for pattern in _SEARCH:
        for path in glob.glob(pattern):
            major = _llvm_major(path)
            if major is None or major < min_major or not os.path.isfile(path):
                continue
            if best is None or major > best[0]:
                best = (major, path)
    return best[1] if best else None


def ensure_libllvm() -> None:
    """Point ``DRJIT_LIBLLVM_PATH`` at a libLLVM >= 17 unless the user already chose one."""
    current = os.environ.get("DRJIT_LIBLLVM_PATH")
    if current:
        major = _llvm_major(current)
        if major is not None and major < MIN_LLVM:
            raise RuntimeError(
                f"DRJIT_LIBLLVM_PATH={current} is libLLVM {major}; drjit needs >= {MIN_LLVM}. "
                "Unset it, or install Debian's libllvm19 (apt-get install libllvm19)."
            )
        return
    path = find_libllvm()
    if path is None:
        raise RuntimeError(
            f"No libLLVM >= {MIN_LLVM} found for drjit's CPU backend. Install one "
            "(Debian: apt-get install libllvm19) or set DRJIT_LIBLLVM_PATH to it; "
            "scripts/setup.sh does both."
        )
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    log.debug("DRJIT_LIBLLVM_PATH=%s", path)


def default_variant() -> str:
    """``cuda_ad_rgb`` when ``RECON_VARIANT`` says so, else ``llvm_ad_rgb`` (the CPU)."""
    return os.environ.get("RECON_VARIANT", "llvm_ad_rgb")


def load_variant(name: str | None = None):
    """Import mitsuba with variant ``name`` (default :func:`default_variant`) and return it.

    The first call fixes the variant for the process; a later call asking for another
    variant switches it (Mitsuba allows that, but objects of the old variant become unusable).
    """
    global _variant
    name = name or default_variant()
    if name.startswith("llvm"):
        ensure_libllvm()
    import mitsuba as mi

    if _variant != name:
        mi.set_variant(name)
        _variant = name
    return mi


def variant() -> str | None:
    """The variant set by :func:`load_variant`, or None before the first call."""
    return _variant
