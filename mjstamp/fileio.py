"""Writing files so that no reader ever sees half of one."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def write_atomic(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Writes a file via a temporary sibling and os.replace: never half-written.

    Args:
      path: the file to write; its folder must exist.
      write: called with the open binary temporary file.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def probe(test: Callable[[], bool], shown: str | os.PathLike, what: str = "") -> bool:
    """`test()` (say `path.is_file`), with an OSError from the path itself as one line.

    A name too long for the filesystem, or a path running through a file, makes
    `is_file` / `exists` raise instead of answering False.

    Args:
      test: the check, e.g. `path.exists`.
      shown: the path the message names.
      what: what it is, before the path ("skill bank ", "results directory ").

    Raises:
      MjstampError: "{what}'{shown}' cannot be read: {reason}".
    """
    from mjstamp.errors import MjstampError  # noqa: PLC0415 - fileio imports nothing of ours

    try:
        return test()
    except OSError as e:
        raise MjstampError(f"{what}{str(shown)[:200]!r} cannot be read: "
                           f"{e.strerror or e}") from None

