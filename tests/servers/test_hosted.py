"""The hosted video models against a stand-in for Replicate's API on 127.0.0.1 (no network, no token of
anyone's): the request of each model against the paper's table, the token kept out of every file, log and
error, retries, failures, size and format checks on downloads, resume without paying twice, --dry-run,
and bounded concurrency."""

import base64
import io
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("httpx")
pytest.importorskip("av")
pytest.importorskip("PIL")

from PIL import Image  # noqa: E402

from rigidbench.driver import RunOptions  # noqa: E402
from rigidbench.benchmark import NEGATIVE_PROMPT, full_prompt  # noqa: E402
from rigidbench.cli import main  # noqa: E402
from rigidbench.config import PACKAGE_CONFIG_DIR  # noqa: E402
from rigidbench.context import RunContext  # noqa: E402
from rigidbench.errors import ConfigError, PredictionError, UserError  # noqa: E402
from rigidbench.folders import GENERATION_FILE  # noqa: E402
from rigidbench.predictors import (PREDICTORS, SAMPLE_SEED_RULE, SEED_RULE, Kind, PredictContext,  # noqa: E402
                                   example_seed, sample_seed)
from rigidbench.predictors.hosted import HostedPredictor, load_hosted_config, parse_models  # noqa: E402
from rigidbench.predictors.replicate import (CallStats, ClientSettings, Deadline, ReplicateClient,  # noqa: E402
                                            StopRequested)
from rigidbench.stages.predict import predict  # noqa: E402
from rigidbench.video import probe_video  # noqa: E402

from fixtures.replicate_server import TOKEN, make_split  # noqa: E402
from fixtures.replicate_server import server, video  # noqa: E402,F401 (pytest fixtures)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def sent_frame(split, sample_id="00000", size=(1280, 720)):
    """The example's first frame as the adapter must send it: Lanczos-resized to ``size``, exact pixels."""
    frame = Image.open(split / sample_id / "frames" / "00000.png").convert("RGB")
    return np.asarray(frame.resize(size, Image.Resampling.LANCZOS))

# The paper's table (appendix B.1) and issue 14, written out here rather than read from models.yaml.
NEG = object()  # the paper's negative prompt
EXPECTED = {
    "veo-3.1": ("google/veo-3.1", {"image": "IMAGE", "prompt": "PROMPT", "negative_prompt": NEG, "duration": 4,
                                   "resolution": "720p", "aspect_ratio": "16:9", "generate_audio": False}),
    "veo-3.1-fast": ("google/veo-3.1-fast", {"image": "IMAGE", "prompt": "PROMPT", "negative_prompt": NEG,
                                             "duration": 4, "resolution": "720p", "aspect_ratio": "16:9",
                                             "generate_audio": False}),
    "kling-3.0": ("kwaivgi/kling-v3-video", {"start_image": "IMAGE", "prompt": "PROMPT", "negative_prompt": NEG,
                                             "duration": 3, "mode": "pro", "aspect_ratio": "16:9",
                                             "generate_audio": False}),
    "seedance-2.0": ("bytedance/seedance-2.0", {"image": "IMAGE", "prompt": "PROMPT", "duration": 4,
                                                "resolution": "720p", "aspect_ratio": "16:9", "generate_audio": False}),
    "seedance-2.0-fast": ("bytedance/seedance-2.0-fast", {"image": "IMAGE", "prompt": "PROMPT", "duration": 4,
                                                          "resolution": "720p", "aspect_ratio": "16:9",
                                                          "generate_audio": False}),
    "grok-imagine": ("xai/grok-imagine-video", {"image": "IMAGE", "prompt": "PROMPT", "duration": 4,
                                                "resolution": "720p", "aspect_ratio": "auto"}),
}
FAST_CLIENT = {"request_timeout_s": 5, "poll_interval_s": 0.01, "poll_max_interval_s": 0.02, "max_retries": 3,
               "backoff_base_s": 0.01, "backoff_max_s": 0.05, "example_timeout_s": 10, "max_output_bytes": 200_000}


