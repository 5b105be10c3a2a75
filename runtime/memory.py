"""What this process may still allocate: one home for the memory checks of the precompute (the factor, the
tiles) and of the runtime (whether a compressed artifact's Green's functions fit in the native core's memory)."""
from __future__ import annotations

import os

from pmask.errors import InputError


def available_memory() -> int | None:
    """Bytes this process can still allocate without swapping (Linux: MemAvailable), None if unknown;
    at most ``PMASK_MAX_MEMORY`` (bytes, or with a K/M/G suffix) where that is set, to keep a precompute
    within a share of a shared machine."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    cap = os.environ.get("PMASK_MAX_MEMORY", "").strip()
    if cap:
        limit = parse_bytes(cap, "PMASK_MAX_MEMORY")
        avail = limit if avail is None else min(avail, limit)
    return avail


def parse_bytes(text, what: str) -> int:
    """Bytes from '4G', '512M', '2.5GiB' or a plain number (K, M, G, T: powers of 1024); ``what`` names the
    setting in the one-line error (``PMASK_MAX_MEMORY``, ``--worker-memory``)."""
    s = str(text).strip().upper().removesuffix("IB").removesuffix("B")
    try:
        unit = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}.get(s[-1:], 1)
        return int(float(s[:-1] if unit > 1 else s) * unit)
    except ValueError:
        raise InputError(f"{what} must be bytes or a number with K, M or G (e.g. 4G), got {text!r}") from None
