"""Dataset descriptions (YAML) and the resumable, verified, safely extracted download, against a stand-in
dataset host on 127.0.0.1 (tests/fixtures/dataset_server.py)."""

import hashlib
import json
import os
import random
import shutil
import tarfile
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

httpx = pytest.importorskip("httpx")

from rigidbench.datasets import download as dl  # noqa: E402
from rigidbench.datasets.describe import load_dataset, list_datasets  # noqa: E402
from rigidbench.datasets.download import (ChecksumError, DiskSpaceError, DownloadBusyError,  # noqa: E402
                                          DownloadError, TransferSettings, download_dataset, download_dir)
from rigidbench.datasets.extract import ConcatenatedFiles, UnsafeMemberError, md5_of  # noqa: E402
from rigidbench.errors import ConfigError, UnknownNameError  # noqa: E402

from fixtures.dataset_server import StandInDatasetServer, make_tar_gz, split, write_description  # noqa: E402

PART_BYTES = 4096
FAST = TransferSettings(connect_timeout_s=2.0, read_timeout_s=2.0, retries=2, max_requests_per_part=10,
                        backoff_s=0.01, backoff_max_s=0.05, min_bytes_per_s=1.0, throughput_window_s=10.0,
                        disk_margin_bytes=0)


def published_members():
    """A small archive in the published layout: a top folder, a manifest and two samples (random bytes, so
    the gzip does not shrink them and the archive spans several parts)."""
    rng = random.Random(7)
    return [
        ("rigidbench-eval-v1.1", None, {}),
        ("rigidbench-eval-v1.1/manifest.json", b'[{"sample_id": "00000"}, {"sample_id": "00001"}]', {}),
        ("rigidbench-eval-v1.1/samples/00000/video.mp4", rng.randbytes(9000), {}),
        ("rigidbench-eval-v1.1/samples/00000/prompt.txt", b"A ball drops onto the table.", {}),
        ("rigidbench-eval-v1.1/samples/00001/video.mp4", rng.randbytes(7000), {}),
    ]


@pytest.fixture
def no_proxy(monkeypatch):
    for var in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        monkeypatch.delenv(var, raising=False)


@pytest.fixture
def client():
    with httpx.Client(trust_env=False, follow_redirects=True) as c:  # only ever 127.0.0.1
        yield c


@pytest.fixture
def make_set(tmp_path):
    """make_set(members=None, md5=None) -> a served dataset: server, desc (read back through load_dataset
    from a --config directory), data dir, archive bytes, parts {name: bytes}."""
    servers = []

    def make(members=None, md5=None):
        archive = make_tar_gz(members if members is not None else published_members())
        parts = split(archive, PART_BYTES, "test-eval-v0.1.tar.gz")
        server = StandInDatasetServer(parts).start()
        servers.append(server)
        config = tmp_path / f"config{len(servers)}"
        write_description(config, "test-eval-v0.1", name="test-eval", version="0.1", archive="test-eval-v0.1.tar.gz",
                          data=archive, md5=md5 or hashlib.md5(archive).hexdigest(), part_bytes=PART_BYTES,
                          url=server.url_template)
        desc = load_dataset("test-eval", [config])
        data = tmp_path / f"data{len(servers)}"
        return SimpleNamespace(server=server, desc=desc, data=data, archive=archive, parts=parts,
                               root=download_dir(desc, data), names=list(parts))

    yield make
    for s in servers:
        s.stop()