def write_config(tmp_path, client=None, image=None) -> Path:
    """A --config directory holding the packaged models.yaml with tiny client limits."""
    data = yaml.safe_load((PACKAGE_CONFIG_DIR / "models.yaml").read_text())
    data["client"].update({**FAST_CLIENT, **(client or {})})
    data["image"].update(image or {})
    d = tmp_path / f"config{len(list(tmp_path.glob('config*')))}"
    d.mkdir()
    (d / "models.yaml").write_text(yaml.safe_dump(data))
    return d


@pytest.fixture
def config(tmp_path):
    return write_config(tmp_path)


def run(name, split, out, config_dir, dry_run=False, samples=1, **options):
    options.setdefault("concurrency", 2)
    ctx = PredictContext(RunContext(config_dirs=(config_dir,)), seed=7, options=options)
    return predict(name, split, out, ctx, dry_run=dry_run, samples=samples, run=RunOptions(progress=False))


def generation(out) -> dict:
    return json.loads((out / GENERATION_FILE).read_text())


# -- the six models -------------------------------------------------------------------------------------


def test_the_six_hosted_models_are_registered_and_configured():
    hosted = [n for n, info in PREDICTORS.items() if info.kind == Kind.HOSTED]
    assert set(EXPECTED) <= set(hosted)
    cfg = load_hosted_config()
    for name, (slug, _) in EXPECTED.items():
        assert PREDICTORS[name].target == "rigidbench.predictors.hosted:HostedPredictor"
        assert isinstance(PREDICTORS[name].create(), HostedPredictor) and PREDICTORS[name].create().paid
        assert cfg.model(name).replicate == slug
    assert (cfg.image.width, cfg.image.height, cfg.image.upload_threshold_bytes) == (1280, 720, 1_000_000)
    assert cfg.image.format == "png" and cfg.image.mime == "image/png"
    assert HostedPredictor(PREDICTORS["veo-3.1"]).concurrency(PredictContext()) == 8


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_request_body_matches_the_paper_table(name, server, config, tmp_path):
    slug, expected = EXPECTED[name]
    split = make_split(tmp_path / "eval", 1)
    out = tmp_path / "out"
    summary = run(name, split, out, config)
    assert summary.succeeded == ["00000"] and not summary.failed
    (create,) = server.creations()
    assert create.path == f"/v1/models/{slug}/predictions"
    assert create.headers["prefer"] == "wait" and create.headers["authorization"] == f"Bearer {TOKEN}"
    assert create.headers["content-type"] == "application/json"
    assert set(create.json) == {"input"}
    sent = create.json["input"]
    assert set(sent) == set(expected), f"{name}: inputs {sorted(sent)} != {sorted(expected)}"
    task_prompt = (split / "00000" / "prompt.txt").read_text().strip()
    for field, want in expected.items():
        got = sent[field]
        if want == "IMAGE":  # a lossless PNG, as the paper's runs sent it
            assert got.startswith("data:image/png;base64,") and len(got) < 1_000_000
            data = base64.b64decode(got.split(",", 1)[1])
            image = Image.open(io.BytesIO(data))
            assert data.startswith(PNG_SIGNATURE) and image.format == "PNG" and image.size == (1280, 720)
            assert np.array_equal(np.asarray(image.convert("RGB")), sent_frame(split))
        elif want == "PROMPT":
            assert got == full_prompt(task_prompt) and got.endswith("Motion begins on the first frame.")
        elif want is NEG:
            assert got == NEGATIVE_PROMPT
        else:
            assert got == want and type(got) is type(want), f"{name}.{field}: {got!r} != {want!r}"
    doc = generation(out)
    assert doc["model"]["model"] == slug and doc["model"]["inputs"] == {k: v for k, v in expected.items()
                                                                         if v not in ("IMAGE", "PROMPT", NEG)}
    assert doc["settings"]["model"] == slug and doc["settings"]["seed"] is None  # no model takes a seed
    assert doc["settings"]["image"] == {"width": 1280, "height": 720, "format": "png"}
    assert "seeds" not in doc["settings"]  # no seed is sent, so none is derived
    entry = doc["examples"]["00000"]
    assert entry["status"] == "succeeded" and entry["prediction_id"].startswith("stand")
    assert entry["version"] == "hidden" and entry["metrics"]["predict_time"] == 0.01 and entry["seed"] is None
    assert entry["negative_prompt"] == (NEGATIVE_PROMPT if NEG in expected.values() else None)
    assert entry["prompt"] == full_prompt(task_prompt) and entry["image_sent_as"] == "data URI"
    assert probe_video(out / "00000.mp4").n_frames == 12
    assert not list((out / ".hosted").glob("*.mp4"))  # the download was moved into place, not kept twice


