"""Reading input files without ever blocking: `open_regular` opens a path only once it is known to be a regular
file (opened with O_NONBLOCK, so a FIFO without a writer answers at once, then checked with fstat); a FIFO,
device, socket or folder given as an input is one DataError naming it. `check_regular` is the same check for
the libraries that open a path themselves (OpenCV, Pillow, zarr); `read_yaml` reads a YAML mapping through it,
refusing a key given twice."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import IO, Any

from pipeline.io.errors import DataError, not_found

_KINDS = {
    stat.S_ISFIFO: "a FIFO",
    stat.S_ISDIR: "a folder",
    stat.S_ISCHR: "a character device",
    stat.S_ISBLK: "a block device",
    stat.S_ISSOCK: "a socket",
}


def open_regular(path: Path | str, mode: str = "rb", what: str = "", **kwargs: Any) -> IO[Any]:
    """`path` opened for reading (`mode` "rb" or "r", `kwargs` as `open`'s: encoding, newline) when it is a
    regular file (a symbolic link to one is followed); else a DataError "[what ]PATH is not a regular file
    (a FIFO)" or, when it is missing, the `not_found` line. Never blocks on a FIFO."""
    if mode not in ("r", "rb"):
        raise ValueError(f"open_regular reads only, got mode {mode!r}")
    path = Path(path)
    name = f"{what + ' ' if what else ''}{path}"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise not_found(path, what) from None
    except OSError as e:
        raise DataError(f"{name} cannot be read ({e.strerror})") from None
    try:
        bits = os.fstat(fd).st_mode
        if not stat.S_ISREG(bits):
            kind = next((k for test, k in _KINDS.items() if test(bits)), "a special file")
            raise DataError(f"{name} is not a regular file ({kind})")
        os.set_blocking(fd, True)
        return os.fdopen(fd, mode, **kwargs)
    except BaseException:
        os.close(fd)
        raise


def check_regular(path: Path | str, what: str = "") -> Path:
    """`path` once `open_regular` accepts it (for a reader that opens the path itself), else its DataError."""
    open_regular(path, "rb", what).close()
    return Path(path)


def read_bytes(path: Path | str, what: str = "") -> bytes:
    """The bytes of the regular file `path` (`open_regular`)."""
    with open_regular(path, "rb", what) as f:
        return f.read()


def read_yaml(path: Path | str, what: str = "") -> Any:
    """A YAML document (yaml.safe_load) of the regular file `path`; a DataError naming the file when it is not
    valid YAML or a mapping gives one key twice (yaml itself keeps the last silently)."""
    import yaml

    class _Unique(yaml.SafeLoader):
        pass

    def mapping(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=True)
            if key in seen:
                raise DataError(f"{path}: key {key!r} is given twice (line {key_node.start_mark.line + 1}); keep one")
            seen.add(key)
        return loader.construct_mapping(node, deep=True)

    _Unique.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    with open_regular(path, "r", what, encoding="utf-8") as f:
        text = f.read()
    try:
        return yaml.load(text, Loader=_Unique)
    except yaml.YAMLError as e:
        raise DataError(f"{path} is not valid YAML: {e}") from None
