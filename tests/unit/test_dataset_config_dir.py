"""Where `rigidbench --config DIR download` looks for a dataset description: DIR/datasets/<id>.yaml, and an
"unknown dataset" error that says so (a file directly in DIR is not read). The download through such a
directory runs in tests/servers/test_no_secret_in_logs.py."""

from pathlib import Path

from rigidbench.cli import main
from rigidbench.config import PACKAGE_CONFIG_DIR
from rigidbench.datasets.describe import load_dataset

MIRROR = """name: mirror
version: "1.0"
archive: m.tar.gz
size_bytes: 10
md5: "0123456789abcdef0123456789abcdef"
parts: {count: 3, size_bytes: 4, name: "{archive}.{index}"}
url: "http://127.0.0.1:9/{part}"
licence: CC BY 4.0
"""


def test_a_description_directly_in_the_config_directory_is_named_with_where_it_belongs(tmp_path, capsys):
    config = tmp_path / "config"
    config.mkdir()
    stray = config / "mirror-v1.yaml"
    stray.write_text(MIRROR)
    assert main(["--config", str(config), "download", "--dataset", "mirror-v1", "--data", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    for part in ("unknown dataset 'mirror-v1'", f"looked for mirror-v1.yaml in {PACKAGE_CONFIG_DIR / 'datasets'}, "
                 f"{config.resolve() / 'datasets'} ", f"{stray.resolve()} is not read there: move it to "
                 f"{config.resolve() / 'datasets' / 'mirror-v1.yaml'}"):
        assert part in err, part
    assert not (tmp_path / "d" / ".download").exists()  # nothing fetched, nothing prepared for it
    # where the message says: found, under the id its file name gives
    (config / "datasets").mkdir()
    stray.rename(config / "datasets" / "mirror-v1.yaml")
    desc = load_dataset("mirror-v1", [config])
    assert (desc.id, desc.name, desc.version) == ("mirror-v1", "mirror", "1.0")
    assert load_dataset("mirror", [config]) == desc


def test_an_unknown_dataset_without_a_stray_file_names_the_folders_only(tmp_path, capsys):
    assert main(["--config", str(tmp_path), "download", "--dataset", "nothing-v9", "--data", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert f"looked for nothing-v9.yaml in {PACKAGE_CONFIG_DIR / 'datasets'}, {tmp_path.resolve() / 'datasets'} " in err
    assert "move it" not in err


def test_the_readme_gives_the_config_directory_layout():
    readme = " ".join((Path(__file__).resolve().parents[2] / "README.md").read_text().split())
    assert "`DIR/datasets/<id>.yaml`" in readme and "`rigidbench --config DIR download --dataset <id>`" in readme
