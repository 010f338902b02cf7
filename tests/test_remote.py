"""`rpod remote add`, end to end: a small DVC project pushed to a real S3 API (moto's server, on 127.0.0.1 only,
stopped at the end) and to a local folder, pulled into a fresh clone, `dvc status` clean and the files
identical; addresses that can't be used are refused with one line and leave .dvc/config as it was."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("dvc_s3", reason="the test extra (dvc-s3) is not installed")
moto_server = pytest.importorskip("moto.server", reason="the test extra (moto[server]) is not installed")

REPO = Path(__file__).resolve().parents[1]
BUCKET = "rpod-remote-test"
FILES = {
    "data/table.csv": b"a,b\n1,2\n",
    "data/images/0.bin": bytes(range(256)) * 8,
    "data/images/1.bin": b"\x00\xff" * 1000,
    "data/images/sub/2.txt": b"nested\n",
}


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, str]:
    """Subprocess environment: this tree first, dummy S3 credentials, no AWS files or instance metadata, a git
    identity."""
    home = tmp_path_factory.mktemp("home")
    return {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_EC2_METADATA_DISABLED": "true",
        "AWS_CONFIG_FILE": str(home / "aws-config"),
        "AWS_SHARED_CREDENTIALS_FILE": str(home / "aws-credentials"),
        "DVC_NO_ANALYTICS": "1",
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@example.org",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@example.org",
    }


@pytest.fixture(scope="module")
def endpoint(env):
    """http://127.0.0.1:PORT of a moto S3 server holding an empty bucket BUCKET; stopped after the module."""
    import boto3

    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        url = f"http://{host}:{port}"
        boto3.client(
            "s3",
            endpoint_url=url,
            region_name="us-east-1",
            aws_access_key_id="testing",
            aws_secret_access_key="testing",
        ).create_bucket(Bucket=BUCKET)
        yield url
    finally:
        server.stop()


@pytest.fixture(scope="module")
def origin(tmp_path_factory, env) -> Path:
    """A git + DVC project with a `dvc add`ed file and a `dvc add`ed folder, committed; no remote yet."""
    root = tmp_path_factory.mktemp("origin")
    _run(["git", "init", "-q"], root, env)
    _dvc(["init", "-q"], root, env)
    for name, data in FILES.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    _dvc(["add", "-q", "data/table.csv", "data/images"], root, env)
    _run(["git", "add", "-A"], root, env)
    _run(["git", "commit", "-qm", "data"], root, env)
    return root


