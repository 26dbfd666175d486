"""``bench/bench_forward_kidnap.py``: what it reads from a kidnapped demo's summary (the
relocalising group, accepted as edges or as one edge; the wrong loops after the put-down)
and the page it writes from its JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from bench.bench_forward_kidnap import kidnapped_row, main, markdown, plain_row
from robotd.graph.gate import GROUP_MEMBER


def _loop(a: int, b: int, fate: str, detail: str, right: bool, **kw: Any) -> dict[str, Any]:
    return {"from": a, "to": b, "fate": fate, "fate_detail": detail, "right": right, "yaw_error_deg": 0.5,
            "bearing_error_deg": 3.0, "true_distance_m": 0.4, "truth_chi2": 1.0, "outside_own_noise": False,
            "sigma_bearing_deg": 20.0, "sigma_yaw_deg": None, **kw}


def _summary(members: list[dict[str, Any]]) -> dict[str, Any]:
    before = _loop(1, 10, "accepted", "chi2 1.20", True)  # before the lift
    after = [_loop(3, 40, "accepted", "chi2 2.00", True),
             _loop(4, 44, "accepted", "chi2 9.90", False, yaw_error_deg=4.4, bearing_error_deg=52.4),
             _loop(5, 46, "failed_gate", "chi2 30.1 > 13.82", False)]
    return {"relocalisation": {"relocalised": True, "put_down_at_s": 100.0, "after_s": 5.0, "after_m_true": 2.5,
                               "after_m_daemon": 2.4, "carried_m": 2.6, "cameras": "forward",
                               "agreeing_candidates": len(members), "position_error_m": 0.03,
                               "heading_error_deg": 0.5},
            "forward_detector": {"verified_loops": 1 + len(members) + len(after), "loops": [before, *members, *after]}}


STAMPS = {10: 50.0, 30: 101.0, 31: 102.0, 32: 105.0, 40: 110.0, 44: 111.0, 46: 112.0}


def test_a_group_accepted_as_its_members_edges_counts_them_among_the_accepted():
    members = [_loop(2, 30, "accepted", "relocalisation: 3 candidates agree", True),
               _loop(2, 31, "accepted", "relocalisation: 3 candidates agree", False, yaw_error_deg=4.3),
               _loop(3, 32, "accepted", "relocalisation: 3 candidates agree", True)]
    k = kidnapped_row(_summary(members), STAMPS)
    assert (k["agreeing"], k["agreeing_right"], k["agreeing_accepted"]) == (3, 2, 3)
    assert (k["forward_accepted"], k["forward_accepted_right"], k["forward_accepted_wrong"]) == (6, 4, 2)
    # After the put-down: the members not counted, the wrong one gated in 6 s after the relocalisation.
    assert (k["after_put_down_accepted"], k["after_put_down_wrong"]) == (2, 1)
    assert [(w["from"], w["to"], w["s_after_reloc"], w["gate_chi2"]) for w in k["wrong_after"]] == [(4, 44, 6.0, 9.9)]
    assert [(w["from"], w["to"], w["accepted"]) for w in k["wrong_members"]] == [(2, 31, True)]


@pytest.mark.parametrize("fate, detail", [
    ("grouped", f"{GROUP_MEMBER} (2->30): 3 candidates agree"),
    ("grouped", "relocalisation: 3 candidates agree"),  # by the fate alone
    ("failed_gate", f"{GROUP_MEMBER} (2->30): 3 candidates agree"),  # a summary of robotd before ``grouped``
])
def test_a_group_that_entered_as_one_edge_is_not_counted_among_the_accepted(fate: str, detail: str):
    members = [_loop(2, 30, fate, detail, True), _loop(2, 31, fate, detail, False),
               _loop(3, 32, fate, detail, True)]
    k = kidnapped_row(_summary(members), STAMPS)
    assert (k["agreeing"], k["agreeing_right"], k["agreeing_accepted"]) == (3, 2, 0)
    assert (k["forward_accepted"], k["forward_accepted_right"], k["forward_accepted_wrong"]) == (3, 2, 1)
    assert (k["after_put_down_accepted"], k["after_put_down_wrong"]) == (2, 1)
    assert [(w["from"], w["to"], w["accepted"]) for w in k["wrong_members"]] == [(2, 31, False)]


def test_the_page_from_the_json_says_how_the_group_entered_and_lists_the_wrong_loops(tmp_path: Path):
    detail = f"{GROUP_MEMBER} (2->30): 3 candidates agree"
    one = kidnapped_row(_summary([_loop(2, 30, "grouped", detail, True),
                                  _loop(2, 31, "grouped", detail, False),
                                  _loop(3, 32, "grouped", detail, True)]), STAMPS)
    edges = kidnapped_row(_summary([_loop(2, 30, "accepted", "relocalisation: x", True),
                                    _loop(3, 32, "accepted", "relocalisation: x", True)]), STAMPS)
    plain = plain_row({"forward_detector": {"verified_loops": 3, "loops": [
        _loop(1, 9, "accepted", "chi2 1.0", True), _loop(2, 9, "accepted", "chi2 1.0", True),
        _loop(3, 9, "failed_gate", "chi2 99.0 > 13.82", False)]}})
    assert plain == {"forward_verified": 3, "forward_accepted": 2, "forward_accepted_wrong": 0,
                     "forward_accepted_outside_own_noise": 0}
    payload = {"trees": [{"label": "this tree", "path": "/a", "commit": "abc"},
                         {"label": "before", "path": "/b", "commit": None}],
               "seeds": [{"seed": 2, "kidnapping": [100.0, 40.0, 160.0],
                          "kidnapped": {"this tree": {**one, "cpu_s": 200.0}, "before": {**edges, "cpu_s": 190.0}},
                          "plain": {"this tree": {**plain, "cpu_s": 240.0}}}]}
    src = tmp_path / "k.json"
    src.write_text(json.dumps(payload))
    page = tmp_path / "page.md"
    assert main(["--page-from", str(src), "--markdown", str(page)]) == 0
    text = page.read_text()
    assert text == "\n".join(markdown(payload))
    rows = [ln for ln in text.splitlines() if ln.startswith("| this tree | 2 |") or ln.startswith("| before | 2 |")]
    assert rows[0].split(" | ")[6] == "3 (2); one edge" and rows[1].split(" | ")[6] == "2 (2); 2 edges"
    assert rows[0].split(" | ")[8] == "3 (2 / **1**)" and rows[1].split(" | ")[8] == "5 (4 / **1**)"
    assert "| this tree | 2 | 2 -> 31 | relocalising, one edge |" in text
    assert "| this tree | 2 | 4 -> 44 | after | 6.0 | 9.90 | 4.4 | 52.4 |" in text
    assert "| this tree | 2 | 3 | 2 | 0 | 0 | 240 |" in text
