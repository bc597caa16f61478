"""How much memory a setting asks for, refused in one line above a share of the machine's.

A setting that sizes an allocation (a voxel block, a cost volume, a rendered image) is
checked before the allocation: a typo such as `fusion.block_resolution=1000` then ends in one
line naming the setting, not in the kernel's OOM killer or a swap storm minutes later.
"""

from __future__ import annotations

import os

from stages.common.errors import BlunfError

SHARE = 0.5  # of the machine's memory one allocation may ask for


def machine_memory() -> int:
    """Bytes of physical memory (cgroup limit not counted)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError):  # not POSIX: assume 8 GB
        return 8 << 30


def check_memory(nbytes: float, what: str) -> None:
    """Refuse `what` (a setting and its value) when it asks for more than SHARE of memory."""
    total = machine_memory()
    if not nbytes <= SHARE * total:
        raise BlunfError(
            f"{what}: asks for ~{nbytes / 2**30:.1f} GB, more than {SHARE:.0%} of this "
            f"machine's {total / 2**30:.1f} GB"
        )
