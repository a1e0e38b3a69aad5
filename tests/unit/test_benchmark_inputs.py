import json
from pathlib import Path

import numpy as np
import pytest

import rigidbench
from rigidbench.benchmark import (NEGATIVE_PROMPT, PROMPT_SUFFIX, PROTOCOL, PublishedLayoutError,
                                  find_published_layout, write_inputs)
from rigidbench.cli import main
from rigidbench.errors import BundleError


def _fake_split(root, n=3):
    for i in range(n):
        d = root / f"{i:05d}"
        (d / "frames").mkdir(parents=True)
        (d / "frames" / "00000.png").write_bytes(b"\x89PNG")
        (d / "metadata.json").write_text(json.dumps({"task": "free_fall", "partition": "ood_scene",
                                                     "prompt": f"An apple number {i} is dropping."}))
    (root / "00099.tmp").mkdir()  # an unfinished render is ignored
    return root


def test_benchmark_iterates_examples_with_full_prompts(tmp_path):
    bench = rigidbench.Benchmark.load(_fake_split(tmp_path / "eval"))
    assert [e.id for e in bench] == ["00000", "00001", "00002"]
    ex = bench["00001"]
    assert ex.prompt == "An apple number 1 is dropping. " + PROMPT_SUFFIX
    assert ex.prompt.endswith("Motion begins on the first frame.")
    assert ex.negative_prompt == NEGATIVE_PROMPT and ex.negative_prompt.startswith("camera motion, camera shake")
    assert ex.image == tmp_path / "eval" / "00001" / "frames" / "00000.png" and ex.task == "free_fall"


def test_inputs_jsonl_via_cli(tmp_path):
    data = _fake_split(tmp_path / "eval")
    assert main(["inputs", "--data", str(data)]) == 0
    lines = [json.loads(line) for line in (tmp_path / "inputs.jsonl").read_text().splitlines()]  # beside eval/
    assert len(lines) == 3 and lines[2]["id"] == "00002" and lines[2]["partition"] == "ood_scene"
    assert set(lines[0]) >= {"id", "image", "prompt", "negative_prompt", "task", "partition"}
    # the same rows wherever the file goes; only `image` is relative to the file's own folder
    other = [json.loads(line) for line in write_inputs(data, data / "x.jsonl").read_text().splitlines()]
    assert [r["image"] for r in lines] == [f"eval/{i:05d}/frames/00000.png" for i in range(3)]
    assert [r["image"] for r in other] == [f"{i:05d}/frames/00000.png" for i in range(3)]
    assert [{**r, "image": None} for r in other] == [{**r, "image": None} for r in lines]


def test_missing_data_dir_is_a_clear_error(tmp_path, capsys):
    assert main(["inputs", "--data", str(tmp_path / "nowhere")]) == 2
    assert "data directory does not exist" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError):
        rigidbench.Benchmark.load(tmp_path / "nowhere")


# -- the release's keys, image paths relative to the file, imported bundles, the published layout ----------


RELEASE_KEYS = {"id", "image", "scene_prompt", "prompt", "negative_prompt", "duration_seconds", "reference_fps",
                "reference_frames", "reference_resolution", "task", "protocol"}
OUR_KEYS = {"id", "image", "prompt", "negative_prompt", "task", "partition", "task_prompt"}


def _png(path, width, height, seed):
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(path)


def _bundle(split_dir, sample_id, *, source=None, size=(64, 36), prompt_in_metadata=True):
    """A bundle as our renders (or, with ``source``, `rigidbench import`) write it: a real first frame."""
    d = split_dir / sample_id
    _png(d / "frames" / "00000.png", *size, seed=int(sample_id))
    meta = {"bundle_version": 1, "sample_id": sample_id, "task": "bounce", "partition": "in_distribution",
            "fps": 24.0, "frames": 49, "resolution": list(size)}
    prompt = f"A baseball number {sample_id} drops onto the table."
    if prompt_in_metadata:
        meta["prompt"] = prompt
    (d / "prompt.txt").write_text(prompt + "\n")
    if source is not None:
        meta["source"] = source
    (d / "metadata.json").write_text(json.dumps(meta))
    return d