def tree(root: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def expected_tree(members) -> dict[str, bytes | None]:
    out = {}
    for name, content, _ in members:
        parts = name.split("/")
        for i in range(1, len(parts)):
            out.setdefault("/".join(parts[:i]), None)
        out[name] = content
    return out


# -- descriptions ------------------------------------------------------------------------------------


def test_packaged_description_is_the_published_archive():
    desc = load_dataset(None)
    assert desc == load_dataset("rigidbench-eval") == load_dataset("rigidbench-eval-v1.1")
    assert (desc.id, desc.name, desc.version) == ("rigidbench-eval-v1.1", "rigidbench-eval", "1.1")
    assert desc.archive == "rigidbench-eval-v1.1.tar.gz" and desc.size_bytes == 18_184_558_630
    assert desc.md5 == "b563f279451e95fe2f32d7e258588636"
    assert (desc.licence, desc.doi, desc.record) == ("CC BY 4.0", "10.5281/zenodo.21649156", "21649156")
    assert len(desc.parts) == 68
    assert [p.name for p in desc.parts[:2]] == ["rigidbench-eval-v1.1.tar.gz.part01-of-68",
                                                "rigidbench-eval-v1.1.tar.gz.part02-of-68"]
    assert desc.parts[-1].name == "rigidbench-eval-v1.1.tar.gz.part68-of-68"
    assert all(p.size_bytes == 268_435_456 for p in desc.parts[:-1])
    assert desc.parts[-1].size_bytes == 18_184_558_630 - 67 * 268_435_456 == 199_383_078
    assert [p.offset_bytes for p in desc.parts] == [i * 268_435_456 for i in range(68)]
    assert desc.parts[4].url == ("https://zenodo.org/api/records/21649156/files/"
                                 "rigidbench-eval-v1.1.tar.gz.part05-of-68/content")


def test_unknown_dataset_suggests_the_nearest_name():
    with pytest.raises(UnknownNameError, match="did you mean 'rigidbench-eval'"):
        load_dataset("rigidbench-evl")


GOOD = {"name": "mirror", "version": "1.0", "archive": "m.tar.gz", "size_bytes": 10,
        "md5": "0123456789abcdef0123456789abcdef", "parts": {"count": 3, "size_bytes": 4, "name": "{archive}.{index}"},
        "url": "http://127.0.0.1:9/{part}", "licence": "CC BY 4.0"}


@pytest.mark.parametrize("change, field", [
    ({"md5": "not-an-md5"}, "md5"),
    ({"size_bytes": 13}, "parts"),  # 3 parts of 4 bytes cannot make 13
    ({"version": 1.0}, "version"),  # unquoted: YAML makes it a number
    ({"url": "http://127.0.0.1:9/{file}"}, "url"),
    ({"url": "ftp://example.org/{part}"}, "url"),
    ({"parts": {"count": 3, "size_bytes": 4, "name": "{archive}"}}, "parts"),  # every part the same name
    ({"parts": {"count": 3, "size_bytes": 4, "name": "../{archive}.{index}"}}, "parts.name"),
    ({"parts": [{"name": "a", "size_bytes": 4}, {"name": "b", "size_bytes": 5}]}, "parts"),  # 9 != 10
    ({"mirrors": []}, "mirrors"),
])
def test_a_bad_description_names_the_file_and_the_field(tmp_path, change, field):
    import yaml

    path = tmp_path / "datasets" / "mirror-v1.yaml"
    path.parent.mkdir()
    path.write_text(yaml.safe_dump({**GOOD, **change}))
    with pytest.raises(ConfigError) as err:
        load_dataset("mirror", [tmp_path])
    assert str(path) in str(err.value) and f"field '{field}'" in str(err.value)


def test_config_directory_adds_a_mirror_and_later_release(tmp_path):
    import yaml

    packaged = load_dataset("rigidbench-eval-v1.1")
    mirror = tmp_path / "datasets" / "rigidbench-eval-v1.1.yaml"  # same id: replaces the packaged file
    mirror.parent.mkdir()
    text = Path(packaged.source).read_text().replace("https://zenodo.org/api/records/21649156/files/",
                                                     "https://mirror.example.org/rb/")
    mirror.write_text(text)
    desc = load_dataset("rigidbench-eval", [tmp_path])
    assert desc.source == str(mirror) and desc.parts[0].url.startswith("https://mirror.example.org/rb/")
    assert desc.md5 == packaged.md5 and len(desc.parts) == 68
    later = tmp_path / "datasets" / "rigidbench-eval-v1.10.yaml"
    later.write_text(yaml.safe_dump({**GOOD, "name": "rigidbench-eval", "version": "1.10"}))
    assert load_dataset(None, [tmp_path]).id == "rigidbench-eval-v1.10"  # 1.10 > 1.1 (not a decimal)
    assert load_dataset("rigidbench-eval-v1.1", [tmp_path]).source == str(mirror)
    assert set(list_datasets([tmp_path])) == {"rigidbench-eval-v1.1", "rigidbench-eval-v1.10"}


# -- download ----------------------------------------------------------------------------------------


def test_download_verifies_extracts_marks_and_a_rerun_makes_no_request(make_set, no_proxy):
    s = make_set()
    assert len(s.parts) >= 4
    out = download_dataset(s.desc, s.data, progress=False, settings=FAST)  # its own client
    assert out == s.root / "extracted"
    assert tree(out) == expected_tree(published_members())
    assert [s.server.requests(n) for n in s.names] == [1] * len(s.names)
    assert s.server.bytes_served() == len(s.archive)
    marker = json.loads((s.root / "complete.json").read_text())
    assert (marker["id"], marker["version"], marker["md5"], marker["md5_verified"]) == (
        "test-eval-v0.1", "0.1", hashlib.md5(s.archive).hexdigest(), True)
    assert not [p for p in s.root.iterdir() if p.name.startswith("test-eval-v0.1.tar.gz")]  # parts deleted
    assert not (s.root / "extracted.tmp").exists()

    before = s.server.requests()
    assert download_dataset(s.desc, s.data, progress=False, settings=FAST) == out
    assert s.server.requests() == before


def test_a_cut_transfer_resumes_with_range_in_the_same_run(make_set, client):
    s = make_set()
    second = s.names[1]
    s.server.cut[second] = [1000]
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    asked = [r.range_start for r in s.server.served if r.name == second]
    assert asked == [None, 1000]
    assert s.server.bytes_served() == len(s.archive)  # nothing fetched twice
    assert tree(s.root / "extracted") == expected_tree(published_members())


def test_an_interrupted_download_resumes_without_refetching(make_set, client):
    s = make_set()
    third = s.names[2]
    # 1500 bytes, then the connection drops at once on every try: the run gives up
    s.server.cut[third] = [1500] + [0] * (FAST.retries + 1)
    with pytest.raises(DownloadError) as err:
        download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    message = str(err.value)
    assert third in message and f"http://127.0.0.1:{s.server.port}/files/{third}/content" in message
    assert "s3cr3t" not in message and "token" not in message  # no query string
    assert "again to resume" in message
    assert (s.root / s.names[0]).stat().st_size == PART_BYTES  # complete parts under their own name
    assert (s.root / f"{third}.part").stat().st_size == 1500
    assert not (s.root / "extracted").exists()

    assert s.server.cut[third] == []  # the host is back
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    for name in s.names[:2]:
        assert s.server.requests(name) == 1  # complete parts are not asked for again
        assert s.server.bytes_served(name) == len(s.parts[name])
    asked = [r.range_start for r in s.server.served if r.name == third]
    assert asked == [None] + [1500] * (FAST.retries + 2)
    assert s.server.bytes_served(third) == len(s.parts[third])
    assert s.server.bytes_served() == len(s.archive)
    assert tree(s.root / "extracted") == expected_tree(published_members())


def test_parts_on_disk_are_not_requested_and_a_partial_part_continues(make_set, client):
    s = make_set()
    s.root.mkdir(parents=True)
    first, second, third, fourth = s.names[:4]
    (s.root / first).write_bytes(s.parts[first])
    (s.root / second).write_bytes(s.parts[second])
    (s.root / f"{third}.part").write_bytes(s.parts[third][:1234])
    (s.root / f"{fourth}.part").write_bytes(s.parts[fourth])  # stopped after its last byte, before the rename
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST, keep_archive=True)
    assert s.server.requests(first) == s.server.requests(second) == s.server.requests(fourth) == 0
    assert [r.range_start for r in s.server.served if r.name == third] == [1234]
    assert s.server.bytes_served() == len(s.archive) - 3 * PART_BYTES - 1234
    assert md5_of([s.root / n for n in s.names]) == hashlib.md5(s.archive).hexdigest()  # kept, and whole


