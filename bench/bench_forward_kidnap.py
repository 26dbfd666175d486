"""The kidnapped robot relocalised by the forward camera alone (the floor detector off), per
seed: how soon and how well, and which forward loops the pose graph let in over the run,
above all the wrong ones let in after a relocalisation from the forward camera.

Each seed runs ``robotd --log-level info demo --forward --route office --kidnap T
--kidnap-to S --duration D --seed N --no-plot --config nofloor.toml`` (``nofloor.toml``
holds ``[floor_detector] enabled = false``; T, S and D per seed in :data:`KIDNAPPINGS`), one
demo at a time, a subprocess each (its CPU time: the children's user + system time). From
each run's ``summary.json`` and map file:

- relocalisation: the time and distance (truth; the daemon's odometry) from the put-down to
  the relocalising keyframe, the cameras, the agreeing loops and how many of them are right
  by the demo's judge, and that keyframe's pose error (the demo's own figures);
- forward loops over the run: verified, accepted into the graph, right / wrong by the
  demo's judge (heading within 5 deg, bearing within 10 deg past 0.2 m), accepted outside
  their own noise (the truth under the edge's information);
- accepted after the put-down, not as a member of the relocalising group: right / wrong,
  and each wrong one's seconds after the relocalisation, its gate chi-square, heading and
  bearing errors and the truth's chi-square under its own edge.

``--against DIR``: every demo also from the tree ``DIR`` (a snapshot of the code before,
``git archive``), one after the other per seed, both in the JSON and the page.
``--plain``: also this tree's demo over the whole route without the kidnapping and with the
floor detector on (``robotd demo --forward --route office --seed N``), whose forward loops
must stay all right (``--plain-seeds``: only on these). ``--full``: seeds 0-4 and
``--plain``; the default, seeds 0-2 kidnapped only (three demos of 3-8 minutes on a loaded
two-core machine). ``--reuse`` keeps a run
whose ``summary.json`` exists in ``--work``; ``--page-from JSON`` writes the page only.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

try:
    from bench.bench_kidnap import CARRY_S, run_demo
    from bench.common import machine_info, print_table, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from bench_kidnap import CARRY_S, run_demo  # type: ignore[no-redef]
    from common import machine_info, print_table, write_json, write_page  # type: ignore[no-redef]

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DEFAULT_OUT = REPO / "docs" / "benchmarks" / "forward_kidnap.json"
KIDNAPPINGS: dict[int, tuple[float, float, float]] = {
    0: (120.0, 60.0, 150.0), 1: (90.0, 20.0, 150.0), 2: (100.0, 40.0, 160.0),
    3: (110.0, 30.0, 150.0), 4: (130.0, 50.0, 160.0)}
"""Per seed: lifted at T s, put down where the office route was at S s, the drive's D s
(seeds 0-2: the kidnappings of the forward camera's first measurements)."""
NOFLOOR = "[floor_detector]\nenabled = false\n"


def keyframe_stamps(out: Path) -> dict[int, float]:
    """Keyframe id -> stamp (s of robot time) from the run's map file."""
    from robotd.io.store import MapStore

    with MapStore.open(out / "map.sqlite", create=False) as store:
        return {int(k.id): k.stamp_ns / 1e9 for k in store.keyframes()}


def _gate_chi2(detail: str) -> float | None:
    m = re.search(r"chi2 ([0-9.]+)", detail or "")
    return float(m.group(1)) if m else None


def is_member(loop: dict[str, Any]) -> bool:
    """Whether a forward loop of the summary relocalised the robot: accepted as an edge of
    its own (``relocalisation: ...``), or a member of a group that entered the graph as one
    edge (fate ``grouped``; in summaries of robotd before it, ``failed_gate`` with the detail
    :data:`robotd.graph.gate.GROUP_MEMBER`)."""
    from robotd.graph.gate import GROUP_MEMBER

    detail = loop.get("fate_detail", "")
    return (loop["fate"] == "grouped" or detail.startswith(GROUP_MEMBER)
            or (loop["fate"] == "accepted" and "relocalisation:" in detail))


def kidnapped_row(summary: dict[str, Any], stamps: dict[int, float]) -> dict[str, Any]:
    """One kidnapped run's figures (module notes)."""
    r = summary.get("relocalisation", {})
    fw = summary.get("forward_detector", {})
    loops = fw.get("loops", [])
    accepted = [x for x in loops if x["fate"] == "accepted"]
    members = [x for x in loops if is_member(x)]
    put_down = r.get("put_down_at_s", 0.0)
    reloc_t = put_down + r["after_s"] if r.get("relocalised") else None
    member_ids = {(x["from"], x["to"]) for x in members}
    after = [x for x in accepted if stamps.get(x["to"], 0.0) >= put_down and (x["from"], x["to"]) not in member_ids]
    def judged(x: dict[str, Any]) -> dict[str, Any]:
        return {"from": x["from"], "to": x["to"], "accepted": x["fate"] == "accepted",
                "s_after_reloc": (None if reloc_t is None else round(stamps.get(x["to"], 0.0) - reloc_t, 2)),
                "gate_chi2": _gate_chi2(x.get("fate_detail", "")), "yaw_error_deg": round(x["yaw_error_deg"], 2),
                "bearing_error_deg": (None if x["bearing_error_deg"] is None else round(x["bearing_error_deg"], 1)),
                "true_distance_m": round(x["true_distance_m"], 2), "truth_chi2": round(x["truth_chi2"], 1),
                "sigma_bearing_deg": (None if x.get("sigma_bearing_deg") is None else round(x["sigma_bearing_deg"], 1)),
                "sigma_yaw_deg": (None if x.get("sigma_yaw_deg") is None else round(x["sigma_yaw_deg"], 1))}

    wrong_after = [judged(x) for x in after if not x["right"]]
    wrong_members = [judged(x) for x in members if not x["right"]]
    return {
        "relocalised": bool(r.get("relocalised", False)),
        "carried_m": r.get("carried_m"),
        "after_s": r.get("after_s"), "after_m_true": r.get("after_m_true"), "after_m_daemon": r.get("after_m_daemon"),
        "cameras": r.get("cameras"), "agreeing": r.get("agreeing_candidates"),
        "agreeing_right": sum(x["right"] for x in members),
        "agreeing_accepted": sum(x["fate"] == "accepted" for x in members),
        "position_error_m": r.get("position_error_m"), "heading_error_deg": r.get("heading_error_deg"),
        "forward_verified": fw.get("verified_loops"), "forward_accepted": len(accepted),
        "forward_accepted_right": sum(x["right"] for x in accepted),
        "forward_accepted_wrong": sum(not x["right"] for x in accepted),
        "forward_accepted_outside_own_noise": sum(x["outside_own_noise"] for x in accepted),
        "after_put_down_accepted": len(after), "after_put_down_wrong": len(wrong_after),
        "wrong_after": wrong_after, "wrong_members": wrong_members,
    }


def plain_row(summary: dict[str, Any]) -> dict[str, Any]:
    fw = summary.get("forward_detector", {})
    accepted = [x for x in fw.get("loops", []) if x["fate"] == "accepted"]
    return {"forward_verified": fw.get("verified_loops"), "forward_accepted": len(accepted),
            "forward_accepted_wrong": sum(not x["right"] for x in accepted),
            "forward_accepted_outside_own_noise": sum(x["outside_own_noise"] for x in accepted)}


def _as_edges(k: dict[str, Any]) -> str:
    """How the relocalising group entered the graph (``; one edge`` or ``; N edges``), ""
    when not relocalised or not recorded."""
    if not k.get("relocalised") or k.get("agreeing_accepted") is None:
        return ""
    n = k["agreeing_accepted"]
    return "; one edge" if n == 0 else f"; {n} edges"


def _how(kind: str, w: dict[str, Any]) -> str:
    if kind != "relocalising":
        return kind
    return "relocalising, an edge" if w.get("accepted", True) else "relocalising, one edge"


def _f(v: Any, fmt: str, none: str = "-") -> str:
    return none if v is None else format(v, fmt)


def markdown(payload: dict[str, Any]) -> list[str]:
    """The page from the bench's JSON."""
    trees = payload["trees"]
    lines = ["# The kidnapped robot relocalised by the forward camera, the floor detector off "
             "(generated by bench/bench_forward_kidnap.py --markdown)", "",
             "Per seed: `robotd --log-level info demo --forward --route office --kidnap T --kidnap-to S "
             "--duration D --seed N --no-plot --config nofloor.toml` (`[floor_detector] enabled = false`), "
             "one demo at a time; " + ("; ".join(f"{t['label']}: {t['commit'] or t['path']}" for t in trees)) + ".",
             "", "| code | seed | lifted at / put down where the route was at / drive (s) | carried | relocalised "
             "after (time, driven truth / odometry) | cameras | agreeing loops (right); into the graph as | pose error then | "
             "forward loops accepted in the run (right / wrong) | outside own noise | accepted after the put-down "
             "(wrong) | CPU s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in payload["seeds"]:
        for t in trees:
            k = row["kidnapped"].get(t["label"])
            if k is None:
                continue
            at, to, dur = row["kidnapping"]
            rel = (f"{k['after_s']:.1f} s, {k['after_m_true']:.2f} / {k['after_m_daemon']:.2f} m"
                   if k["relocalised"] else "never")
            perr = (f"{k['position_error_m']:.2f} m, {k['heading_error_deg']:.2f} deg" if k["relocalised"] else "-")
            lines.append(
                f"| {t['label']} | {row['seed']} | {at:g} / {to:g} / {dur:g} | {_f(k['carried_m'], '.1f')} m | {rel} | "
                f"{k['cameras'] or '-'} | {_f(k['agreeing'], 'd')} ({k['agreeing_right']}){_as_edges(k)} | {perr} | "
                f"{k['forward_accepted']} ({k['forward_accepted_right']} / **{k['forward_accepted_wrong']}**) | "
                f"{k['forward_accepted_outside_own_noise']} | {k['after_put_down_accepted']} "
                f"({k['after_put_down_wrong']}) | {_f(k.get('cpu_s'), '.0f')} |")
    wrong = [(t["label"], row["seed"], _how(kind, w), w) for row in payload["seeds"] for t in trees
             for kind, key in (("relocalising", "wrong_members"), ("after", "wrong_after"))
             for w in (row["kidnapped"].get(t["label"]) or {}).get(key, [])]
    lines += ["", "Right by the demo's judge: heading change within 5 deg, bearing within 10 deg where the "
              "true cameras are more than 0.2 m apart. Outside own noise: the true relative pose past the "
              "99.9 % point under the loop edge's own information. Agreeing loops: the relocalising group "
              "(right by the same judge), into the graph as one edge (its fit: the members are no accepted "
              "loops) or as its members' edges (each an accepted loop). Accepted after the put-down: forward "
              "loops from the lost trajectory the gate let in, the relocalising group not counted.", ""]
    if wrong:
        lines += ["Wrong forward loops after the put-down (relocalising, an edge: a member of the relocalising "
                  "group accepted as a loop edge; relocalising, one edge: a member of a group that entered as one "
                  "edge, not accepted; after: gated in after the relocalisation). Sigmas: the loop's own bearing "
                  "sigma and the "
                  "heading sigma it adds for a ridge no heading settled (- where none, or not recorded by the code):", "",
                  "| code | seed | loop (old -> query keyframe) | how | s after the relocalisation | gate chi2 | "
                  "heading error (deg) | bearing error (deg) | true distance (m) | bearing / heading sigma (deg) | "
                  "truth chi2 under its edge |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for label, seed, kind, w in wrong:
            lines.append(f"| {label} | {seed} | {w['from']} -> {w['to']} | {kind} | {_f(w['s_after_reloc'], '.1f')} | "
                         f"{_f(w['gate_chi2'], '.2f')} | {w['yaw_error_deg']:.1f} | "
                         f"{_f(w['bearing_error_deg'], '.1f')} | {w['true_distance_m']:.2f} | "
                         f"{_f(w.get('sigma_bearing_deg'), '.1f')} / {_f(w.get('sigma_yaw_deg'), '.1f')} | "
                         f"{w['truth_chi2']:.1f} |")
        lines.append("")
    plains = [(t["label"], row["seed"], row["plain"][t["label"]]) for row in payload["seeds"] for t in trees
              if t["label"] in row.get("plain", {})]
    if plains:
        lines += ["The same seeds without the kidnapping, the floor detector on (`robotd --log-level info demo "
                  "--forward --route office --no-plot --seed N`):", "",
                  "| code | seed | forward loops verified | accepted | wrong | outside own noise | CPU s |",
                  "|---|---|---|---|---|---|---|"]
        for label, seed, p in plains:
            lines.append(f"| {label} | {seed} | {p['forward_verified']} | {p['forward_accepted']} | "
                         f"{p['forward_accepted_wrong']} | {p['forward_accepted_outside_own_noise']} | "
                         f"{_f(p.get('cpu_s'), '.0f')} |")
        lines.append("")
    return lines


def main(argv: list[str] | None = None) -> int:
    from robotd.app.demo import KIDNAP_CARRY_S

    if KIDNAP_CARRY_S != CARRY_S:
        raise SystemExit(f"the demo carries for {KIDNAP_CARRY_S} s, this bench assumes {CARRY_S}")
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default=None, help="default 0,1,2 (--full: 0,1,2,3,4)")
    ap.add_argument("--full", action="store_true", help="seeds 0-4 and --plain")
    ap.add_argument("--plain", action="store_true", help="also each seed's whole route, no kidnapping, floor on")
    ap.add_argument("--plain-seeds", default=None, help="--plain on these seeds only (default: all)")
    ap.add_argument("--against", type=Path, default=None, help="a tree of the code before: its demos beside")
    ap.add_argument("--against-label", default="before")
    ap.add_argument("--against-commit", default=None, help="the commit the --against tree holds (for the JSON)")
    ap.add_argument("--label", default="this tree")
    ap.add_argument("--config-extra", default="", help="TOML appended to nofloor.toml (a selectable variant)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench-forward-kidnap"))
    ap.add_argument("--reuse", action="store_true", help="keep a run whose summary.json is in --work")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--page-from", type=Path, default=None, help="measure nothing: write --markdown from this JSON")
    args = ap.parse_args(argv)
    if args.page_from is not None:
        if args.markdown is None:
            ap.error("--page-from needs --markdown")
        write_page(args.markdown, markdown(json.loads(args.page_from.read_text())))
        return 0
    seeds = [int(s) for s in (args.seeds or ("0,1,2,3,4" if args.full else "0,1,2")).split(",")]
    if any(s not in KIDNAPPINGS for s in seeds):
        ap.error(f"seeds are {sorted(KIDNAPPINGS)}")
    plain = args.plain or args.full
    plain_seeds = set(seeds) if args.plain_seeds is None else {int(s) for s in args.plain_seeds.split(",")}
    args.work.mkdir(parents=True, exist_ok=True)
    info = machine_info()
    trees = [{"label": args.label, "path": str(REPO), "commit": info["git_commit"]}]
    if args.against is not None:
        trees.append({"label": args.against_label, "path": str(args.against.resolve()), "commit": args.against_commit})
    nofloor = args.work / "nofloor.toml"  # this tree's (with the variant)
    nofloor.write_text(NOFLOOR + args.config_extra)
    nofloor_before = args.work / "nofloor-before.toml"  # the code before's (it may not know the variant's keys)
    nofloor_before.write_text(NOFLOOR)
    extra_cfg = None
    if args.config_extra:
        extra_cfg = args.work / "extra.toml"
        extra_cfg.write_text(args.config_extra)
    rows = []
    for seed in seeds:
        at, to, dur = KIDNAPPINGS[seed]
        row: dict[str, Any] = {"seed": seed, "kidnapping": [at, to, dur], "kidnapped": {}, "plain": {}}
        for n, t in enumerate(trees):
            out = (args.work / f"t{n}-seed{seed}-kidnapped").resolve()
            print(f"{t['label']} seed {seed} kidnapped: {out}", file=sys.stderr, flush=True)
            run = run_demo(out, seed, dur, (at, to), nofloor if n == 0 else nofloor_before, args.reuse,
                           ("--forward",), Path(t["path"]))
            k = kidnapped_row(run["summary"], keyframe_stamps(out))
            row["kidnapped"][t["label"]] = {**k, "cpu_s": run["cpu_s"], "wall_s": run["wall_s"]}
        if plain and seed in plain_seeds:  # this tree's only
            out = (args.work / f"t0-seed{seed}-plain").resolve()
            print(f"{trees[0]['label']} seed {seed} plain: {out}", file=sys.stderr, flush=True)
            run = run_demo(out, seed, None, None, extra_cfg, args.reuse, ("--forward",), Path(trees[0]["path"]))
            row["plain"][trees[0]["label"]] = {**plain_row(run["summary"]), "cpu_s": run["cpu_s"]}
        rows.append(row)
        for label, k in row["kidnapped"].items():
            print(f"{label} seed {seed}: relocalised {k['relocalised']} after {k['after_s']} s, "
                  f"forward loops accepted {k['forward_accepted']} ({k['forward_accepted_wrong']} wrong, "
                  f"{k['after_put_down_wrong']} after the put-down)", file=sys.stderr, flush=True)
    head = ["code", "seed", "reloc s", "m true", "agree (right)", "err m", "err deg", "accepted", "wrong",
            "after put-down (wrong)"]
    print_table(head, [[label, r["seed"], round(k["after_s"] or -1.0, 1), round(k["after_m_true"] or -1.0, 2),
                        f"{k['agreeing']} ({k['agreeing_right']})", round(k["position_error_m"] or -1.0, 3),
                        round(k["heading_error_deg"] or -1.0, 2), k["forward_accepted"], k["forward_accepted_wrong"],
                        f"{k['after_put_down_accepted']} ({k['after_put_down_wrong']})"]
                       for r in rows for label, k in r["kidnapped"].items()])
    payload = {"machine": info, "trees": trees, "config_extra": args.config_extra, "carry_s": CARRY_S,
               "seeds": rows}
    path = write_json(args.out, payload)
    print(f"\nwrote {path}")
    if args.markdown is not None:
        write_page(args.markdown, markdown(payload))
    return 0


if __name__ == "__main__":
    sys.exit(main())
