"""`rpod remote add PATH_OR_URL`: the project's default DVC remote (what `dvc push` and `dvc pull` use), in one command.

Writes `[remote "NAME"]` (url, and `endpointurl` for an S3-compatible server) and `core.remote = NAME` to
.dvc/config, as `dvc remote add -d` and `dvc remote modify` would, after checking that DVC can use the
address and that it answers: a local folder is created (its parent must exist or be creatable) and must
be writable; `s3://BUCKET/PATH` needs `dvc-s3` installed and the bucket to exist, checked with one
bounded request to its endpoint (`--endpoint URL` for MinIO, Ceph or any S3-compatible server; AWS
otherwise); an http(s) URL must answer a HEAD request with success, a redirect or 404 (an empty remote);
other schemes need their DVC plugin and one bounded answer. Not a DVC stage; reads no params.
Credentials are never written: S3 takes them from AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY, ~/.aws, or
`dvc remote modify --local NAME access_key_id ...` (.dvc/config.local, not in git).
"""

from __future__ import annotations

import os
import socket
import threading
from pathlib import Path
from typing import Any, Callable
from urllib.parse import urlparse

import typer

from stages.errors import StageError

app = typer.Typer(help="Set up the DVC remote that `dvc push` and `dvc pull` use.", no_args_is_help=True)

AWS_ENDPOINT = "https://s3.amazonaws.com"  # where an s3:// URL goes without --endpoint
DEFAULT_PORTS = {"http": 80, "https": 443}
TIMED = ("s3", "http", "https")  # schemes whose DVC config takes connect_timeout / read_timeout (s)


@app.command("add")
def add(
    target: str = typer.Argument(
        ...,
        metavar="PATH_OR_URL",
        help="A local folder (created if missing) or a URL DVC can use, e.g. s3://BUCKET/PATH.",
    ),
    name: str = typer.Option("storage", "--name", help="Remote name in .dvc/config."),
    endpoint: str = typer.Option(
        None,
        "--endpoint",
        help="S3-compatible endpoint URL (MinIO, Ceph, ...), e.g. http://127.0.0.1:9000; AWS S3 when not given.",
    ),
    timeout: float = typer.Option(10.0, "--timeout", min=0.1, help="Seconds to wait for the remote's answer."),
) -> None:
    """Make PATH_OR_URL the default DVC remote (.dvc/config), after checking it can be reached."""
    from dvc.config import Config
    from dvc.exceptions import NotDvcRepoError
    from dvc.repo import Repo

    try:
        root = Path(Repo.find_root())
    except NotDvcRepoError:
        raise StageError(
            "rpod remote add: not inside a DVC project (run it in the project folder; `dvc init` makes one)"
        ) from None
    section = remote_section(target, endpoint, timeout)
    config = Config(dvc_dir=str(root / ".dvc"))
    with config.edit("repo") as conf:
        replaced = name in conf["remote"]
        conf["remote"][name] = section
        conf["core"]["remote"] = name
    typer.echo(
        f".dvc/config: remote {name!r} -> {section['url']}"
        + (f" (endpoint {endpoint})" if endpoint else "")
        + (", replacing the old one" if replaced else "")
        + "; it is the default: `dvc push`, `dvc pull`"
    )


def remote_section(target: str, endpoint: str | None, timeout: float) -> dict[str, str]:
    """The .dvc/config remote section for TARGET, once it is known to be usable (StageError otherwise)."""
    parsed = urlparse(target)
    if not parsed.scheme or len(parsed.scheme) == 1 or parsed.scheme == "file":  # a path (C:/... on Windows)
        if endpoint:
            raise StageError("rpod remote add: --endpoint is for an s3:// URL, not a local folder")
        return {"url": str(local_folder(Path(parsed.path if parsed.scheme == "file" else target)))}
    if endpoint and parsed.scheme != "s3":
        raise StageError(f"rpod remote add: --endpoint is for an s3:// URL, not {parsed.scheme}://")
    section = {"url": target, **({"endpointurl": endpoint} if endpoint else {})}
    fs, path = _filesystem(section, timeout)
    if parsed.scheme == "s3":
        address = endpoint or AWS_ENDPOINT
        _connect(address, timeout)
        _answer(lambda: fs.fs.info(parsed.netloc), f"s3 bucket {parsed.netloc!r} at {address}", timeout)
    else:
        _connect(target, timeout)
        probe = (lambda: _http_head(target, timeout)) if parsed.scheme in DEFAULT_PORTS else (lambda: fs.exists(path))
        _answer(probe, target, timeout)
    return section


