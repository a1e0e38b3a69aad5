"""Hosted models under fault injection (issue 26, items 5-10): the stand-in Replicate server on 127.0.0.1
kills or hangs the exchange at each point (a creation in flight, after its answer, mid-download, a server
that trickles), and runs are stopped by SIGKILL, SIGTERM and SIGINT with several predictions in flight.
Each case checks that nothing is lost (every finished example has its video and a record with its
prediction id), nothing is paid twice (the server counts the predictions it created: one per example
over the interrupted run and the rerun) and the message is clear; and that the token reaches no file
and no log line, even when the server echoes it in a URL or an error."""

from __future__ import annotations

import json
import os
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

pytest.importorskip("httpx")
pytest.importorskip("av")
pytest.importorskip("PIL")

from rigidbench.driver import RunOptions, ledger_path, read_ledger  # noqa: E402
from rigidbench.cli import main  # noqa: E402
from rigidbench.config import PACKAGE_CONFIG_DIR  # noqa: E402
from rigidbench.context import RunContext  # noqa: E402
from rigidbench.folders import GENERATION_FILE  # noqa: E402
from rigidbench.predictors import PredictContext  # noqa: E402
from rigidbench.predictors.replicate import ReplicateClient  # noqa: E402
from rigidbench.stages.predict import predict  # noqa: E402
from rigidbench.video import probe_video  # noqa: E402

from fixtures.replicate_server import TOKEN, make_split  # noqa: E402
from fixtures.replicate_server import server, video  # noqa: E402,F401 (pytest fixtures)

MODEL = "veo-3.1"
FAST_CLIENT = {"request_timeout_s": 5, "poll_interval_s": 0.01, "poll_max_interval_s": 0.02, "max_retries": 3,
               "backoff_base_s": 0.01, "backoff_max_s": 0.05, "example_timeout_s": 20, "max_output_bytes": 200_000}
CLI = "import sys; from rigidbench.cli import main; sys.exit(main(sys.argv[1:]))"
# the process dies (SIGKILL) right after Replicate answered the creation, before the id is saved
KILL_AFTER_ANSWER = """
import os, signal, sys
from rigidbench.predictors import replicate
real = replicate.ReplicateClient.create
def create(self, *args, **kwargs):
    real(self, *args, **kwargs)
    os.kill(os.getpid(), signal.SIGKILL)
replicate.ReplicateClient.create = create
from rigidbench.cli import main
sys.exit(main(sys.argv[1:]))
"""


def write_config(tmp_path, **client) -> Path:
    data = yaml.safe_load((PACKAGE_CONFIG_DIR / "models.yaml").read_text())
    data["client"].update({**FAST_CLIENT, **client})
    d = tmp_path / f"config{len(list(tmp_path.glob('config*')))}"
    d.mkdir()
    (d / "models.yaml").write_text(yaml.safe_dump(data))
    return d


def run(split, out, config, **options):
    options.setdefault("concurrency", 2)
    ctx = PredictContext(RunContext(config_dirs=(config,)), seed=7, options=options)
    return predict(MODEL, split, out, ctx, run=RunOptions(progress=False))


