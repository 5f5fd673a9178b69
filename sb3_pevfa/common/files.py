"""Files written whole or not at all: a failed save leaves what was there as it was."""

import contextlib
import os
import pathlib
import shutil
import uuid
from collections.abc import Iterator


def with_default_suffix(path: str | os.PathLike, suffix: str) -> pathlib.Path:
    """The file SB3 writes for ``path``: ``.suffix`` added where it has none (``model`` -> ``model.zip``)."""
    path = pathlib.Path(path)
    return path if path.suffix else pathlib.Path(f"{path}.{suffix}")


@contextlib.contextmanager
def replacing(path: pathlib.Path) -> Iterator[pathlib.Path]:
    """A temporary path beside ``path`` (the file a link points to) to write to: it replaces that file, taking its
    permissions, when the block ends without an error, and is removed when it raises, so that an existing file is
    either replaced whole or left as it was. Nested blocks for several files replace them one after the other, once
    the innermost block has written them all."""
    path = pathlib.Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        yield temporary
        if path.exists():
            shutil.copymode(path, temporary)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
