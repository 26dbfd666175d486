"""``bench/bench_forward_scale.py``'s page of the scale part: the windows' stage and CPU
columns, and the ratios written from them (the docs quote them)."""

from __future__ import annotations

from bench.bench_forward_scale import page


def _window(median: float, orb: float, cpu: float | None, orb_cpu: float | None, stages: bool = True) -> dict:
    w = {"median_ms": median, "p99_ms": 3 * median, "opencv_orb_median_ms": orb, "words_median_ms": median / 4,
         "verify_p99_ms": 2 * median}
    if cpu is not None:
        w.update(cpu_median_ms=cpu, opencv_orb_cpu_median_ms=orb_cpu)
    if stages:
        w["stages_median_ms"] = {"features": orb, "words": median / 4, "likelihood": 0.5, "filter": 0.25,
                                 "verify": 6.0, "memory": 0.0}
    return w


def _result(first: dict, last: dict) -> dict:
    sample = {"images": 10000, "rss_bytes": 2e9, "ram_bytes_per_image": 12000.0, "searchable_words": 55000,
              "ram_bytes_per_image_by_part": {"images": 10000.0, "index": 1500.0, "vocabulary": 500.0}}
    return {"machine": {"machine": "x86_64", "cpu_count": 2, "python": "3.11", "numpy": "2", "opencv": "5"},
            "command": "bench/bench_forward_scale.py --full", "sequences": {},
            "scale": {"images": 10000, "images_planned": 10000, "base_images": 1139, "loops": 1, "window": 200,
                      "at": {"1000": first, "10000": last}, "median_ratio_end_to_1000": last["median_ms"] / first["median_ms"],
                      "samples": [sample]}}


def test_the_scale_page_gives_the_wall_orb_and_cpu_ratios_and_the_stage_columns():
    text = "\n".join(page(_result(_window(10.0, 4.0, 12.0, 5.0), _window(15.0, 5.0, 13.2, 6.6))))
    assert "over the median at 1000: 1.50 as measured; 1.20 with each window's time divided by OpenCV's ORB" in text
    assert "in the process's CPU 1.10, 0.83 divided by OpenCV's ORB CPU" in text  # (13.2 / 6.6) / (12 / 5)
    assert "| 10000 | 15.0 | 45.0 | 5.0 | 3.8 | 0.8 | 6.0 / 30.0 | 13.2 | 6.6 |" in text


def test_an_earlier_result_without_cpu_or_stages_gives_dashes_and_no_cpu_ratio():
    text = "\n".join(page(_result(_window(10.0, 4.0, None, None, False), _window(15.0, 5.0, None, None, False))))
    assert "process's CPU" not in text.split("over the median at 1000")[1].split("\n")[0]
    assert "| 1000 | 10.0 | 30.0 | 4.0 | 2.5 | - | - / 20.0 | - | - |" in text