def spawn(server, split, out, config, concurrency=1, code=CLI, verbose=False, extra=()):
    """``rigidbench predict`` in a child process (its own session, so signals reach only it)."""
    env = {**os.environ, "REPLICATE_API_TOKEN": TOKEN, "REPLICATE_BASE_URL": server.url, "PYTHONUNBUFFERED": "1"}
    args = [*(["-v"] if verbose else []), "--config", str(config), "predict", MODEL, "--data", str(split), "--out",
            str(out), "--concurrency", str(concurrency), *extra]
    return subprocess.Popen([sys.executable, "-c", code, *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def wait_for(condition, timeout=20.0, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def finish(proc, timeout=20.0) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def state(out, sample_id) -> dict:
    return json.loads((out / ".hosted" / f"{sample_id}.json").read_text())


def examples(out) -> dict:
    return json.loads((out / GENERATION_FILE).read_text())["examples"]


def assert_complete(out, server, ids):
    """Every id has its video and a succeeded record whose prediction id the server made; each example was
    paid for exactly once."""
    records = examples(out)
    for sample_id in ids:
        assert probe_video(out / f"{sample_id}.mp4").n_frames == 12
        entry = records[sample_id]
        assert entry["status"] == "succeeded" and entry["prediction_id"] in server.created, (sample_id, entry)
        number = int(sample_id)
        assert server.paid(f"number {number} ") == [entry["prediction_id"]], f"{sample_id} paid twice"
    assert len(server.created) == len(ids)


# -- a kill in the creation window --------------------------------------------------------------------


def test_a_kill_while_the_creation_is_in_flight_is_adopted_not_paid_again(server, tmp_path):
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    server.hold_answers["number 0 "] = 30  # Replicate made it and holds the answer (Prefer: wait)
    proc = spawn(server, split, out, config)
    wait_for(server.creation_recorded.is_set, what="the creation")
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)
    stored = state(out, "00000")
    assert "prediction_id" not in stored and stored["intent"]["model"] == "google/veo-3.1"  # only the intent
    (paid,) = server.created
    server.hold_answers.clear()
    for i in range(3):  # later predictions of the account, so the listing is paged to reach it
        server.predictions[f"other{i}"] = {"id": f"other{i}", "model": "google/veo-3.1", "input": {"prompt": "x"},
                                           "status": "succeeded", "created_at": server.now()}
        server.created.append(f"other{i}")
    server.page_size = 2
    summary = run(split, out, config, concurrency=1)
    assert summary.succeeded == ["00000", "00001"] and not summary.failed
    assert server.paid("number 0 ") == [paid] and len(server.paid("number 1 ")) == 1
    entry = examples(out)["00000"]
    assert entry["prediction_id"] == paid and entry["adopted"] is True
    assert len(server.requests_to("/v1/predictions", "GET")) >= 2  # the listing followed "next"


def test_a_kill_after_the_answer_before_the_id_is_saved_is_adopted(server, tmp_path):
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    proc = spawn(server, split, out, config, code=KILL_AFTER_ANSWER)
    code, _, _ = finish(proc)
    assert code == -signal.SIGKILL and len(server.created) == 1
    assert "prediction_id" not in state(out, "00000")
    summary = run(split, out, config)
    assert summary.succeeded == ["00000", "00001"] and not summary.failed
    assert_complete(out, server, ["00000", "00001"])
    assert examples(out)["00000"]["adopted"] is True


def test_an_intent_whose_request_never_left_creates_one_and_an_older_same_input_is_not_adopted(
        server, tmp_path, monkeypatch):
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 1), tmp_path / "out"
    server.clock_offset_s = -3600  # an earlier prediction of the very same input, an hour before
    assert not run(split, out, config).failed
    (old,) = server.created
    for path in [out / "00000.mp4", out / ".hosted" / "00000.json", ledger_path(out, "predict", "00000")]:
        path.unlink()
    server.clock_offset_s = 0

    def killed(self, *args, **kwargs):  # the process dies after the intent, before the request is sent
        raise KeyboardInterrupt

    monkeypatch.setattr(ReplicateClient, "create", killed)
    with pytest.raises(KeyboardInterrupt):
        run(split, out, config, concurrency=1)
    monkeypatch.undo()
    monkeypatch.setenv("REPLICATE_API_TOKEN", TOKEN)
    monkeypatch.setenv("REPLICATE_BASE_URL", server.url)
    assert "intent" in state(out, "00000") and len(server.created) == 1
    assert not run(split, out, config).failed
    new = examples(out)["00000"]["prediction_id"]
    assert new != old and server.created == [old, new]  # nothing to adopt: one new prediction
    assert server.requests_to("/v1/predictions", "GET")  # the account was checked first


# -- kills and hangs after creation --------------------------------------------------------------------


def test_a_kill_mid_download_resumes_by_id_and_cleans_the_partial_download(server, tmp_path):
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 1), tmp_path / "out"
    server.hang_downloads = True
    proc = spawn(server, split, out, config)
    wait_for(server.download_started.is_set, what="the download")
    wait_for(lambda: list((out / ".hosted").glob(".00000.*.part.mp4")), what="the partial download")
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)
    server.hang_downloads = False
    (out / ".hosted" / ".00000.json.stale.tmp").write_text("{")  # a state write the kill cut short
    (out / ".00000.partial.mp4").write_bytes(b"x")  # and a video that was being moved into place
    summary = run(split, out, config)
    assert summary.succeeded == ["00000"] and not summary.failed
    assert_complete(out, server, ["00000"])
    assert examples(out)["00000"]["resumed"] is True
    leftovers = [p.name for p in [*out.iterdir(), *(out / ".hosted").iterdir()] if p.name.startswith(".0")]
    assert leftovers == []
    modes = {stat.S_IMODE(p.stat().st_mode) for p in [out / "00000.mp4", out / GENERATION_FILE,
                                                       ledger_path(out, "predict", "00000")]}
    assert len(modes) == 1  # the video as the JSON beside it


