"""Files written whole or not at all: a failed save leaves what was there as it was."""

import contextlib
import os
import pathlib
from collections.abc import Iterator


def with_default_suffix(path: str | os.PathLike, suffix: str) -> pathlib.Path:
    """``path`` as SB3 writes it: with ``.suffix`` added where it has none (``model`` -> ``model.zip``)."""
    path = pathlib.Path(path)
    return path if path.suffix else pathlib.Path(f"{path}.{suffix}")


@contextlib.contextmanager
def replacing(path: pathlib.Path) -> Iterator[pathlib.Path]:
    """A temporary path beside ``path`` to write to: it replaces ``path`` when the block ends without an error and is
    removed when it raises, so that an existing file is either replaced whole or left as it was. Blocks nested for
    several files replace them all only when the innermost block has written them all."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
