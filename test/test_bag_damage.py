"""A truncated or damaged bag is one clear line naming the file and what is wrong (no Python repr, no
traceback), whatever its format and wherever the damage is found (opening or reading)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from test_bag_io import write_sample_bag

from localization.bags import BagError, open_bag
from localization.bags.reader import describe_error
from localization.tools import replay


def _read_all(path) -> int:
    with open_bag(path) as bag:
        return sum(1 for m in bag.messages() if m.msg is not None)


def _assert_clear(message: str, path) -> None:
    assert str(path) in message and "truncated or damaged" in message
    assert "('" not in message and "',)" not in message and "\n" not in message


def _truncated_copy(src: Path, dst: Path, share: float) -> Path:
    dst.write_bytes(src.read_bytes()[: int(src.stat().st_size * share)])
    return dst


@pytest.mark.parametrize("share", [0.01, 0.5, 0.99])
def test_truncated_ros1_bag_says_so_in_one_sentence(shared_dir, tmp_path, share):
    bag = _truncated_copy(shared_dir / "bags/rss2022/localization_bag3.bag", tmp_path / "cut.bag", share)
    with pytest.raises(BagError) as exc:
        _read_all(bag)
    _assert_clear(str(exc.value), bag)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("share", [0.3, 0.95])
def test_truncated_rosbag2_storage_is_a_bag_error(tmp_path, storage, share):
    whole = tmp_path / "whole"
    write_sample_bag(whole, storage)
    cut = tmp_path / "cut"
    shutil.copytree(whole, cut)
    data = next(f for f in cut.iterdir() if f.suffix in (".db3", ".mcap"))
    _truncated_copy(next(whole.glob(f"*{data.suffix}")), data, share)
    for target in (cut, data):  # the folder and the bare storage file
        with pytest.raises(BagError) as exc:  # never apsw's or struct's own exception
            _read_all(target)
        _assert_clear(str(exc.value), target)


def test_describe_error_unwraps_nested_arguments():
    inner = ValueError("Header could not be read from file.")
    outer = RuntimeError(f"Bag index looks damaged: {inner.args}")
    text = describe_error(outer)
    assert text.startswith("the file is truncated or damaged")
    assert "Header could not be read from file" in text and "('" not in text
    assert describe_error(KeyError("x")) == "x" and describe_error(OSError()) == "OSError"


def test_replay_of_a_truncated_bag_is_one_error_line(shared_dir, tmp_path, capsys):
    bag = _truncated_copy(shared_dir / "bags/rss2022/localization_bag3.bag", tmp_path / "cut.bag", 0.5)
    assert replay.main([str(bag), "--map", "basement_fixed", "--out", str(tmp_path / "out"), "--no-plots"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("localization-replay: error: cannot read bag")
    _assert_clear(err, bag)