@pytest.mark.timeout(60)
@pytest.mark.parametrize("where", ["creation", "poll", "download"])
def test_a_trickling_server_cannot_hold_a_worker_past_the_deadline(server, tmp_path, where):
    # a byte every 0.15 s is well inside the 0.4 s read timeout: only a limit on the whole exchange stops it
    config = write_config(tmp_path, request_timeout_s=0.4, wait_s=1, max_retries=1, example_timeout_s=4)
    split, out = make_split(tmp_path / "eval", 1), tmp_path / "out"
    server.wait_finishes = where != "poll"
    server.trickle[{"creation": "/v1/models/", "poll": "/v1/predictions/", "download": "/output/"}[where]] = 0.15
    started = time.monotonic()
    summary = run(split, out, config)
    elapsed = time.monotonic() - started
    assert elapsed < 6, f"the worker was held {elapsed:.1f} s"
    message = summary.failed["00000"]
    assert message.startswith("example 00000:") and "rerun" in message, message
    if where == "creation":
        assert "no complete answer within" in message and "adopts it instead of paying again" in message
    else:
        assert "resumes it without paying again" in message
    if where == "download":
        assert "minimum of 16,384 bytes/s" in message
    server.trickle.clear()
    assert not run(split, out, write_config(tmp_path)).failed
    assert_complete(out, server, ["00000"])


# -- SIGTERM and Ctrl-C with several in flight -----------------------------------------------------------


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_records_what_was_paid_for_and_creates_nothing_more(server, tmp_path, signum):
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 5), tmp_path / "out"
    ids = [f"{i:05d}" for i in range(5)]
    server.hold_answers["apple"] = 1.0  # every creation is held a second: three are in flight at the signal
    polling = signum == signal.SIGINT
    server.wait_finishes = not polling  # SIGINT: the three are still running, the client polls them
    server.never_finish = polling
    proc = spawn(server, split, out, config, concurrency=3)
    wait_for(lambda: len(server.created) == 3, what="three creations")
    os.killpg(proc.pid, signum)
    code, _, err = finish(proc)
    assert code == 130 and "Traceback" not in err, err
    assert "no new predictions are created" in err and "rerun the same command to resume" in err
    assert len(server.created) == 3  # nothing was created after the signal
    paid = {}
    for sample_id in ids:
        path = out / ".hosted" / f"{sample_id}.json"
        if path.exists():
            paid[sample_id] = state(out, sample_id)["prediction_id"]
    assert sorted(paid.values()) == sorted(server.created)  # every paid id is on disk
    records = examples(out)
    for sample_id, pid in paid.items():
        entry = records[sample_id]
        if polling:  # stopped while running: kept, to be resumed
            assert entry["status"] == "interrupted" and pid in entry["error"] and not (out / f"{sample_id}.mp4").exists()
        else:  # finished: its output was already paid for, so it was downloaded and recorded
            assert entry["status"] == "succeeded" and entry["prediction_id"] == pid
            assert (out / f"{sample_id}.mp4").is_file()
    assert not set(records) - set(paid)  # examples never started have no record
    server.never_finish = False
    summary = run(split, out, config, concurrency=3)
    assert sorted(summary.succeeded) == ids and not summary.failed
    assert_complete(out, server, ids)
    for sample_id, pid in paid.items():
        assert examples(out)[sample_id]["prediction_id"] == pid