def test_a_server_ignoring_range_restarts_the_part(make_set, client):
    s = make_set()
    s.root.mkdir(parents=True)
    first = s.names[0]
    (s.root / f"{first}.part").write_bytes(s.parts[first][:2000])
    s.server.ignore_range[first] = 1  # answers 200 with the whole part
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert [(r.range_start, r.status) for r in s.server.served if r.name == first] == [(2000, 200)]
    assert s.server.bytes_served() == len(s.archive)  # the part once, in full; not appended to the stale bytes
    assert tree(s.root / "extracted") == expected_tree(published_members())


def test_server_errors_and_rate_limits_are_retried(make_set, client):
    s = make_set()
    s.server.fail[s.names[0]] = [500, 429]
    s.server.fail[s.names[-1]] = [503]
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests(s.names[0]) == 3 and s.server.requests(s.names[-1]) == 2
    assert (s.root / "complete.json").is_file()


def test_retries_are_bounded(make_set, client):
    s = make_set()
    s.server.always_fail = 500
    start = time.monotonic()
    with pytest.raises(DownloadError, match=r"HTTP 500; gave up after 3 requests"):
        download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests() == FAST.retries + 1  # the first part, then it stops
    assert time.monotonic() - start < 2


def test_a_missing_file_is_not_retried(make_set, client, tmp_path):
    s = make_set()
    config = tmp_path / "moved"
    write_description(config, "test-eval-v0.1", name="test-eval", version="0.1", archive="test-eval-v0.1.tar.gz",
                      data=s.archive, md5=hashlib.md5(s.archive).hexdigest(), part_bytes=PART_BYTES,
                      url=s.server.url_template.replace("{part}", "old-{part}"))
    desc = load_dataset("test-eval", [config])
    with pytest.raises(DownloadError, match=f"old-{s.names[0]}/content\\): HTTP 404; check the URL in {desc.source}"):
        download_dataset(desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests() == 1


def test_progress_resets_the_retry_count_but_requests_stay_bounded(make_set, client):
    s = make_set()
    first = s.names[0]
    s.server.cut[first] = [100] * 100  # every answer brings 100 bytes, then the connection drops
    with pytest.raises(DownloadError, match="gave up after 10 requests"):
        download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests() == FAST.max_requests_per_part
    assert (s.root / f"{first}.part").stat().st_size == 100 * FAST.max_requests_per_part


@pytest.mark.parametrize("every_s, limits", [
    (0.05, {"min_bytes_per_s": 10_000.0, "throughput_window_s": 0.3}),  # 320 bytes/s: below the floor
    (0.6, {"read_timeout_s": 0.2}),  # silent for longer than the read timeout
])
def test_a_trickling_server_is_dropped_and_the_part_resumed(make_set, client, every_s, limits):
    s = make_set()
    first = s.names[0]
    s.server.trickle[first] = 1  # 16 bytes at a time, every_s apart
    s.server.trickle_every_s = every_s
    slow = TransferSettings(**{**FAST.__dict__, **limits})
    start = time.monotonic()
    download_dataset(s.desc, s.data, progress=False, client=client, settings=slow)
    assert time.monotonic() - start < 5
    asked = [r.range_start for r in s.server.served if r.name == first]
    assert len(asked) == 2 and asked[0] is None and 0 < asked[1] < PART_BYTES
    assert tree(s.root / "extracted") == expected_tree(published_members())


def test_a_wrong_md5_is_refused_and_nothing_is_deleted(make_set, client):
    s = make_set(md5="0" * 32)
    with pytest.raises(ChecksumError) as err:
        download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    message = str(err.value)
    assert "test-eval-v0.1.tar.gz" in message and "0" * 32 in message
    assert hashlib.md5(s.archive).hexdigest() in message and str(s.root) in message
    assert all((s.root / n).stat().st_size == len(s.parts[n]) for n in s.names)
    assert not (s.root / "extracted").exists() and not (s.root / "extracted.tmp").exists()
    assert not (s.root / "complete.json").exists()
    # verify=False skips the check (and records that it did)
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST, verify=False)
    assert json.loads((s.root / "complete.json").read_text())["md5_verified"] is False


