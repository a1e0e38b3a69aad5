"""Fault-test helpers: folders on which writing fails, as a user's would.

Root may write into any folder whatever its mode bits, so a read-only folder is, for root, a tmpfs mounted
read-only (where ``mount -t tmpfs`` works here) and, for anyone else, a folder of mode 0555. A full disk is a
small tmpfs (``tmpfs``), where mounting one works; tests that need it elsewhere use a write wrapper.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from pathlib import Path
from typing import Iterator

import pytest


def _mount_tmpfs(where: Path, options: str) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True)
    return done.returncode == 0


def _unmount(where: Path) -> None:
    subprocess.run(["umount", "-l", str(where)], capture_output=True)


@contextlib.contextmanager
def tmpfs(where: Path, size: str) -> Iterator[Path | None]:
    """A tmpfs of ``size`` (e.g. "2m") mounted at ``where`` (created) for the block; None where none can be
    mounted (not root, or no permission)."""
    where.mkdir(parents=True, exist_ok=True)
    if not _mount_tmpfs(where, f"size={size},mode=0755"):
        yield None
        return
    try:
        yield where
    finally:
        _unmount(where)


@pytest.fixture
def small_tmpfs():
    """``tmpfs(where, size)``: a context manager mounting a tmpfs for its block (None where none can be)."""
    return tmpfs


@pytest.fixture(scope="module")
def read_only_dir(tmp_path_factory) -> Iterator[Path]:
    """An existing, empty folder into which nothing can be written (see the module docstring)."""
    where = tmp_path_factory.mktemp("read-only") / "ro"
    where.mkdir()
    if os.geteuid() != 0:
        where.chmod(0o555)
        yield where
        where.chmod(0o755)
        return
    if not _mount_tmpfs(where, "size=64k,ro"):
        pytest.skip("root, and no read-only tmpfs can be mounted here: no folder is read-only for this test")
    try:
        yield where
    finally:
        _unmount(where)