def _run(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    done = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, f"{args}: {done.stdout}{done.stderr}"
    return done


def _dvc(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return _run([sys.executable, "-m", "dvc", *args], cwd, env)


def _rpod_remote(cwd: Path, env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "stages.cli", "remote", "add", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )


def _round_trip(origin: Path, env: dict[str, str], clone: Path) -> None:
    """Commit the remote config, `dvc push` from ORIGIN, `git clone` into CLONE, `dvc pull` there; check it all."""
    _run(["git", "commit", "-qam", "remote"], origin, env)
    _dvc(["push", "-q"], origin, env)
    _run(["git", "clone", "-q", str(origin), str(clone)], clone.parent, env)
    assert not (clone / "data/table.csv").exists()  # git holds only the .dvc files
    _dvc(["pull", "-q"], clone, env)
    for name, data in FILES.items():
        assert (clone / name).read_bytes() == data, name
    status = _dvc(["status", "--json"], clone, env).stdout.strip()
    cloud = _dvc(["status", "--cloud", "--json"], clone, env).stdout.strip()
    assert status in ("{}", "") and cloud in ("{}", ""), (status, cloud)


def test_s3_remote_push_then_pull_in_a_fresh_clone(origin, endpoint, env, tmp_path):
    import boto3

    done = _rpod_remote(origin, env, f"s3://{BUCKET}/cache", "--endpoint", endpoint)
    assert done.returncode == 0, done.stderr
    config = (origin / ".dvc/config").read_text()
    assert "remote = storage" in config and f"url = s3://{BUCKET}/cache" in config
    assert f"endpointurl = {endpoint}" in config and "testing" not in config  # no credentials written
    _round_trip(origin, env, tmp_path / "clone")
    s3 = boto3.client(
        "s3",
        endpoint_url=endpoint,
        region_name="us-east-1",
        aws_access_key_id="testing",
        aws_secret_access_key="testing",
    )
    keys = [o["Key"] for o in s3.list_objects_v2(Bucket=BUCKET).get("Contents", [])]
    assert len(keys) >= len(FILES) and all(k.startswith("cache/") for k in keys)


def test_local_folder_remote_round_trip(origin, env, tmp_path):
    store = tmp_path / "store" / "dvc"  # created by the command
    done = _rpod_remote(origin, env, str(store))
    assert done.returncode == 0, done.stderr
    assert f"remote 'storage' -> {store}" in done.stdout
    assert f"url = {store}" in (origin / ".dvc/config").read_text()
    _round_trip(origin, env, tmp_path / "clone")
    assert any(p.is_file() for p in store.rglob("*"))


def _closed_port() -> int:
    """A loopback port with no server behind it (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def web() -> str:
    """http://127.0.0.1:PORT of a server that is no HTTP remote under /upgrade/ (426, as a proxy may answer), an
    empty one under /empty/ (404) and a private one under /private/ (403); stopped after the module."""
    import http.server
    import threading

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_HEAD(self) -> None:
            codes = {"upgrade": 426, "empty": 404, "private": 403}
            self.send_response(codes.get(self.path.strip("/").split("/")[0], 200))
            self.end_headers()

        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()


def test_an_empty_http_remote_is_accepted(origin, env, web):
    before = (origin / ".dvc/config").read_text()
    try:
        done = _rpod_remote(origin, env, f"{web}/empty/store")
        assert done.returncode == 0 and f"remote 'storage' -> {web}/empty/store" in done.stdout, done.stderr
    finally:
        (origin / ".dvc/config").write_text(before)


@pytest.mark.parametrize(
    "args, message",
    [
        (["s3://rpod-remote-test/x", "--endpoint", "http://127.0.0.1:{closed}"], "cannot reach 127.0.0.1:{closed}"),
        (["http://127.0.0.1:{closed}/store"], "cannot reach 127.0.0.1:{closed}"),
        (
            ["{web}/upgrade/store"],
            "{web}/upgrade/store did not answer as a DVC remote can use (ConnectionError: HTTP 426",
        ),
        (["{web}/private/store"], "access to {web}/private/store denied"),
        (
            ["s3://no-such-bucket/x", "--endpoint", "{endpoint}"],
            "s3 bucket 'no-such-bucket' at {endpoint} does not exist",
        ),
        (["ftp://example.org/store"], "DVC cannot use ftp://example.org/store: Unsupported URL type"),
        (["{blocked}/sub"], "cannot create the folder"),
    ],
)
def test_unusable_addresses_are_refused_with_one_line(origin, endpoint, web, env, tmp_path, args, message):
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    fill = {"closed": _closed_port(), "endpoint": endpoint, "blocked": blocked, "web": web}
    before = (origin / ".dvc/config").read_text()
    done = _rpod_remote(origin, env, *[a.format(**fill) for a in args])
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("error: rpod remote add: "), done.stderr
    assert message.format(**fill) in done.stderr
    assert (origin / ".dvc/config").read_text() == before


def test_a_scheme_without_its_dvc_plugin_is_refused(origin, env):
    import importlib.util

    if importlib.util.find_spec("dvc_gs") is not None:
        pytest.skip("dvc-gs is installed here")
    done = _rpod_remote(origin, env, "gs://bucket/path")
    assert done.returncode == 1 and "requires 'dvc-gs' to be installed" in done.stderr