@pytest.mark.parametrize("bad, fields, what", [
    ("../evil.txt", {}, "'..'"),
    ("rigidbench-eval-v1.1/../../evil.txt", {}, "'..'"),
    ("/tmp/evil.txt", {}, "absolute"),
    ("rigidbench-eval-v1.1/link", {"type": tarfile.SYMTYPE, "linkname": "/etc/passwd"}, "symbolic link"),
    ("rigidbench-eval-v1.1/hard", {"type": tarfile.LNKTYPE, "linkname": "rigidbench-eval-v1.1/ok.bin"}, "hard link"),
    ("rigidbench-eval-v1.1/fifo", {"type": tarfile.FIFOTYPE}, "device or FIFO"),
    ("rigidbench-eval-v1.1/null", {"type": tarfile.CHRTYPE, "devmajor": 1, "devminor": 3}, "device or FIFO"),
])
def test_unsafe_members_abort_the_extraction_and_leave_nothing(make_set, client, tmp_path, bad, fields, what):
    rng = random.Random(3)
    content = None if fields.get("type") in (tarfile.SYMTYPE, tarfile.LNKTYPE, tarfile.FIFOTYPE, tarfile.CHRTYPE) \
        else b"evil"
    members = [("rigidbench-eval-v1.1/ok.bin", rng.randbytes(6000), {}), (bad, content, fields),
               ("rigidbench-eval-v1.1/after.bin", rng.randbytes(3000), {})]
    if content is None:
        members[1] = (bad, None, fields)
    s = make_set(members)
    with tarfile.open(fileobj=__import__("io").BytesIO(s.archive)) as tar:
        assert bad in tar.getnames()  # the archive really holds the unsafe name
    with pytest.raises(UnsafeMemberError) as err:
        download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert f"member '{bad}'" in str(err.value) and what in str(err.value)
    assert not (s.root / "extracted").exists() and not (s.root / "extracted.tmp").exists()
    assert not (s.root / "complete.json").exists()
    assert not list(tmp_path.rglob("evil.txt")) and not Path("/tmp/evil.txt").exists()


