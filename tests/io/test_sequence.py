"""Image sequences in natural order and ground-truth matrices in every format."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from robotd.base.errors import SequenceError
from robotd.io.sequence import list_images, load_ground_truth, natural_key, read_image


def test_natural_order():
    names = ["10.jpg", "2.jpg", "1.jpg", "img10b.png", "img9b.png", "img9a.png", "B.jpg", "a.jpg"]
    assert sorted(names, key=natural_key) == [
        "1.jpg", "2.jpg", "10.jpg", "a.jpg", "B.jpg", "img9a.png", "img9b.png", "img10b.png"]


def test_list_images_skips_other_files_and_the_ground_truth(tmp_path: Path):
    img = np.zeros((4, 4, 3), np.uint8)
    for name in ("10.jpg", "2.jpg", "1.JPG", "gt.bmp"):
        cv2.imwrite(str(tmp_path / name.lower()) if name != "1.JPG" else str(tmp_path / name), img)
    (tmp_path / "notes.txt").write_text("x")
    files = list_images(tmp_path, exclude=(tmp_path / "gt.bmp",))
    assert [p.name for p in files] == ["1.JPG", "2.jpg", "10.jpg"]


def test_missing_or_empty_folder_and_unreadable_image(tmp_path: Path):
    with pytest.raises(SequenceError, match="does not exist"):
        list_images(tmp_path / "nope")
    with pytest.raises(SequenceError, match="holds no images"):
        list_images(tmp_path)
    bad = tmp_path / "3.jpg"
    bad.write_bytes(b"not a jpeg")
    with pytest.raises(SequenceError, match="cannot read image .*3.jpg"):
        read_image(bad)


LOWER = np.zeros((5, 5), np.uint8)
LOWER[3, 0] = LOWER[4, 1] = 255
EXPECTED = (LOWER > 0) | (LOWER > 0).T


@pytest.mark.parametrize("triangle", ["lower", "upper"])
@pytest.mark.parametrize("fmt", [".npy", ".csv", ".txt", ".bmp", ".png"])
def test_ground_truth_every_format_either_triangle(tmp_path: Path, fmt: str, triangle: str):
    m = LOWER if triangle == "lower" else LOWER.T.copy()
    path = tmp_path / f"gt{fmt}"
    if fmt == ".npy":
        np.save(path, m.astype(np.float32) / 255)
    elif fmt == ".csv":
        np.savetxt(path, m // 255, fmt="%d", delimiter=",")
    elif fmt == ".txt":
        np.savetxt(path, m // 255, fmt="%d")
    else:
        assert cv2.imwrite(str(path), m)
    truth = load_ground_truth(path, 5)
    assert truth.dtype == bool and np.array_equal(truth, EXPECTED)


def test_ground_truth_diagonal_is_cleared(tmp_path: Path):
    path = tmp_path / "gt.npy"
    np.save(path, np.eye(3))
    assert not load_ground_truth(path).any()


def test_ground_truth_errors(tmp_path: Path):
    with pytest.raises(SequenceError, match="does not exist"):
        load_ground_truth(tmp_path / "none.npy")
    np.save(tmp_path / "gt.npy", np.zeros((4, 4)))
    with pytest.raises(SequenceError, match="is 4x4 but the sequence has 5 images"):
        load_ground_truth(tmp_path / "gt.npy", 5)
    np.save(tmp_path / "rect.npy", np.zeros((4, 3)))
    with pytest.raises(SequenceError, match="not a square matrix"):
        load_ground_truth(tmp_path / "rect.npy")
    (tmp_path / "gt.csv").write_text("1,0\n0,x\n")
    with pytest.raises(SequenceError, match="cannot read ground-truth file"):
        load_ground_truth(tmp_path / "gt.csv")
    (tmp_path / "gt.json").write_text("[]")
    with pytest.raises(SequenceError, match="unknown format"):
        load_ground_truth(tmp_path / "gt.json")
    (tmp_path / "gt.png").write_bytes(b"garbage")
    with pytest.raises(SequenceError, match="cannot read ground-truth image"):
        load_ground_truth(tmp_path / "gt.png")


def test_ground_truth_from_a_matlab_file_as_the_public_datasets_publish_it(tmp_path: Path):
    """A .mat file (Lip6, NewCollege, CityCentre): the square numeric variable, dense or
    sparse, beside other variables; a file without one is a clear error."""
    from scipy import io as sio
    from scipy import sparse

    m = np.zeros((6, 6))
    m[4, 1] = m[5, 2] = 1
    sio.savemat(tmp_path / "gt.mat", {"truth": m, "names": np.array([[1.0, 2.0, 3.0]])})
    t = load_ground_truth(tmp_path / "gt.mat", 6)
    assert t[4, 1] and t[1, 4] and t[5, 2] and int(t.sum()) == 4
    sio.savemat(tmp_path / "sparse.mat", {"GroundTruth": sparse.csr_matrix(m)})
    assert np.array_equal(load_ground_truth(tmp_path / "sparse.mat"), t)
    sio.savemat(tmp_path / "none.mat", {"row": np.ones((1, 6))})
    with pytest.raises(SequenceError, match="no square numeric matrix"):
        load_ground_truth(tmp_path / "none.mat")
