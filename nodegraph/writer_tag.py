"""The writer tag of temporary names: which process on which host made a temporary folder.

The cache's temporary entries (`tmp/<key>.<tag>`, `tmp/trash-<key>.<tag>`) and a run's staging
folders (`.nodegraph-staging.<tag>`) end in a tag `host.pid.nonce`, so that a later run can
tell the leftovers of a writer killed on this host (its process is gone) from a live writer's
work. A folder's name is the only record such a writer leaves, so the tag is read back from
names; this module is the one place that writes and reads it.
"""

from __future__ import annotations

import os
import socket
import uuid
from dataclasses import dataclass

__all__ = ["HOST", "WriterTag", "pid_alive"]

HOST = socket.gethostname().replace(".", "-")
"""This host's name as tags write it (dots separate a tag's fields)."""


def pid_alive(pid: int) -> bool:
    """Whether process `pid` exists on this host (one we may not signal counts as existing)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: someone else's process
        return True
    return True


@dataclass(frozen=True)
class WriterTag:
    """A temporary name's owner.

    Attributes:
        host: `HOST` of the writer's machine.
        pid: the writer's process id there.
        nonce: random hex, so that one process's names never collide.
    """

    host: str
    pid: int
    nonce: str

    @classmethod
    def new(cls, nonce_chars: int = 32) -> "WriterTag":
        """A fresh tag of this process."""
        return cls(HOST, os.getpid(), uuid.uuid4().hex[:nonce_chars])

    def __str__(self) -> str:
        return f"{self.host}.{self.pid}.{self.nonce}"

    @classmethod
    def of_name(cls, name: str) -> "WriterTag | None":
        """The tag a file or folder name ends with (after a "." or as the whole name); None
        when it ends in none."""
        parts = name.split(".")
        if len(parts) < 3 or not parts[-2].isdigit():
            return None
        return cls(parts[-3], int(parts[-2]), parts[-1])

    def writer_gone(self) -> bool:
        """True when the writer ran on this host and its process no longer exists (another
        host's writer cannot be checked from here: False)."""
        return self.host == HOST and not pid_alive(self.pid)