def test_too_little_free_disk_is_refused_before_any_request(make_set, client, monkeypatch):
    s = make_set()
    s.root.mkdir(parents=True)
    (s.root / s.names[0]).write_bytes(s.parts[s.names[0]])  # one part already here
    margin = int(0.02 * len(s.archive))
    need = (len(s.archive) - PART_BYTES) + len(s.archive) + margin  # the rest, the extraction, the margin
    real = shutil.disk_usage

    def disk_usage(free):
        return lambda path: real(path)._replace(free=free)

    monkeypatch.setattr(shutil, "disk_usage", disk_usage(need - 1))
    with pytest.raises(DiskSpaceError) as err:
        download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    message = str(err.value)
    assert str(s.data) in message and "--data" in message and "free" in message
    assert f"{(len(s.archive) - PART_BYTES) / 1000:.1f} kB still to download" in message
    assert s.server.requests() == 0
    monkeypatch.setattr(shutil, "disk_usage", disk_usage(need))
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert (s.root / "complete.json").is_file()


def test_all_parts_on_disk_verify_and_extract_without_a_request(make_set, client):
    """A run stopped after the last part (e.g. during the MD5) finishes offline."""
    s = make_set()
    s.root.mkdir(parents=True)
    for name, data in s.parts.items():
        (s.root / name).write_bytes(data)
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests() == 0
    assert tree(s.root / "extracted") == expected_tree(published_members())


def test_a_run_stopped_during_extraction_finishes_without_fetching_or_rehashing(make_set, client, monkeypatch):
    s = make_set()
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST, keep_archive=True)
    assert (s.root / "verified.json").is_file()
    # as if it had stopped half-way through extracting: no marker, a partial extracted.tmp
    (s.root / "complete.json").unlink()
    os.replace(s.root / "extracted", s.root / "extracted.tmp")
    (s.root / "extracted.tmp" / "half-written.bin").write_bytes(b"x")
    requests = s.server.requests()
    monkeypatch.setattr(dl.hashlib, "md5", lambda *a, **k: pytest.fail("the MD5 was computed again"))
    out = download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests() == requests
    assert tree(out) == expected_tree(published_members()) and not (s.root / "extracted.tmp").exists()
    assert json.loads((s.root / "complete.json").read_text())["md5_verified"] is True
    assert not (s.root / s.names[0]).exists()  # keep_archive=False this time: parts deleted


def test_a_run_stopped_before_the_marker_or_during_the_deletion_finishes_offline(make_set, client):
    s = make_set()
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST, keep_archive=True)
    assert all((s.root / n).exists() for n in s.names)  # kept
    (s.root / "complete.json").unlink()  # stopped after the extraction's rename, before the marker
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert (s.root / "complete.json").is_file() and not any((s.root / n).exists() for n in s.names)
    # stopped while deleting the parts: the marker says they go, a rerun removes the rest
    (s.root / s.names[-1]).write_bytes(s.parts[s.names[-1]])
    requests = s.server.requests()
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert not (s.root / s.names[-1]).exists() and s.server.requests() == requests


def test_a_second_run_on_the_same_folder_is_refused(make_set, client):
    s = make_set()
    s.root.mkdir(parents=True)
    with dl._lock(s.root):
        with pytest.raises(DownloadBusyError, match="another run"):
            download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests() == 0


def test_concatenated_files_read_across_part_boundaries(tmp_path):
    data = random.Random(1).randbytes(10_000)
    paths = []
    for i, chunk in enumerate((data[:3], data[3:3], data[3:7000], data[7000:])):  # an empty part too
        paths.append(tmp_path / f"p{i}")
        paths[-1].write_bytes(chunk)
    seen = []
    with ConcatenatedFiles(paths, seen.append) as stream:
        assert stream.read() == data
    assert sum(seen) == len(data)
    assert md5_of(paths) == hashlib.md5(data).hexdigest()


