"""Parquet tables with a CRC checksum on every page, written atomically."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

from pipeline.io.errors import DataError
from pipeline.io.files import open_regular


def write_parquet(df: Any, path: Path | str) -> None:
    """DataFrame -> parquet with a CRC checksum on every page, via a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        df.to_parquet(tmp, index=False, write_page_checksum=True)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_parquet(path: Path | str, what: str = "table") -> Any:
    """A parquet table, its page checksums verified (where written); a clear DataError otherwise."""
    import pandas as pd

    path = Path(path)
    with open_regular(path, "rb", what) as f:
        try:
            return pd.read_parquet(f, page_checksum_verification=True)
        except Exception as e:
            raise DataError(f"{what} {path} is unreadable ({type(e).__name__}: {e})") from None
