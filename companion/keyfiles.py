"""Files that hold secrets (MAVLink signing keys, Zenoh passwords): written mode 600, atomically;
refused when the group or others may read them, as ssh refuses a private key (pure, no logging)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["read_private_text", "write_private_text"]


def read_private_text(path: str | Path, what: str) -> str:
    """The ASCII text of the secret file ``path`` (``what`` it holds, for the messages);
    ``ValueError`` naming the file and the reason (missing, unreadable, readable by others)."""
    path = Path(path)
    try:
        st = path.stat()
        if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise ValueError(f"{path}: readable by others (mode {stat.S_IMODE(st.st_mode):o}); chmod 600 {path}")
        return path.read_text(encoding="ascii")
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: a {what} file is ASCII text") from None


def write_private_text(path: str | Path, text: str, overwrite: bool = False) -> Path:
    """Write ``text`` to ``path`` with mode 600, atomically; refuses to overwrite unless asked."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise ValueError(f"{path} exists (refusing to overwrite a secret)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as fh:
        fh.write(text.strip() + "\n")
    os.chmod(tmp, 0o600)
    tmp.replace(path)
    return path