def test_a_first_frame_too_large_for_a_data_uri_is_uploaded_as_png(server, config, tmp_path):
    server.max_data_uri_bytes = 1_000_000  # Replicate recommends data URIs under 1 MB
    split = make_split(tmp_path / "eval", 1, texture="noise")  # its 1280x720 PNG is about 1.6 MB
    assert not run("kling-3.0", split, tmp_path / "out", config).failed
    (request,) = server.requests_to("/v1/files", "POST")
    assert request.headers["content-type"].startswith("multipart/form-data")
    (upload,) = server.uploads
    assert (upload.filename, upload.content_type) == ("00000.png", "image/png") and len(upload.data) > 1_000_000
    assert upload.data.startswith(PNG_SIGNATURE)
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(upload.data)).convert("RGB")), sent_frame(split))
    assert server.creations()[0].json["input"]["start_image"] == f"{server.url}/v1/files/{upload.file_id}"
    assert generation(tmp_path / "out")["examples"]["00000"]["image_sent_as"] == "upload"
    # the same frame inline (threshold raised past it) is what the size limit refuses
    inline = write_config(tmp_path, image={"upload_threshold_bytes": 10_000_000})
    summary = run("kling-3.0", split, tmp_path / "inline", inline)
    assert "HTTP 413" in summary.failed["00000"] and len(server.uploads) == 1


def seeded_veo(tmp_path) -> Path:
    """A --config directory in which veo-3.1 is sent each prediction's seed as its input "seed"."""
    config = write_config(tmp_path)
    data = yaml.safe_load((config / "models.yaml").read_text())
    data["models"]["veo-3.1"]["seed_field"] = "seed"
    (config / "models.yaml").write_text(yaml.safe_dump(data))
    return config


def test_a_model_that_takes_a_seed_gets_each_examples_own(server, tmp_path):
    config = seeded_veo(tmp_path)
    out = tmp_path / "out"
    assert not run("veo-3.1", make_split(tmp_path / "eval", 2), out, config).failed  # base seed 7
    sent = {json.loads(r.body)["input"]["prompt"].split("number ")[1][0]: json.loads(r.body)["input"]["seed"]
            for r in server.creations()}
    assert sent == {"0": example_seed(7, "00000"), "1": example_seed(7, "00001")}
    doc = generation(out)
    assert doc["settings"]["seed"] == 7 and doc["settings"]["seeds"] == SEED_RULE
    assert [doc["examples"][i]["seed"] for i in ("00000", "00001")] == [sent["0"], sent["1"]]


def test_the_jpeg_of_the_earlier_adapter_is_an_option(server, tmp_path):
    config = write_config(tmp_path, image={"format": "jpeg"})
    split = make_split(tmp_path / "eval", 1)
    assert not run("veo-3.1", split, tmp_path / "out", config).failed
    sent = server.creations()[0].json["input"]["image"]
    assert sent.startswith("data:image/jpeg;base64,")
    assert Image.open(io.BytesIO(base64.b64decode(sent.split(",", 1)[1]))).format == "JPEG"
    assert generation(tmp_path / "out")["settings"]["image"] == {"width": 1280, "height": 720, "format": "jpeg",
                                                                 "jpeg_quality": 95}


# -- the token ------------------------------------------------------------------------------------------