@pytest.mark.timeout(60)
def test_sigterm_while_the_creation_is_held_forever_stops_within_seconds_and_the_rerun_adopts(server, tmp_path):
    # a creation's read timeout: 5 s + Prefer: wait's 60 s; requests in flight get 2 s after a signal (default 3)
    config = write_config(tmp_path, stop_grace_s=2)
    split, out = make_split(tmp_path / "eval", 1), tmp_path / "out"
    server.hold_answers["apple"] = 3600  # Replicate made the prediction and never answers
    proc = spawn(server, split, out, config)
    wait_for(server.creation_recorded.is_set, what="the creation")
    signalled = time.monotonic()
    os.killpg(proc.pid, signal.SIGTERM)
    code, _, err = finish(proc, timeout=40)
    elapsed = time.monotonic() - signalled
    assert 2 <= elapsed < 5, f"the run took {elapsed:.1f} s to stop"  # the grace, then at once
    assert code == 130 and "Traceback" not in err, err
    stored = state(out, "00000")
    assert "prediction_id" not in stored and stored["intent"]["model"] == "google/veo-3.1"  # the intent is kept
    entry = examples(out)["00000"]
    assert entry["status"] == "interrupted" and "adopts it instead of paying again" in entry["error"], entry
    assert "client.stop_grace_s" in entry["error"]
    (paid,) = server.created
    server.hold_answers.clear()
    summary = run(split, out, config)
    assert summary.succeeded == ["00000"] and not summary.failed
    assert server.created == [paid] and examples(out)["00000"]["adopted"] is True


SUMMARY = re.compile(r"predict: (\d+) made, (\d+) up to date, (\d+) failed(?:, \d+ not started)?"
                     r"(?:, (\d+) being made by another process)?")


@pytest.mark.timeout(90)
@pytest.mark.parametrize("wait", [False, True], ids=["skip", "wait"])
def test_two_runs_on_one_folder_started_together_pay_once_for_each_example(server, tmp_path, wait):
    """Two `predict` processes on one --out while every creation is held a second: each example is created
    (paid) once, by one of them; the other skips it, saying so, or waits for it (--wait); nothing fails."""
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 3), tmp_path / "out"
    ids = ["00000", "00001", "00002"]
    server.hold_answers["apple"] = 1.0
    procs = [spawn(server, split, out, config, concurrency=3, extra=["--wait"] if wait else []) for _ in range(2)]
    made = 0
    for proc in procs:
        code, stdout, stderr = finish(proc, timeout=60)
        assert code == 0 and "Traceback" not in stderr and "Errno" not in stderr + stdout, stderr
        now, already, failed, elsewhere = (int(n or 0) for n in SUMMARY.search(stdout).groups())
        assert failed == 0 and now + already + elsewhere == 3, stdout
        assert elsewhere == 0 if wait else (elsewhere > 0) == ("by another process" in stderr), stdout + stderr
        made += now
    assert made == 3  # each example made by exactly one of the two
    assert_complete(out, server, ids)  # one creation per example, every one recorded
    assert not list((out / ".stages" / "predict").glob("staging/*"))


