"""``robotd eval forward`` end to end on a small synthetic sequence, and its clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from robotd.app.cli import main


def _sequence(folder: Path, n: int = 16) -> np.ndarray:
    """``n`` 200x150 views sliding along a textured strip; the last four revisit the first
    four places. Returns the lower-triangle ground truth."""
    rng = np.random.default_rng(0)
    strip = cv2.GaussianBlur(rng.integers(0, 256, (150, 200 + 30 * n), dtype=np.uint8), (0, 0), 3.0)
    folder.mkdir()
    places = list(range(n - 4)) + [0, 1, 2, 3]
    for k, x in enumerate(places):
        cv2.imwrite(str(folder / f"{k + 1}.png"), strip[:, 30 * x:30 * x + 200])
    truth = np.zeros((n, n), np.uint8)
    for i in range(n):
        for j in range(i):
            if abs(places[i] - places[j]) <= 1 and i - j > 2:
                truth[i, j] = 1
    return truth


def test_eval_forward_prints_every_method_and_writes_json_and_plots(tmp_path: Path, capsys):
    truth = _sequence(tmp_path / "seq")
    np.save(tmp_path / "gt.npy", truth)
    out = tmp_path / "out"
    rc = main(["eval", "forward", "--images", str(tmp_path / "seq"), "--ground-truth",
               str(tmp_path / "gt.npy"), "--out", str(out), "--recent", "3", "--plot-image", "13"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "16 images, 4 of them revisit a place at least 3 images back" in text
    for method in ("detector", "best score", "best score + epipolar", "brute force"):
        assert f"\n{method} " in text
    report = json.loads((out / "forward_eval.json").read_text())
    assert report["n_images"] == 16 and len(report["per_image"]) == 16
    assert [r["image"] for r in report["per_image"]][:3] == ["1.png", "2.png", "3.png"]
    assert report["per_image"][9]["image"] == "10.png"  # natural order, not 1, 10, 11, ...
    assert report["methods"]["detector"]["positives"] == 4
    assert report["params"]["recent_excluded"] == 3
    assert report["params"]["verify"]["min_support_area"] == 0.03
    assert all("verification" in r for r in report["per_image"])
    for name in ("stage_times.png", "likelihood_posterior_13.png"):
        assert cv2.imread(str(out / name)) is not None


def test_eval_forward_errors_are_one_line(tmp_path: Path, capsys):
    truth = _sequence(tmp_path / "seq", n=8)
    np.save(tmp_path / "gt.npy", truth)
    args = ["eval", "forward", "--no-brute-force", "--images"]
    assert main(args + [str(tmp_path / "none"), "--ground-truth", str(tmp_path / "gt.npy")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("robotd: error: image folder") and "does not exist" in err
    assert err.count("\n") == 1 and "Traceback" not in err

    np.save(tmp_path / "small.npy", truth[:5, :5])
    assert main(args + [str(tmp_path / "seq"), "--ground-truth", str(tmp_path / "small.npy")]) == 2
    assert "is 5x5 but the sequence has 8 images" in capsys.readouterr().err

    assert main(args + [str(tmp_path / "seq"), "--ground-truth", str(tmp_path / "gt.npy"),
                        "--plot-image", "8"]) == 2
    assert "--plot-image 8 is outside the sequence (0..7)" in capsys.readouterr().err

    assert main(args + [str(tmp_path / "seq"), "--ground-truth", str(tmp_path / "gt.npy"),
                        "--min-support-area", "1.5"]) == 2
    err = capsys.readouterr().err
    assert "--min-support-area must be in [0, 1), got 1.5" in err and err.count("\n") == 1

    (tmp_path / "seq" / "5.png").write_bytes(b"\x89PNG broken")
    assert main(args + [str(tmp_path / "seq"), "--ground-truth", str(tmp_path / "gt.npy")]) == 2
    err = capsys.readouterr().err
    assert "cannot read image" in err and "5.png" in err


def test_eval_forward_method_tolerance_every_and_the_pr_curve(tmp_path: Path, capsys):
    truth = _sequence(tmp_path / "seq")
    np.save(tmp_path / "gt.npy", truth)
    out = tmp_path / "out"
    rc = main(["eval", "forward", "--images", str(tmp_path / "seq"), "--ground-truth", str(tmp_path / "gt.npy"),
               "--out", str(out), "--recent", "2", "--method", "paper", "--tolerance", "1", "--every", "2",
               "--no-brute-force"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "8 images" in text and "method paper (features sift" in text and "tolerance 1" in text
    report = json.loads((out / "forward_eval.json").read_text())
    assert report["n_images"] == 8 and report["per_image"][1]["image"] == "3.png"  # every 2nd image
    assert report["params"]["features"]["kind"] == "sift" and report["tolerance"] == 1
    pr = json.loads((out / "pr_curve.json").read_text())
    assert set(pr["curves"]) == {"detector (verified loops)", "best score"}
    c = pr["curves"]["best score"]
    assert len(c["threshold"]) == len(c["precision"]) == len(c["recall"])
    assert c["threshold"] == sorted(c["threshold"], reverse=True)
    assert cv2.imread(str(out / "pr_curve.png")) is not None
    assert main(["eval", "forward", "--images", str(tmp_path / "seq"), "--ground-truth",
                 str(tmp_path / "gt.npy"), "--every", "0"]) == 2
    assert "--every must be at least 1" in capsys.readouterr().err
