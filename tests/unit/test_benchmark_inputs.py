import json

import pytest

import rigidbench
from rigidbench.benchmark import NEGATIVE_PROMPT, PROMPT_SUFFIX, write_inputs
from rigidbench.cli import main


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
    lines = [json.loads(line) for line in (data / "inputs.jsonl").read_text().splitlines()]
    assert len(lines) == 3 and lines[2]["id"] == "00002" and lines[2]["partition"] == "ood_scene"
    assert set(lines[0]) >= {"id", "image", "prompt", "negative_prompt", "task", "partition"}
    assert write_inputs(data, tmp_path / "x.jsonl").read_text() == (data / "inputs.jsonl").read_text()


def test_missing_data_dir_is_a_clear_error(tmp_path, capsys):
    assert main(["inputs", "--data", str(tmp_path / "nowhere")]) == 2
    assert "data directory does not exist" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError):
        rigidbench.Benchmark.load(tmp_path / "nowhere")