def test_examples_finishing_out_of_order_keep_their_records_through_a_kill(server, tmp_path):
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 3), tmp_path / "out"
    server.hold_answers["number 0 "] = 30  # the first example is slow; the two after it finish first
    proc = spawn(server, split, out, config, concurrency=3)
    wait_for(lambda: all(ledger_path(out, "predict", f"0000{i}").exists() for i in (1, 2)), what="two records")
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)
    for sample_id in ("00001", "00002"):
        entry = read_ledger(out, "predict", sample_id)["result"]
        assert entry["status"] == "succeeded" and entry["prediction_id"] == state(out, sample_id)["prediction_id"]
        assert (out / f"{sample_id}.mp4").is_file()
    server.hold_answers.clear()
    summary = run(split, out, config)
    assert summary.reused == ["00001", "00002"] and summary.succeeded == ["00000", "00001", "00002"]
    assert_complete(out, server, ["00000", "00001", "00002"])


def test_a_finished_video_without_a_record_gets_it_back_from_the_hosted_state(server, tmp_path):
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    assert not run(split, out, config).failed
    pid = examples(out)["00001"]["prediction_id"]
    ledger_path(out, "predict", "00001").unlink()  # killed between the video and its record (the ledger entry)
    doc = json.loads((out / GENERATION_FILE).read_text())
    del doc["examples"]["00001"]
    (out / GENERATION_FILE).write_text(json.dumps(doc))
    summary = run(split, out, config)
    assert summary.reused == ["00000", "00001"]
    entry = examples(out)["00001"]
    assert entry["prediction_id"] == pid and entry["status"] == "succeeded" and "recovered" in entry
    assert entry["prompt"].startswith("A red apple number 1") and entry["version"] == "hidden"
    assert read_ledger(out, "predict", "00001")["result"]["prediction_id"] == pid
    assert len(server.created) == 2


# -- the token -----------------------------------------------------------------------------------------


def test_the_token_reaches_no_file_or_log_line_even_when_the_server_echoes_it(server, tmp_path):
    config = write_config(tmp_path)
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    server.output_query = f"?token={TOKEN}&X-Amz-Signature=abc123"  # echoed in the output URL ...
    server.output_path_part = TOKEN  # ... in its path
    server.failures["number 1 "] = f"upstream refused key {TOKEN} at {server.url}/v1/x?auth={TOKEN}"  # and an error
    proc = spawn(server, split, out, config, concurrency=2, verbose=True)
    code, stdout, stderr = finish(proc)
    assert code == 1 and "FAILED 00001" in stderr
    assert "HTTP Request: GET" in stderr  # httpx's own request lines were logged, scrubbed
    assert TOKEN not in stdout + stderr
    entry = examples(out)["00000"]
    assert entry["output_url"] == f"{server.url}/output/[REDACTED]/{entry['prediction_id']}.mp4"
    assert "[REDACTED]" in examples(out)["00001"]["error"]
    written = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert len(written) > 10
    for path in written:
        assert TOKEN.encode() not in path.read_bytes(), path


@pytest.mark.parametrize("token, kind", [("r8_abc\u00e9def123", "a non-ASCII character"),
                                         ("r8_abc def123", "a space or line break"),
                                         ("r8_abc\ndef123", "a space or line break")])
def test_a_token_that_cannot_be_one_is_one_line_without_the_token(server, tmp_path, monkeypatch, capsys, token,
                                                                   kind):
    monkeypatch.setenv("REPLICATE_API_TOKEN", token)
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    assert main(["--config", str(write_config(tmp_path)), "predict", MODEL, "--data", str(split),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and f"REPLICATE_API_TOKEN holds {kind}" in lines[0], err
    assert "Traceback" not in err and "abc" not in err and "def123" not in err
    assert server.requests == []
