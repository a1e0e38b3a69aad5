"""No URL query, user information or token reaches a log line, the terminal or a file: a download and a
hosted prediction whose URLs carry canary tokens, run through the command line (in this process with every
record of the root logger captured at DEBUG, and in a child process with its own stderr), at the default
level and with -v. Stand-in servers on 127.0.0.1 (tests/fixtures/dataset_server.py, replicate_server.py)."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("httpx")
pytest.importorskip("av")

from fixtures import published_set as ps  # noqa: E402
from fixtures.dataset_server import StandInDatasetServer, split, write_description  # noqa: E402
from fixtures.replicate_server import TOKEN, make_split  # noqa: E402
from fixtures.replicate_server import server, video  # noqa: E402,F401 (pytest fixtures)
from test_hosted import write_config  # noqa: E402

from rigidbench.cli import main  # noqa: E402
from rigidbench.logsafe import public_url, scrub_record, scrub_text  # noqa: E402

QUERY_CANARY = "QueryCanary7f3e91"
USER_CANARY = "UserCanary52ab"
PASSWORD_CANARY = "PasswordCanary0c4d"
CANARIES = (QUERY_CANARY, USER_CANARY, PASSWORD_CANARY, TOKEN)
PART_BYTES = 40_000


def leaks(text: str) -> list[str]:
    return [c for c in CANARIES if c in text]


def files_with_canaries(*roots: Path) -> list[Path]:
    return [p for root in roots for p in root.rglob("*")
            if p.is_file() and any(c.encode() in p.read_bytes() for c in CANARIES)]


def captured_records(caplog) -> str:
    """Every captured record as a handler would render it: message, exception text, stack."""
    formatter = logging.Formatter("%(levelname)s %(name)s: %(message)s")
    return "\n".join(formatter.format(r) for r in caplog.records)


@pytest.fixture
def dataset(tmp_path, monkeypatch):
    """A one-sample published set served in parts whose URLs carry canaries in the user information and query;
    its description is DIR/datasets/<id>.yaml, as `rigidbench --config DIR download` reads it. No proxy
    variables (here and in child processes): the requests go to 127.0.0.1 only."""
    for var in [k for k in os.environ if k.lower() in ("http_proxy", "https_proxy", "all_proxy")]:
        monkeypatch.delenv(var)
    root = ps.write_set(tmp_path / "authors" / "set", ps.DEFAULT_SAMPLES[:1])
    archive = tmp_path / "authors" / "canary-eval-v0.1.tar.gz"
    md5 = ps.make_archive(root, archive)
    data = archive.read_bytes()
    parts = split(data, PART_BYTES, archive.name)
    with StandInDatasetServer(parts) as srv:
        url = (f"http://{USER_CANARY}:{PASSWORD_CANARY}@127.0.0.1:{srv.port}/files/{{part}}/content"
               f"?token={QUERY_CANARY}&download=1")
        config = tmp_path / "config"
        write_description(config, "canary-eval-v0.1", name="canary-eval", version="0.1", archive=archive.name,
                          data=data, md5=md5, part_bytes=PART_BYTES, url=url)
        srv.fail[next(iter(parts))] = [500]  # a retry: its warning names the part's URL
        yield srv, config


@pytest.mark.parametrize("verbose", [False, True])
def test_a_download_logs_no_url_secret(dataset, tmp_path, caplog, capsys, monkeypatch, verbose):
    srv, config = dataset
    monkeypatch.chdir(tmp_path)
    caplog.set_level(logging.DEBUG)  # the root logger, every record of every logger that reaches it
    argv = [*(["-v"] if verbose else []), "--config", str(config), "download", "--dataset", "canary-eval-v0.1",
            "--data", "data"]
    assert main(argv) == 0
    assert srv.requests() >= 2 and (tmp_path / "data" / "eval" / "00000" / "metadata.json").is_file()
    logged = captured_records(caplog)
    # the URLs were logged (scrubbed) where they would have leaked: httpx's request lines with -v, the retry
    assert "retrying" in logged and f"127.0.0.1:{srv.port}/files/" in logged
    assert ("HTTP Request: GET" in logged) == verbose
    out = capsys.readouterr()
    assert not leaks(logged + out.out + out.err)
    assert not files_with_canaries(tmp_path / "data", tmp_path / "authors")


def test_a_hosted_prediction_logs_no_url_secret(server, tmp_path, caplog, capsys):
    server.output_query = f"?token={QUERY_CANARY}&X-Amz-Signature={QUERY_CANARY}"  # as a signed delivery URL
    split_dir = make_split(tmp_path / "data" / "eval", 2)
    config = write_config(tmp_path)
    caplog.set_level(logging.DEBUG)
    for verbose in (False, True):
        out_dir = tmp_path / f"out-{verbose}"
        argv = [*(["-v"] if verbose else []), "--config", str(config), "predict", "veo-3.1", "--data",
                str(split_dir), "--out", str(out_dir), "--concurrency", "1"]
        assert main(argv) == 0
        assert sorted(p.name for p in out_dir.glob("*.mp4")) == ["00000.mp4", "00001.mp4"]
    logged = captured_records(caplog)
    assert "HTTP Request: GET" in logged and "/output/" in logged  # the delivery URL was logged, scrubbed
    out = capsys.readouterr()
    assert not leaks(logged + out.out + out.err)
    assert not files_with_canaries(tmp_path)


def test_the_terminal_shows_no_url_secret(dataset, server, tmp_path):
    """The command's own stderr handler (not the test's capture) in a fresh process: a download at the default
    level and with -v, a hosted prediction with -v (the most it logs)."""
    srv, config = dataset
    server.output_query = f"?token={QUERY_CANARY}"
    models = write_config(tmp_path)
    split_dir = make_split(tmp_path / "split" / "eval", 1)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}  # the stand-in Replicate's token and URL included
    for verbose in (False, True):
        flag = ["-v"] if verbose else []
        data, out = tmp_path / f"data-{verbose}", tmp_path / f"predictions-{verbose}"
        commands = [[*flag, "--config", str(config), "download", "--dataset", "canary-eval", "--data", str(data)]]
        if verbose:
            commands.append([*flag, "--config", str(models), "predict", "veo-3.1", "--data", str(split_dir), "--out",
                             str(out)])
        for argv in commands:
            proc = subprocess.run([sys.executable, "-m", "rigidbench", *argv], capture_output=True, text=True,
                                  timeout=120, env=env)
            assert proc.returncode == 0, proc.stderr[-2000:]
            assert ("HTTP Request: GET" in proc.stderr) == verbose  # quiet by default, scrubbed with -v
            assert not leaks(proc.stdout + proc.stderr), (proc.stdout + proc.stderr)[-2000:]
        assert not files_with_canaries(data, out)


def test_scrubbing_removes_query_user_information_and_remembered_secrets():
    url = f"https://{USER_CANARY}:{PASSWORD_CANARY}@host.example:8443/a/b.mp4?sig={QUERY_CANARY}#frag"
    assert public_url(url) == "https://host.example:8443/a/b.mp4"
    assert scrub_text(f"GET {url} 200", secrets=("b.mp4",)) == "GET https://host.example:8443/a/[REDACTED] 200"
    record = logging.LogRecord("httpx", logging.INFO, __file__, 1, 'HTTP Request: %s %s "%s"',
                               ("GET", url, "HTTP/1.1 200 OK"), None)
    try:
        raise RuntimeError(f"failed on {url}")
    except RuntimeError:
        record.exc_info = sys.exc_info()
    scrub_record(record)
    text = logging.Formatter().format(record)
    assert 'HTTP Request: GET https://host.example:8443/a/b.mp4 "HTTP/1.1 200 OK"' in text
    assert "RuntimeError: failed on https://host.example:8443/a/b.mp4" in text and not leaks(text)


LIBRARY_DOWNLOAD = """
import logging, sys
logging.basicConfig(level=logging.DEBUG, stream=sys.stderr)  # the user's own logging, not ours
from rigidbench.datasets.describe import load_dataset
from rigidbench.datasets.download import download_dataset
desc = load_dataset("canary-eval-v0.1", [sys.argv[1]])
download_dataset(desc, sys.argv[2], progress=False)
"""


def test_a_download_called_from_python_logs_no_url_secret(dataset, tmp_path):
    """Library use: a script with its own DEBUG logging calls download_dataset directly (no command line, no
    hosted predictor imported); httpx's request lines are there, scrubbed."""
    srv, config = dataset
    data = tmp_path / "data-library"
    proc = subprocess.run([sys.executable, "-c", LIBRARY_DOWNLOAD, str(config), str(data)], capture_output=True,
                          text=True, timeout=120, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "HTTP Request: GET" in proc.stderr  # httpx logged at DEBUG as asked...
    assert not leaks(proc.stdout + proc.stderr), (proc.stdout + proc.stderr)[-2000:]  # ...with no secret
    assert not files_with_canaries(data)