def test_listed_parts_with_their_own_md5_name_the_damaged_part(make_set, client, tmp_path):
    import yaml

    s = make_set()
    config = tmp_path / "listed"
    (config / "datasets").mkdir(parents=True)
    parts = [{"name": n, "size_bytes": len(b), "md5": hashlib.md5(b).hexdigest()} for n, b in s.parts.items()]
    doc = {"name": "listed", "version": "2", "archive": "test-eval-v0.1.tar.gz", "size_bytes": len(s.archive),
           "md5": hashlib.md5(s.archive).hexdigest(), "parts": parts, "url": s.server.url_template,
           "licence": "CC BY 4.0"}
    (config / "datasets" / "listed-v2.yaml").write_text(yaml.safe_dump(doc))
    desc = load_dataset("listed", [config])
    assert [p.size_bytes for p in desc.parts] == [len(b) for b in s.parts.values()]
    root = download_dir(desc, s.data)
    root.mkdir(parents=True)
    damaged = s.names[1]
    for name, data in s.parts.items():  # all on disk, one with a flipped byte
        (root / name).write_bytes(data if name != damaged else bytes([data[0] ^ 1]) + data[1:])
    with pytest.raises(ChecksumError, match=f"the parts {damaged} do not match their own MD5"):
        download_dataset(desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests() == 0 and (root / damaged).exists()
    (root / damaged).unlink()  # as the message says: delete it and run again
    download_dataset(desc, s.data, progress=False, client=client, settings=FAST)
    assert s.server.requests() == s.server.requests(damaged) == 1
    assert tree(root / "extracted") == expected_tree(published_members())


# -- issue 32 ----------------------------------------------------------------------------------------


def test_the_disk_check_counts_what_the_import_writes(make_set, client, monkeypatch):
    """The import's own files (up to the archive's size: depth, masks, tracks) land in the space the deleted
    parts free; with --keep-archive they need room of their own, and the check says so before any request."""
    s = make_set()
    margin = int(0.02 * len(s.archive))
    extraction_peak = len(s.archive) + len(s.archive) + margin  # every part, the extraction, the margin
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda path: real(path)._replace(free=extraction_peak))
    with pytest.raises(DiskSpaceError) as err:
        download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST, keep_archive=True)
    message = str(err.value)
    assert f"{len(s.archive) / 1000:.1f} kB more to import" in message and "beside the kept parts" in message
    assert s.server.requests() == 0
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)  # the parts go before the import
    assert (s.root / "complete.json").is_file()


def test_deleting_the_extraction_never_fetches_the_archive_again(make_set, client):
    s = make_set()
    download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    shutil.rmtree(s.root / "extracted")
    before = s.server.requests()
    with pytest.raises(dl.ExtractionDeletedError) as err:
        download_dataset(s.desc, s.data, progress=False, client=client, settings=FAST)
    assert str(s.root / "complete.json") in str(err.value) and s.server.requests() == before
    # parts kept: extracted again from them, offline
    k = make_set()
    download_dataset(k.desc, k.data, progress=False, client=client, settings=FAST, keep_archive=True)
    shutil.rmtree(k.root / "extracted")
    before = k.server.requests()
    out = download_dataset(k.desc, k.data, progress=False, client=client, settings=FAST, keep_archive=True)
    assert tree(out) == expected_tree(published_members()) and k.server.requests() == before


def test_data_naming_a_file_is_a_clear_error(make_set, client, tmp_path):
    from rigidbench.errors import UserError

    s = make_set()
    (tmp_path / "afile").write_text("x")
    with pytest.raises(UserError, match="a file, not a folder"):
        download_dataset(s.desc, tmp_path / "afile", progress=False, client=client, settings=FAST)
    assert s.server.requests() == 0


def test_a_download_into_data_another_run_imports_into_is_refused(make_set, tmp_path, capsys):
    import fcntl

    from rigidbench.cli import main
    from rigidbench.datasets.datadir import LOCK_FILE

    s = make_set()
    s.data.mkdir()
    config = Path(s.desc.source).parent.parent
    with open(s.data / LOCK_FILE, "a") as running:
        fcntl.flock(running.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert main(["--config", str(config), "download", "--data", str(s.data), "--dataset", "test-eval"]) == 2
    err = capsys.readouterr().err
    assert "another rigidbench download or import" in err and len(err.strip().splitlines()) == 1
    assert s.server.requests() == 0