SOURCE = {"dataset": "rigidbench-eval", "version": "1.1", "md5": "b563f279451e95fe2f32d7e258588636",
          "original_metadata": {"task_type": "bounce", "split": "in-distribution"}}


@pytest.fixture()
def data_root(tmp_path):
    root = tmp_path / "data"
    _bundle(root / "eval", "00000")
    _bundle(root / "eval", "00001", source=SOURCE)  # an imported bundle beside a render
    _bundle(root / "eval", "00002", source=SOURCE, prompt_in_metadata=False)  # prompt from prompt.txt
    return root


def read_like_the_release(jsonl):
    """What a generation script written for the authors' release does with inputs.jsonl: image paths are
    relative to the file's folder; it needs id, image, prompt, negative_prompt, duration_seconds, reference_fps."""
    from PIL import Image

    jobs = []
    for line in Path(jsonl).read_text().splitlines():
        row = json.loads(line)
        image = Path(jsonl).parent / row["image"]
        with Image.open(image) as im:
            im.load()
            size = im.size
        n_frames = round(row["duration_seconds"] * row["reference_fps"]) + 1
        jobs.append((row["id"], size, row["prompt"], row["negative_prompt"], n_frames))
    return jobs


def test_inputs_carry_the_release_keys_beside_ours(data_root):
    out = write_inputs(data_root)  # a data root: the file goes to data/inputs.jsonl, as the release writes it
    assert out == data_root / "inputs.jsonl"
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["id"] for r in rows] == ["00000", "00001", "00002"]
    for r in rows:
        assert set(r) == RELEASE_KEYS | OUR_KEYS
        assert r["image"] == f"eval/{r['id']}/frames/00000.png"  # POSIX, relative to data/
        assert r["scene_prompt"] == r["task_prompt"] == f"A baseball number {r['id']} drops onto the table."
        assert r["prompt"] == r["scene_prompt"] + " " + PROMPT_SUFFIX
        assert r["negative_prompt"] == NEGATIVE_PROMPT
        assert r["duration_seconds"] == 2.0 and r["reference_fps"] == 24 and isinstance(r["reference_fps"], int)
        assert r["reference_frames"] == 49 and r["reference_resolution"] == [64, 36]
        assert r["task"] == "bounce" and r["partition"] == "in_distribution"
        assert r["protocol"] == PROTOCOL == "rigidbench-v1"


def test_a_release_generation_script_runs_unchanged(data_root, tmp_path, monkeypatch):
    out = write_inputs(data_root)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # paths resolve against the file's folder, not the working directory
    jobs = read_like_the_release(out)
    assert [j[0] for j in jobs] == ["00000", "00001", "00002"]
    assert all(size == (64, 36) and n == 49 and p.endswith("Motion begins on the first frame.")
               for _, size, p, _, n in jobs)
    # the same through the command line, given the split directory: the same file, data/inputs.jsonl
    out.unlink()
    assert main(["inputs", "--data", str(data_root / "eval")]) == 0
    assert len(read_like_the_release(out)) == 3
    assert json.loads(out.read_text().splitlines()[0])["image"] == "eval/00000/frames/00000.png"
    assert not (data_root / "eval" / "inputs.jsonl").exists()


def test_a_linked_first_frame_keeps_its_bundle_path(data_root, tmp_path):
    # `rigidbench import` may link frames into the extracted archive instead of copying them
    frame = data_root / "eval" / "00001" / "frames" / "00000.png"
    archive_copy = tmp_path / "extracted" / "samples" / "00001" / "frames" / "00000.png"
    archive_copy.parent.mkdir(parents=True)
    frame.rename(archive_copy)
    frame.symlink_to(archive_copy)
    rows = [json.loads(line) for line in write_inputs(data_root).read_text().splitlines()]
    assert rows[1]["image"] == "eval/00001/frames/00000.png"
    assert len(read_like_the_release(data_root / "inputs.jsonl")) == 3


def test_image_is_absolute_only_when_not_below_the_file(data_root, tmp_path):
    out = write_inputs(data_root / "eval", tmp_path / "runs" / "inputs.jsonl")  # a folder that does not exist yet
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    for r in rows:
        image = Path(r["image"])
        assert image.is_absolute() and image == (data_root / "eval" / r["id"] / "frames" / "00000.png").absolute()
    assert len(read_like_the_release(out)) == 3