def test_the_token_reaches_no_file_log_or_error(server, config, tmp_path, caplog, capsys):
    caplog.set_level(logging.DEBUG)
    split = make_split(tmp_path / "eval", 3, prompts=["A ball rolls.", "A box falls. FAILME", "A cup slides."])
    server.failures["FAILME"] = "E001: the model failed"
    server.script("POST", "/v1/models/", 500, times=1)
    good = run("veo-3.1", split, tmp_path / "good", config)
    assert sorted(good.succeeded) == ["00000", "00002"] and "E001" in good.failed["00001"]
    # Every download went out without the token (delivery URLs may live on another host).
    downloads = server.requests_to("/output/")
    assert downloads and all("authorization" not in r.headers for r in downloads)
    # An API that echoes the token back in its error message: the message is kept, the token is not.
    server.token, server.echo_token_in_errors = "another-token", True
    bad = run("veo-3.1", split, tmp_path / "bad", config)
    assert len(bad.failed) == 3 and all("HTTP 401" in m and "[REDACTED]" in m for m in bad.failed.values())
    # A network error (nothing listens there) and the client's own repr.
    client = ReplicateClient(ClientSettings(max_retries=1, backoff_base_s=0.01), base_url="http://127.0.0.1:9")
    with pytest.raises(PredictionError) as err:
        client.get("abc", Deadline(5), CallStats())
    assert "network error after 2 attempts" in str(err.value)
    messages = [str(err.value), repr(client), *good.failed.values(), *bad.failed.values()]
    client.close()
    for path in [*(tmp_path / "good").rglob("*"), *(tmp_path / "bad").rglob("*")]:
        if path.is_file():
            assert TOKEN.encode() not in path.read_bytes(), path
    assert (tmp_path / "good" / GENERATION_FILE).is_file() and (tmp_path / "bad" / GENERATION_FILE).is_file()
    records = [r.getMessage() + str(r.args) + (r.exc_text or "") for r in caplog.records]
    assert records and not [r for r in records if TOKEN in r]
    captured = capsys.readouterr()
    assert not [m for m in messages + [captured.out, captured.err] if TOKEN in m]


