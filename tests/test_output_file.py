"""Output files: checked before the work that fills them, written whole or not at all, and every
failure one line naming the path the user gave (never the temporary name)."""

import os

import numpy as np
import pytest

from io_usd.cache import CacheWriter
from io_usd.output_file import check_output_folder, check_output_path, write_whole
from sim.errors import InputError


def test_a_writable_path_passes_and_leaves_nothing_behind(tmp_path):
    path = tmp_path / "new" / "deeper" / "out.png"
    assert check_output_path(path, (".png",)) == str(path)
    assert os.listdir(tmp_path) == []  # neither the probe nor the folders the writer will make


@pytest.mark.parametrize("name, reason", [("out.bmp", "the preview must end in .png or .gif, not .bmp"),
                                         ("out", "the preview must end in .png or .gif"),
                                         ("folder.png", "is a folder; name a file in it"),
                                         ("afile/out.png", "afile is not a folder"),
                                         ("afile/deeper/out.png", "afile is not a folder")])
def test_a_path_that_cannot_take_the_file_is_refused(tmp_path, name, reason):
    (tmp_path / "folder.png").mkdir()
    (tmp_path / "afile").write_text("")
    with pytest.raises(InputError, match=reason) as caught:
        check_output_path(tmp_path / name, (".png", ".gif"), "the preview")
    assert str(caught.value).startswith(str(tmp_path / name) + ": ")


def test_a_folder_that_takes_no_new_file_is_refused(tmp_path, monkeypatch):
    """As root every mode bit lets a file in, so the refusal is the file system's (a read-only mount, /sys)."""
    import tempfile

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(InputError, match=f"cannot write in {tmp_path}: Permission denied"):
        check_output_path(tmp_path / "a" / "out.usdc", (".usdc",), "the cache")
    with pytest.raises(InputError, match="cannot write in"):
        check_output_folder(tmp_path / "capture")


def test_an_output_folder_must_not_be_a_file(tmp_path):
    (tmp_path / "afile").write_text("")
    with pytest.raises(InputError, match="exists and is not a folder"):
        check_output_folder(tmp_path / "afile")
    assert check_output_folder(tmp_path / "capture") == str(tmp_path / "capture")


def test_a_failed_write_leaves_the_old_file_and_no_partial(tmp_path):
    path = tmp_path / "report.txt"
    path.write_text("old")

    def fails(tmp):
        with open(tmp, "w") as f:
            f.write("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(InputError, match="report.txt: cannot write it: No space left on device"):
        write_whole(path, fails)
    assert path.read_text() == "old" and os.listdir(tmp_path) == ["report.txt"]
    write_whole(path, lambda tmp: open(tmp, "w").write("new"))
    assert path.read_text() == "new" and os.listdir(tmp_path) == ["report.txt"]


def test_a_cache_whose_path_became_a_folder_during_the_run_leaves_no_partial(tmp_path):
    path = tmp_path / "cache.usdc"
    writer = CacheWriter(path, 24.0, 1, 1)
    writer.add_curves("hair", "hair", [3], np.full(3, 1e-4))
    writer.write_frame(1, {"hair": np.zeros((3, 3))})
    path.mkdir()  # what a user (or another program) may do while a long run goes on
    with pytest.raises(InputError, match="cache.usdc: is a folder"):
        writer.close()
    assert os.listdir(tmp_path) == ["cache.usdc"] and os.listdir(path) == []


def test_a_cache_written_without_a_version_records_the_engines(tmp_path):
    """SPEC: the root layer names the engine version, also for caches a host writes through the API."""
    from pxr import Sdf

    import sim

    path = tmp_path / "api.usdc"
    with CacheWriter(path, 24.0, 1, 1) as writer:
        writer.add_curves("hair", "hair", [3], np.full(3, 1e-4))
        writer.write_frame(1, {"hair": np.zeros((3, 3))})
    data = Sdf.Layer.FindOrOpen(str(path)).customLayerData
    assert data["cfx:engineVersion"] == sim.__version__ and data["cfx:complete"]
