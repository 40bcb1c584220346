"""What the benches that watch a fleet read from ``/proc`` (Linux): a process's descendants, its
command line, CPU seconds, peak and current RSS and open file descriptors, its role in the fleet
from its command line, and a folder's size on disk. Shared by ``sitl`` (:mod:`.speed`) and
``soak`` (:mod:`.soak`)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["descendants", "command", "sample", "memory", "role", "disk_usage"]

_TICK_S = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def descendants(pid: int) -> set[int]:
    """Every live process below ``pid`` (children, their children, ...)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def command(pid: int) -> str | None:
    """A live process's command line, its arguments joined by spaces."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return fh.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return None


def sample(pid: int) -> tuple[str, float, int] | None:
    """(command line, CPU seconds, peak RSS [kB]) of a live process."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        cpu = (int(fields[11]) + int(fields[12])) / _TICK_S  # utime, stime
        cmd = command(pid)
        if cmd is None:
            return None
        hwm = 0
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    hwm = int(line.split()[1])
        return cmd, cpu, hwm
    except (OSError, ValueError, IndexError):
        return None


def memory(pid: int) -> tuple[int, int] | None:
    """(current RSS [kB] (``VmRSS``, not the high-water mark), open file descriptors) of a live
    process, ``None`` for one gone (or not ours to read)."""
    try:
        rss = None
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    rss = int(line.split()[1])
                    break
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (OSError, ValueError, IndexError):
        return None
    return (rss, fds) if rss is not None else None


def role(cmd: str) -> str | None:
    """A fleet process's role from its command line: ``vehicle <i>``, ``companion[ g<G>]``, ``wire``."""
    parts = cmd.split()
    if "link_firmware_sim" in parts:
        return f"vehicle {int(parts[parts.index('--instance') + 1]) + 1}" if "--instance" in parts else "vehicle"
    if "companion" in parts:
        return f"companion g{parts[parts.index('--group') + 1]}" if "--group" in parts else "companion"
    if "sitl.fleet.wire" in parts:
        return "wire"
    return None


def disk_usage(path: str | Path) -> int:
    """Bytes a folder's files take on disk (allocated blocks, like ``du``); files that vanish while
    it is walked are skipped, a missing folder is 0."""
    total, todo = 0, [str(path)]
    while todo:
        try:
            entries = list(os.scandir(todo.pop()))
        except OSError:
            continue
        for e in entries:
            try:
                if e.is_dir(follow_symlinks=False):
                    todo.append(e.path)
                else:
                    total += e.stat(follow_symlinks=False).st_blocks * 512
            except OSError:
                continue
    return total