def test_a_missing_token_is_one_up_front_error_and_nothing_is_sent(server, config, tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("REPLICATE_API_TOKEN")
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    with pytest.raises(UserError, match="REPLICATE_API_TOKEN is not set"):
        run("grok-imagine", split, out, config)
    assert server.requests == [] and not list(out.glob("*.mp4"))
    assert not (out / GENERATION_FILE).exists()  # no example ran, so none is recorded as failed
    command = ["--config", str(config), "predict", "grok-imagine", "--data", str(split), "--out", str(out)]
    assert main(command) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "REPLICATE_API_TOKEN is not set" in err[0] and "Traceback" not in err[0]
    monkeypatch.setenv("REPLICATE_BASE_URL", "ftp://example.invalid")
    with pytest.raises(UserError, match="REPLICATE_BASE_URL must be an http"):
        run("grok-imagine", make_split(tmp_path / "eval", 2), tmp_path / "out", config)


# -- robustness -------------------------------------------------------------------------------------------


def test_rate_limits_and_server_errors_are_retried_and_counted(server, config, tmp_path):
    server.wait_finishes = False  # creation answers "starting"; the status is polled
    server.polls_to_finish = 2
    server.script("POST", "/v1/models/", 429, headers={"Retry-After": "1"}, detail="Request was throttled")
    server.script("POST", "/v1/models/", 429, detail="Request was throttled")  # no Retry-After: backoff
    server.script("POST", "/v1/models/", 503)
    server.script("GET", "/v1/predictions/", 500)
    server.script("GET", "/output/", 502)
    started = time.monotonic()
    summary = run("seedance-2.0", make_split(tmp_path / "eval", 1), tmp_path / "out", config)
    elapsed = time.monotonic() - started
    assert summary.succeeded == ["00000"] and not summary.failed
    assert len(server.creations()) == 4 and len(server.predictions) == 1  # three refusals, one paid prediction
    assert elapsed >= 1.0  # Retry-After was waited; backoff alone is at most 0.05 s here
    entry = generation(tmp_path / "out")["examples"]["00000"]
    assert entry["retries"] == 5
    assert entry["retried"] == {"rate_limited": 2, "server_errors": 3, "network_errors": 0}


def test_server_errors_past_the_retries_fail_the_example_with_the_api_message(server, config, tmp_path):
    server.script("POST", "/v1/models/", 500, detail="model backend unavailable", times=4)  # max_retries 3 + 1
    summary = run("veo-3.1-fast", make_split(tmp_path / "eval", 3), tmp_path / "out", config, concurrency=1)
    assert list(summary.failed) == ["00000"] and sorted(summary.succeeded) == ["00001", "00002"]
    assert "HTTP 500 after 4 attempts" in summary.failed["00000"]
    assert "model backend unavailable" in summary.failed["00000"]
    assert generation(tmp_path / "out")["examples"]["00000"]["status"] == "failed"


def test_a_failed_prediction_is_recorded_the_others_go_on_and_a_rerun_retries_it(server, config, tmp_path):
    server.wait_finishes = False
    server.failures["number 1"] = "E005: the input was flagged as sensitive"
    split = make_split(tmp_path / "eval", 3)
    out = tmp_path / "out"
    summary = run("kling-3.0", split, out, config, concurrency=3)
    assert sorted(summary.succeeded) == ["00000", "00002"]
    assert "E005: the input was flagged as sensitive" in summary.failed["00001"]
    entry = generation(out)["examples"]["00001"]
    assert entry["status"] == "failed" and "E005" in entry["error"] and "stand" in entry["error"]  # the id
    del server.failures["number 1"]
    again = run("kling-3.0", split, out, config, concurrency=3)
    assert again.reused == ["00000", "00002"] and not again.failed
    assert len(server.creations("number 1")) == 2 and len(server.creations()) == 4
    doc = generation(out)
    assert doc["examples"]["00001"]["status"] == "succeeded"
    assert doc["examples"]["00001"]["replaces_prediction"] == entry["error"].split()[1]


@pytest.mark.parametrize("kind, message", [("oversize", "over the cap"), ("oversize_unsized", "passed the cap"),
                                           ("not_video", "not a decodable video")])
def test_oversized_and_non_video_outputs_are_refused(server, config, tmp_path, kind, message):
    server.outputs["number 0"] = kind
    server.oversize_bytes = 300_000  # the test cap is 200,000 bytes
    out = tmp_path / "out"
    summary = run("veo-3.1", make_split(tmp_path / "eval", 2), out, config)
    assert summary.succeeded == ["00001"] and message in summary.failed["00000"]
    assert not (out / "00000.mp4").exists()
    assert not [p for p in (out / ".hosted").iterdir() if p.suffix != ".json"]  # no partial download left


# -- resume ------------------------------------------------------------------------------------------------


def test_a_run_killed_after_creation_resumes_without_a_second_creation(server, config, tmp_path, monkeypatch):
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    real = ReplicateClient.download

    def killed(self, *args, **kwargs):
        monkeypatch.setattr(ReplicateClient, "download", real)
        raise KeyboardInterrupt  # the process dies between creation and download

    monkeypatch.setattr(ReplicateClient, "download", killed)
    with pytest.raises(KeyboardInterrupt):
        run("veo-3.1", split, out, config, concurrency=1)
    (first,) = server.creations()
    stored = json.loads((out / ".hosted" / "00000.json").read_text())
    assert stored["prediction_id"] in server.predictions and TOKEN not in json.dumps(stored)
    summary = run("veo-3.1", split, out, config, concurrency=1)
    assert summary.succeeded == ["00000", "00001"] and not summary.failed
    assert len(server.creations("number 0")) == 1 and len(server.creations()) == 2
    assert server.requests_to(f"/v1/predictions/{stored['prediction_id']}", "GET")
    entry = generation(out)["examples"]["00000"]
    assert entry["resumed"] is True and entry["prediction_id"] == stored["prediction_id"]


def test_an_interrupted_download_is_fetched_again_by_prediction_id(server, config, tmp_path):
    split, out = make_split(tmp_path / "eval", 1), tmp_path / "out"
    server.drop_downloads = 4  # every attempt of the first run (max_retries 3 + 1) is cut off
    summary = run("seedance-2.0-fast", split, out, config)
    assert "network error after 4 attempts" in summary.failed["00000"]
    again = run("seedance-2.0-fast", split, out, config)
    assert again.succeeded == ["00000"] and not again.failed
    assert len(server.creations()) == 1  # paid once
    assert probe_video(out / "00000.mp4").n_frames == 12


def test_a_prediction_past_the_timeout_is_kept_and_waited_for_on_rerun(server, tmp_path):
    config = write_config(tmp_path, client={"example_timeout_s": 0.3})
    split, out = make_split(tmp_path / "eval", 1), tmp_path / "out"
    server.never_finish = True
    summary = run("veo-3.1", split, out, config)
    assert "per-example timeout" in summary.failed["00000"] and "resumes it without paying again" in summary.failed["00000"]
    server.never_finish = False
    again = run("veo-3.1", split, out, config)
    assert again.succeeded == ["00000"] and len(server.creations()) == 1


def test_a_stop_cuts_a_hung_download_after_its_grace_and_ends_a_pause_at_once(server, tmp_path):
    """After the run's stop (SIGTERM, Ctrl-C) a request in flight gets ``stop_grace`` seconds, then is cut off
    and not retried; a pause between polls ends at once, and no poll follows."""
    slow = ClientSettings(request_timeout_s=30, poll_interval_s=30, poll_max_interval_s=30, max_retries=3)
    client = ReplicateClient(slow, base_url=server.url, token=TOKEN)
    done = client.create("google/veo-3.1", {"prompt": "a"}, Deadline(10), CallStats())
    server.hang_downloads = True  # half the video, then the connection is held
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    started = time.monotonic()
    with pytest.raises(StopRequested, match="the run is stopping"):
        client.download(done["output"], tmp_path / "x.mp4", Deadline(60, stop=stop, stop_grace=0.5), CallStats())
    assert 0.8 <= time.monotonic() - started < 3  # 0.3 s to the stop, its 0.5 s grace, then at once
    assert len(server.requests_to("/output/")) == 1 and not list(tmp_path.iterdir())  # no retry, no partial file

    server.wait_finishes, server.never_finish = False, True
    running = client.create("google/veo-3.1", {"prompt": "b"}, Deadline(10), CallStats())
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    started = time.monotonic()
    with pytest.raises(StopRequested):
        client.wait(running, Deadline(60, stop=stop), CallStats())  # its first pause is 30 s
    assert time.monotonic() - started < 2 and not server.requests_to(f"/v1/predictions/{running['id']}")
    client.close()


def test_an_output_deleted_by_replicate_is_paid_for_again_only_when_asked(server, config, tmp_path, caplog):
    split, out = make_split(tmp_path / "eval", 1), tmp_path / "out"
    server.drop_downloads = 4
    run("veo-3.1", split, out, config)
    server.data_removed = True  # more than an hour later
    again = run("veo-3.1", split, out, config)
    assert "--repay-expired" in again.failed["00000"] and len(server.creations()) == 1  # no second payment
    assert not run("veo-3.1", split, out, config, repay_expired=True).failed
    assert len(server.creations()) == 2 and "deleted its output" in caplog.text


# -- several samples per example (--samples K): each is a paid prediction of its own ---------------------------

SAMPLES = ["00000", "00000.s1", "00001", "00001.s1"]


def test_k_samples_are_paid_once_each_and_a_rerun_pays_nothing(server, config, tmp_path, capsys):
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    assert run("veo-3.1", split, out, config).succeeded == ["00000", "00001"] and len(server.created) == 2
    capsys.readouterr()
    planned = run("veo-3.1", split, out, config, dry_run=True, samples=2)  # only the new samples are paid for
    assert planned.facts.planned == ["00000.s1", "00001.s1"] and planned.facts.paid_calls == 2
    assert "the service's own randomness" in planned.facts.note and len(server.created) == 2
    summary = run("veo-3.1", split, out, config, samples=2)
    assert summary.reused == ["00000", "00001"] and summary.ran == ["00000.s1", "00001.s1"] and not summary.failed
    assert len(server.paid("number 0")) == 2 and len(server.paid("number 1")) == 2 and len(server.created) == 4
    held = {i: json.loads((out / ".hosted" / f"{i}.json").read_text())["prediction_id"] for i in SAMPLES}
    assert sorted(held.values()) == sorted(server.created)  # one paid prediction per sample, none shared
    first, second = server.creations("number 0")
    assert first.json == second.json and "seed" not in first.json["input"]  # no seed: the same request twice
    doc = generation(out)
    assert {i: (r["sample"], r["prediction_id"]) for i, r in doc["examples"].items()} == \
           {i: (1 if ".s1" in i else 0, held[i]) for i in SAMPLES}
    assert "no seed" in doc["samples"]["seeds"] and doc["samples"]["per_example"] == 2
    assert sorted(p.name for p in out.glob("*.mp4")) == [f"{i}.mp4" for i in SAMPLES]
    requests = len(server.requests)
    again = run("veo-3.1", split, out, config, samples=2)
    assert again.reused == SAMPLES and len(server.requests) == requests  # nothing paid, not even a poll


def test_a_seeded_model_sends_each_sample_its_own_seed(server, tmp_path):
    config = seeded_veo(tmp_path)
    out = tmp_path / "out"
    assert not run("veo-3.1", make_split(tmp_path / "eval", 1), out, config, samples=3).failed
    sent = sorted(c.json["input"]["seed"] for c in server.creations())
    assert sent == sorted(sample_seed(7, "00000", k) for k in range(3)) and len(set(sent)) == 3
    assert sample_seed(7, "00000", 0) == example_seed(7, "00000")
    doc = generation(out)
    assert [doc["examples"][i]["seed"] for i in ("00000", "00000.s1", "00000.s2")] == \
           [sample_seed(7, "00000", k) for k in range(3)]
    assert doc["samples"] == {"per_example": 3, "seeds": SAMPLE_SEED_RULE}


def test_an_interrupted_creation_of_a_sample_never_adopts_another_samples_prediction(server, config, tmp_path,
                                                                                     capsys):
    split, out = make_split(tmp_path / "eval", 1), tmp_path / "out"
    run("veo-3.1", split, out, config)
    zero = json.loads((out / ".hosted" / "00000.json").read_text())
    # sample 1's run was killed while creating it: its intent, older than sample 0's prediction, with the same
    # input (the model is sent no seed), so sample 0's prediction looks like the one it made
    intent = {**zero["intent"], "at": zero["intent"]["at"] - 1}
    (out / ".hosted" / "00000.s1.json").write_text(json.dumps({"model": zero["model"], "intent": intent,
                                                               "fingerprint": zero["fingerprint"]}))
    capsys.readouterr()
    run("veo-3.1", split, out, config, dry_run=True, samples=2)
    (line,) = capsys.readouterr().out.strip().splitlines()
    assert line.startswith("00000.s1: ") and "resolves_interrupted_creation" in line
    summary = run("veo-3.1", split, out, config, samples=2)
    assert summary.ran == ["00000.s1"] and not summary.failed
    assert server.requests_to("/v1/predictions", "GET")  # the account's predictions were checked ...
    one = json.loads((out / ".hosted" / "00000.s1.json").read_text())["prediction_id"]
    assert len(server.created) == 2 and one == server.created[1] != zero["prediction_id"]  # ... and 0's not taken


def test_a_samples_stale_temporaries_are_removed_and_no_other_samples(tmp_path):
    state_dir = tmp_path / ".hosted"
    state_dir.mkdir()
    names = [".00000.k3_x9q2a.part.mp4", ".00000.json.abc.tmp", ".00000.s1.k3_x9q2a.part.mp4",
             ".00000.s1.json.abc.tmp", ".00000.s1.json"]
    for name in names:
        (state_dir / name).write_bytes(b"x")
    HostedPredictor(PREDICTORS["veo-3.1"])._clean_temporaries(state_dir, "00000")
    assert sorted(p.name for p in state_dir.iterdir()) == sorted(names[2:])  # sample 1's may be downloading
    HostedPredictor(PREDICTORS["veo-3.1"])._clean_temporaries(state_dir, "00000.s1")
    assert [p.name for p in state_dir.iterdir()] == [".00000.s1.json"]


# -- dry run, concurrency, command line, configuration ------------------------------------------------------


def test_dry_run_sends_nothing_and_counts_the_paid_calls(server, config, tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("REPLICATE_API_TOKEN")  # not needed to plan
    out = tmp_path / "out"
    summary = run("kling-3.0", make_split(tmp_path / "eval", 3), out, config, dry_run=True)
    assert summary.facts.paid_calls == 3 and summary.facts.planned == ["00000", "00001", "00002"]
    assert server.requests == [] and not out.exists()
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and all("elided" in line and "base64" not in line for line in lines)
    request = json.loads(lines[0].split(": ", 1)[1])
    assert request["url"].endswith("/v1/models/kwaivgi/kling-v3-video/predictions")
    assert request["headers"]["Authorization"] == "Bearer $REPLICATE_API_TOKEN"
    assert request["body"]["input"]["mode"] == "pro" and request["body"]["input"]["duration"] == 3


def test_concurrency_is_bounded(server, config, tmp_path):
    server.create_delay_s = 0.15  # a slow model: each creation holds its connection
    summary = run("veo-3.1", make_split(tmp_path / "eval", 6), tmp_path / "out", config, concurrency=2)
    assert len(summary.succeeded) == 6
    assert server.max_in_flight == 2  # two at once, never more


def test_command_line_with_a_config_directory(server, config, tmp_path, capsys):
    split, out = make_split(tmp_path / "eval", 2), tmp_path / "out"
    command = ["--config", str(config), "predict", "grok-imagine", "--data", str(split), "--out", str(out)]
    assert main(command + ["--dry-run"]) == 0
    assert "2 paid API calls; nothing was sent" in capsys.readouterr().out and server.requests == []
    assert main(command + ["--dry-run", "--samples", "2"]) == 0
    text = capsys.readouterr().out
    assert "grok-imagine: 4 paid API calls (2 samples per example, each a paid call of its own)" in text
    assert "note: grok-imagine takes no seed" in text and server.requests == []
    assert main(command + ["--concurrency", "1"]) == 0
    assert sorted(p.name for p in out.glob("*.mp4")) == ["00000.mp4", "00001.mp4"]
    doc = generation(out)
    assert doc["model"]["client"]["backoff_base_s"] == 0.01  # the --config copy was used
    assert doc["model"]["concurrency"] == 1 and server.max_in_flight == 1
    assert main(["predict", "--list"]) == 0
    assert "grok-imagine" in capsys.readouterr().out


def test_models_yaml_errors_name_the_file_and_the_field(tmp_path):
    good = yaml.safe_load((PACKAGE_CONFIG_DIR / "models.yaml").read_text())
    path = tmp_path / "models.yaml"

    def broken(edit):
        data = json.loads(json.dumps(good))
        edit(data)
        return data

    cases = [
        (lambda d: d["models"]["veo-3.1"].update(durration=4), "field 'models.veo-3.1.durration': unknown field"),
        (lambda d: d["models"]["kling-3.0"].pop("image_field"), "field 'models.kling-3.0.image_field': is required"),
        (lambda d: d["models"]["veo-3.1"]["inputs"].update(prompt="x"), "models.veo-3.1.inputs.prompt"),
        (lambda d: d["models"]["grok-imagine"].update(replicate="grok"), "models.grok-imagine.replicate"),
        (lambda d: d["client"].update(max_retries=-1), "field 'client.max_retries': must be >= 0"),
        (lambda d: d["client"].update(wait_s=120), "field 'client.wait_s'"),
        (lambda d: d["image"].update(width="wide"), "field 'image.width': expected an integer"),
        (lambda d: d["image"].update(format="gif"), "field 'image.format': unknown value 'gif'"),
        (lambda d: d["image"].update(qualty=90), "field 'image.qualty': unknown field"),
        (lambda d: d.update(extra=1), "field 'extra': unknown field"),
    ]
    for edit, message in cases:
        with pytest.raises(ConfigError) as err:
            parse_models(path, broken(edit))
        assert str(err.value).startswith(str(path)) and message in str(err.value), str(err.value)
    cfg = parse_models(path, broken(lambda d: d["models"].pop("veo-3.1")))
    with pytest.raises(ConfigError, match="no entry for 'veo-3.1'"):
        cfg.model("veo-3.1")
    (tmp_path / "models.yaml").write_text("models: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_hosted_config([tmp_path])
