"""Writing a file whole or not at all: a temporary file beside it, renamed
over it once written (a shared leaf: it imports no domain)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable, Optional, Union

from .errors import FlowloopError

NEW_FILE_MODE = 0o644


def replace_atomically(path: Union[str, Path], write: Callable[[BinaryIO], None],
                       mode_from: Optional[Path] = None) -> None:
    """Write `path` through write(binary file): whole, or (any error) not at
    all, the file that was there left as it was. Its mode is mode_from's,
    else the old file's, else NEW_FILE_MODE. A folder where no temporary
    file can be made is one FlowloopError; what write() raises (a full disk:
    OSError) is raised as it is."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp",
                                   dir=folder)
    except OSError as e:
        raise FlowloopError(f"{path}: cannot write: {e.strerror}") from None
    try:
        with os.fdopen(fd, "wb") as out:
            write(out)
        if mode_from is None and path.exists():
            mode_from = path
        if mode_from is not None:
            shutil.copymode(mode_from, tmp)
        else:
            os.chmod(tmp, NEW_FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_text_atomically(path: Union[str, Path], text: str) -> None:
    """replace_atomically with UTF-8 text, written as it is (no newline
    translation)."""
    data = text.encode("utf-8")
    replace_atomically(path, lambda out: out.write(data))