def test_inputs_are_replaced_atomically(data_root, monkeypatch):
    out = data_root / "inputs.jsonl"
    out.write_text("previous\n")

    def fail(self, target):
        raise OSError("disk full")

    monkeypatch.setattr(Path, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_inputs(data_root)
    monkeypatch.undo()
    assert out.read_text() == "previous\n"
    assert sorted(p.name for p in data_root.iterdir()) == ["eval", "inputs.jsonl"]  # no temporary left behind
    write_inputs(data_root)
    assert len(out.read_text().splitlines()) == 3
    assert sorted(p.name for p in data_root.iterdir()) == ["eval", "inputs.jsonl"]


def test_load_takes_a_data_root_or_a_split_directory(data_root):
    by_root, by_split = rigidbench.Benchmark.load(data_root), rigidbench.Benchmark.load(data_root / "eval")
    assert by_root.root == by_split.root == data_root / "eval"
    assert [e.to_dict() for e in by_root] == [e.to_dict() for e in by_split]
    ex = by_root["00001"]  # the imported one
    assert ex.image == data_root / "eval" / "00001" / "frames" / "00000.png"
    assert (ex.scene_prompt, ex.duration_seconds, ex.reference_fps, ex.reference_frames, ex.reference_resolution,
            ex.protocol) == (ex.task_prompt, 2.0, 24.0, 49, (64, 36), PROTOCOL)
    assert by_root["00002"].scene_prompt == "A baseball number 00002 drops onto the table."  # from prompt.txt


def test_reference_facts_follow_the_metadata(tmp_path):
    d = _bundle(tmp_path / "eval", "00007", size=(96, 64))
    meta = json.loads((d / "metadata.json").read_text())
    (d / "metadata.json").write_text(json.dumps({**meta, "fps": 16, "frames": 33}))
    row = rigidbench.Benchmark.load(tmp_path)["00007"].to_dict()
    assert (row["duration_seconds"], row["reference_fps"], row["reference_frames"], row["reference_resolution"]) == \
        (2.0, 16, 33, [96, 64])


def _published_sample(folder, sample_id):
    """A sample folder as the authors published it: metadata.json with task_type and no sample_id."""
    d = folder / sample_id
    _png(d / "frames" / "00000.png", 64, 36, seed=1)
    (d / "metadata.json").write_text(json.dumps({"task_type": "bounce", "scene_id": "loft", "split": "in-distribution",
                                                 "seed": 3, "render": {"fps": 24, "resolution": [64, 36]}}))
    (d / "prompt.txt").write_text("A ball drops.\n")


def _published_roots(tmp_path):
    manifest = tmp_path / "pub_manifest"
    _published_sample(manifest / "samples", "00000")
    (manifest / "manifest.json").write_text(json.dumps([{"sample_id": "00000", "task_type": "bounce"}]))
    eval_layout = tmp_path / "pub_eval"
    _published_sample(eval_layout / "eval", "00000")
    archive_top = tmp_path / "extracted"
    _published_sample(archive_top / "rigidbench-eval-v1.1" / "samples", "00000")
    (archive_top / "rigidbench-eval-v1.1" / "manifest.json").write_text("[]")
    return [manifest, manifest / "samples", eval_layout, eval_layout / "eval", archive_top]


def test_the_published_layout_is_refused_with_the_import_command(tmp_path, capsys):
    for folder in _published_roots(tmp_path):
        with pytest.raises(PublishedLayoutError) as caught:
            rigidbench.Benchmark.load(folder)
        assert isinstance(caught.value, BundleError)
        assert "rigidbench import" in str(caught.value) and "--data DIR" in str(caught.value)
        assert find_published_layout(folder) is not None
        assert main(["inputs", "--data", str(folder)]) == 2
        err = capsys.readouterr().err
        assert "rigidbench import" in err and "Traceback" not in err and "KeyError" not in err
        assert not (folder / "inputs.jsonl").exists()


def test_our_bundles_are_not_mistaken_for_the_published_layout(data_root):
    assert find_published_layout(data_root) is None and find_published_layout(data_root / "eval") is None
    # the archive extracted by hand beside the bundles imported from it does not hide them
    _published_sample(data_root / "rigidbench-eval-v1.1" / "samples", "00000")
    (data_root / "rigidbench-eval-v1.1" / "manifest.json").write_text("[]")
    assert find_published_layout(data_root) is None
    assert [e.id for e in rigidbench.Benchmark.load(data_root)] == ["00000", "00001", "00002"]
    assert main(["inputs", "--data", str(data_root)]) == 0
    # a published sample folder slipped in among ours is refused by name, not read with the wrong keys
    _published_sample(data_root / "eval", "00005")
    with pytest.raises(PublishedLayoutError, match="rigidbench import"):
        rigidbench.Benchmark.load(data_root)


# -- one place for inputs.jsonl; the release's indexing and names ------------------------------------------------


def test_inputs_go_to_one_place_whichever_data_is_named(data_root, capsys):
    from rigidbench.folders import inputs_path
    from rigidbench.firstframe import mismatch_message
    from rigidbench.groundtruth.bundle import resolve_split_dir

    expected = data_root / "inputs.jsonl"  # beside eval/, where download and import write it (the release's place)
    for data in (data_root, data_root / "eval"):
        expected.unlink(missing_ok=True)
        assert main(["inputs", "--data", str(data)]) == 0
        assert capsys.readouterr().out.strip() == f"wrote {expected}"
        assert len(read_like_the_release(expected)) == 3 and not (data_root / "eval" / "inputs.jsonl").exists()
        assert write_inputs(data) == expected == inputs_path(resolve_split_dir(data))
        # the first-frame error validate and evaluate give (they hold the split directory) names that file
        message = mismatch_message(Path("p/00000.mp4"), "00000", resolve_split_dir(data), None, 0.1)
        assert f"writes {expected})" in message
    # a split directory of another name keeps its own file: train inputs never overwrite the evaluation's
    _bundle(data_root / "train", "00005")
    assert main(["inputs", "--data", str(data_root), "--split", "train"]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {data_root / 'train' / 'inputs.jsonl'}"
    assert [json.loads(line)["id"] for line in expected.read_text().splitlines()] == ["00000", "00001", "00002"]
    assert inputs_path(Path("bundles")) == Path("bundles/inputs.jsonl")


def test_the_readme_names_the_same_place():
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert "data/inputs.jsonl" in readme and "eval/inputs.jsonl" not in readme


def test_examples_are_indexed_by_position_as_in_the_release_and_by_id(data_root):
    bench = rigidbench.Benchmark.load(data_root)
    ids = ["00000", "00001", "00002"]
    assert [bench[i].id for i in range(len(bench))] == ids == [e.id for e in bench]
    assert bench[-1].id == "00002" and bench[np.int64(1)] is bench["00001"] is bench[1]
    assert [e.id for e in bench[1:]] == ids[1:]
    with pytest.raises(IndexError, match="has 3 examples"):
        bench[3]
    with pytest.raises(KeyError, match="00009"):
        bench["00009"]
    with pytest.raises(TypeError):
        bench[1.0]


def test_the_release_names_are_exported(data_root, tmp_path):
    from rigidbench import Benchmark, BenchmarkExample, export_inputs_jsonl  # the release's __all__

    example = Benchmark.load(data_root)[0]
    assert isinstance(example, BenchmarkExample) and BenchmarkExample is rigidbench.Example
    assert all(hasattr(example, key) for key in RELEASE_KEYS)
    assert {"Benchmark", "BenchmarkExample", "export_inputs_jsonl", "write_inputs"} <= set(rigidbench.__all__)
    positional = export_inputs_jsonl(data_root, tmp_path / "a.jsonl")
    keyword = export_inputs_jsonl(data_root / "eval", output=tmp_path / "b.jsonl")
    assert positional.read_text() == keyword.read_text() == write_inputs(data_root, tmp_path / "c.jsonl").read_text()
    assert export_inputs_jsonl(data_root) == data_root / "inputs.jsonl"