def _http_head(url: str, timeout: float) -> None:
    """One HEAD request to URL: fine when it succeeds, redirects or says 404 (nothing pushed yet); 401 and 403
    are a PermissionError, any other error status (a server that is no HTTP remote) a ConnectionError."""
    import urllib.error
    import urllib.request

    try:
        urllib.request.urlopen(urllib.request.Request(url, method="HEAD"), timeout=timeout).close()
    except urllib.error.HTTPError as e:
        if e.code in (401, 403):
            raise PermissionError(url) from None
        if e.code != 404:
            raise ConnectionError(f"HTTP {e.code} {e.reason}") from None


def local_folder(path: Path) -> Path:
    """PATH as an absolute folder, created if missing and checked writable (so every clone on this machine finds it)."""
    folder = path.expanduser().resolve()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise StageError(f"rpod remote add: cannot create the folder {folder} ({e.strerror or e})") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise StageError(f"rpod remote add: the folder {folder} is not writable")
    return folder


def _filesystem(section: dict[str, str], timeout: float) -> tuple[Any, str]:
    """(DVC filesystem, path in it) for a remote section, with connect/read timeouts of TIMEOUT seconds; a
    scheme DVC does not know, or whose plugin is not installed here, is a StageError."""
    from dvc.config import ConfigError
    from dvc.fs import get_cloud_fs

    seconds = int(max(1, timeout))
    timed = {"connect_timeout": seconds, "read_timeout": seconds} if urlparse(section["url"]).scheme in TIMED else {}
    try:
        cls, conf, path = get_cloud_fs(None, **section, **timed)
        return cls(**conf), path
    except ImportError as e:  # "s3 is supported, but requires 'dvc-s3' to be installed"
        raise StageError(
            f"rpod remote add: DVC cannot use {section['url']} here: {e} (pip install it into the "
            f"project's environment)"
        ) from None
    except ConfigError as e:
        reason = str(e).removeprefix("config file error: ")
        raise StageError(f"rpod remote add: DVC cannot use {section['url']}: {reason}") from None


def _connect(url: str, timeout: float) -> None:
    """Open (and close) one TCP connection to URL's host and port within TIMEOUT seconds, or StageError."""
    parsed = urlparse(url)
    port = parsed.port or DEFAULT_PORTS.get(parsed.scheme)
    if not parsed.hostname or port is None:
        return  # no host to dial (the filesystem's own answer decides)
    try:
        socket.create_connection((parsed.hostname, port), timeout=timeout).close()
    except OSError as e:
        raise StageError(
            f"rpod remote add: cannot reach {parsed.hostname}:{port} for {url} "
            f"({e.strerror or type(e).__name__}); check the URL, the endpoint and the network"
        ) from None


def _answer(probe: Callable[[], Any], what: str, timeout: float) -> None:
    """Run PROBE (one request to the remote) and turn a failure, or no answer within TIMEOUT s, into a StageError."""
    outcome: dict[str, BaseException | None] = {}

    def run() -> None:
        try:
            probe()
            outcome["error"] = None
        except BaseException as e:  # reported below, in the caller's thread
            outcome["error"] = e

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(timeout)
    if "error" not in outcome:
        raise StageError(f"rpod remote add: no answer from {what} within {timeout:g} s")
    error = outcome["error"]
    if error is None:
        return
    if isinstance(error, FileNotFoundError):
        raise StageError(f"rpod remote add: {what} does not exist; create it first")
    if isinstance(error, PermissionError):
        raise StageError(f"rpod remote add: access to {what} denied; check the credentials")
    if type(error).__name__ == "NoCredentialsError":
        raise StageError(
            f"rpod remote add: no credentials for {what}: set AWS_ACCESS_KEY_ID and "
            f"AWS_SECRET_ACCESS_KEY (or `dvc remote modify --local NAME access_key_id ...`)"
        )
    message = " ".join(str(error).split())
    raise StageError(
        f"rpod remote add: {what} did not answer as a DVC remote can use ({type(error).__name__}: {message})"
    )
