"""A 7154-keyframe map: storage per mode, and the last keyframe's query, brute force vs index.

Paper 003 Table V: the robot drives ~110 m through an office and takes 7154 floor images;
the table gives the storage of all their descriptors and the time to match the last image
against all the previous ones (4.2-58 s for CDVS modes 2-6, 1264 s for SIFT). Here:

* the virtual robot drives the ``office`` route (``sim.route``: ~110 m, corridor and
  room loops each driven both ways, back to the start) and a 640x480 frame is rendered at
  7154 instants evenly spread over the drive (one every ~1.5 cm at full speed, as in the
  paper; the start and end standstills and the turns in place are part of it). Every
  frame is really rendered and described in all six modes; nothing is extrapolated for
  our descriptor;
* storage: the sum of the descriptor bytes per mode; SIFT's storage is estimated from the
  keypoints of every ``--sift-every``-th frame (features x 128 x float32, and x uint8);
* the last keyframe (back at the start) is matched against every earlier one by brute
  force (``local_score`` against each, one pass, timed) and through
  :class:`robotd.floor.index.FloorIndex` (global shortlist, then local scoring of the
  shortlist; median and IQR of ``--repeats`` queries after a warm-up); target >= 100x;
  SIFT's brute force is the median time of the last frame's match against the sampled
  frames times 7153 (estimated: running it would take ~10-40 min);
* whether the true overlapping keyframes (ground-truth J >= 0.33, older than
  ``--exclude-recent-s``) are among the shortlist and the candidates, for the last
  keyframe and for ``--queries`` keyframes spread over the second half of the drive;
* query time against map size (500 ... 7154 keyframes) next to brute force at the same
  size (cumulative measured per-pair times of the brute-force pass): sub-linear growth.

Run from the repo root: ``.venv/bin/python bench/bench_floor_map.py [--out DIR]``.
Writes ``DIR/floor_map.json`` and ``DIR/floor_map_scaling.png``. Takes ~10 min.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

try:
    from bench.common import print_table, time_repeats, write_json
    from bench.floor_common import (LOOP_OVERLAP, MODES, SiftBaseline, add_common_args, bench_floors,
                                    header, load_average, log, one_thread, printed_floor, pyplot, r,
                                    spread)
except ImportError:  # run as a script: bench/ is on sys.path
    from common import print_table, time_repeats, write_json
    from floor_common import (LOOP_OVERLAP, MODES, SiftBaseline, add_common_args, bench_floors, header,
                              load_average, log, one_thread, printed_floor, pyplot, r, spread)

from robotd.floor.descriptor import MODE_BYTES, decode, extract
from robotd.floor.index import FloorIndex, IndexParams
from robotd.floor.match import local_score
from robotd.base.camera import FloorCameraModel, overlap_ratios
from sim.cameras.floor import FloorRenderer, RenderParams
from sim.route import build_route, plan_motion

MB = 1e6  # the paper's MB (7154 x 1 kB bound = 7.3 MB, Table V: 7.67 MB for mode 2)
SIZES = (500, 1000, 2000, 4000)


def build_map(floor: object, args: argparse.Namespace, sift: SiftBaseline) -> dict:
    """Render the office drive, describe every frame in every mode, sample SIFT."""
    motion = plan_motion(build_route("office"), dt_s=0.01)
    t = np.linspace(motion.t_s[0], motion.t_s[-1], args.keyframes)
    poses = motion.poses_at(t)
    cam = FloorCameraModel.default()
    renderer = FloorRenderer(floor, cam, RenderParams(), np.random.default_rng(args.seed))

    def frame(k: int) -> np.ndarray:
        v, w = motion.velocity_at(float(t[k]))
        return renderer.render(poses[k], v, w, float(t[k]))

    last = len(t) - 1
    sift_last = sift.extract(frame(last))
    blobs: dict[int, list[bytes]] = {m: [] for m in MODES}
    sift_counts, sift_match_s = [], []
    t_render = t_extract = 0.0
    t0 = time.perf_counter()
    for k in range(len(t)):
        a = time.perf_counter()
        image = frame(k)
        b = time.perf_counter()
        for m in MODES:
            blobs[m].append(extract(image, m))
        t_render += b - a
        t_extract += time.perf_counter() - b
        if k % args.sift_every == 0 and k != last:
            f = sift.extract(image)
            sift_counts.append(len(f))
            c = time.perf_counter()
            sift.match(sift_last, f)
            if sift_counts[1:]:  # the first match is the warm-up
                sift_match_s.append(time.perf_counter() - c)
        if k % 500 == 0 or k == last:
            el = time.perf_counter() - t0
            log(f"  frame {k + 1}/{len(t)}: {el:.0f} s (render {t_render:.0f} s, 6 modes {t_extract:.0f} s)")
    return {"motion": motion, "t": t, "poses": poses, "blobs": blobs, "sift_counts": sift_counts,
            "sift_match_s": sift_match_s, "sift_features_last": len(sift_last),
            "render_s": t_render, "extract_all_modes_s": t_extract, "length_m": motion.length_m}


def true_overlaps(cam: FloorCameraModel, poses: np.ndarray, q: int, eligible_upto: int) -> np.ndarray:
    """Ids ``<= eligible_upto`` whose footprint overlaps keyframe ``q``'s with J >= 0.33."""
    if eligible_upto < 0:
        return np.zeros(0, np.int64)
    j = overlap_ratios(cam, np.repeat(poses[q:q + 1], eligible_upto + 1, axis=0), poses[: eligible_upto + 1])
    return np.flatnonzero(j >= LOOP_OVERLAP)


def passages(ids: np.ndarray, gap: int) -> list[np.ndarray]:
    """Split sorted keyframe ids into runs (separate visits of a place): a new run starts
    after a jump of more than ``gap`` ids."""
    if len(ids) == 0:
        return []
    cuts = np.flatnonzero(np.diff(ids) > gap) + 1
    return np.split(ids, cuts)


def bench_mode(mode: int, m: dict, args: argparse.Namespace, recent: int) -> dict:
    cam = FloorCameraModel.default()
    blobs = m["blobs"][mode]
    n = len(blobs)
    last = n - 1
    a = time.perf_counter()
    decs = [decode(b) for b in blobs]
    t_decode = time.perf_counter() - a
    index = FloorIndex(IndexParams(k=args.k, shortlist=args.shortlist))
    sizes = [s for s in SIZES if s < n] + [n - 1]
    scaling = []
    a = time.perf_counter()
    for kf, d in enumerate(decs[:last]):
        index.add(kf, d)
        if len(index) in sizes:
            tq = time_repeats(lambda: index.query(decs[last]), repeats=args.repeats, warmup=2)
            tg = time_repeats(lambda: index.global_scores(decs[last]), repeats=args.repeats, warmup=2)
            scaling.append({"size": len(index), "query_ms": 1e3 * tq["median_s"], "query_iqr_ms": 1e3 * tq["iqr_s"],
                            "global_scan_ms": 1e3 * tg["median_s"], "nbytes": index.nbytes})
    t_build = time.perf_counter() - a

    # Brute force, as in the paper: the last keyframe against every earlier one.
    for kf in range(3):  # warm-up
        local_score(decs[last], decs[kf])
    per_pair = np.empty(last)
    brute_scores = np.empty(last)
    a = time.perf_counter()
    for kf in range(last):
        c = time.perf_counter()
        brute_scores[kf] = local_score(decs[last], decs[kf]).score
        per_pair[kf] = time.perf_counter() - c
    brute_s = time.perf_counter() - a
    cum = np.cumsum(per_pair)
    for row in scaling:
        row["brute_force_ms"] = 1e3 * float(cum[row["size"] - 1])

    # The index query with the recent keyframes excluded (the detector's use).
    exclude_after = last - recent
    tq = time_repeats(lambda: index.query(decs[last], exclude_after_id=exclude_after), args.repeats, warmup=2)
    before = index.local_matches
    cands = index.query(decs[last], exclude_after_id=exclude_after)
    matches_per_query = index.local_matches - before
    short = index.shortlist(decs[last], exclude_after_id=exclude_after)
    truth = true_overlaps(cam, m["poses"], last, exclude_after)
    truth_set = set(truth.tolist())
    visits = passages(truth, gap=30)
    short_ids = {kf for kf, _ in short}
    cand_ids = [c.keyframe_id for c in cands]
    eligible_scores = brute_scores[: exclude_after + 1]
    brute_top = np.argsort(-eligible_scores, kind="stable")[: args.k]
    last_query = {
        "true_overlaps": len(truth), "visits": len(visits),
        "visits_in_shortlist": sum(bool(short_ids & set(v.tolist())) for v in visits),
        "visits_in_candidates": sum(bool(set(cand_ids) & set(v.tolist())) for v in visits),
        "true_in_shortlist": len(short_ids & truth_set), "shortlist": len(short),
        "candidates": [{"id": c.keyframe_id, "local": float(c.local.score), "global": c.global_score,
                        "true": c.keyframe_id in truth_set} for c in cands],
        "brute_top": [{"id": int(i), "local": float(eligible_scores[i]), "true": int(i) in truth_set}
                      for i in brute_top],
        "local_matches_per_query": matches_per_query,
    }

    # Many queries over the second half of the drive, each against the keyframes older
    # than it by more than the exclusion window.
    rng = np.random.default_rng(args.seed)
    qs = np.sort(rng.choice(np.arange(n // 2, last), size=min(args.queries, last - n // 2), replace=False))
    with_truth = found_short = found_cand = top1 = 0
    for q in qs:
        elig = int(q) - recent
        truth_q = set(true_overlaps(cam, m["poses"], int(q), elig).tolist())
        if not truth_q:
            continue
        with_truth += 1
        cs = index.query(decs[q], exclude_after_id=elig)
        sh = {kf for kf, _ in index.shortlist(decs[q], exclude_after_id=elig)}
        found_short += bool(sh & truth_q)
        found_cand += bool({c.keyframe_id for c in cs} & truth_q)
        top1 += bool(cs) and cs[0].keyframe_id in truth_q
    many = {"queries": len(qs), "with_true_overlap": with_truth, "shortlist_hit": found_short,
            "candidates_hit": found_cand, "top1_true": top1}

    return {
        "mode": mode, "keyframes": n, "storage_bytes": int(sum(len(b) for b in blobs)),
        "bytes_per_keyframe_mean": float(np.mean([len(b) for b in blobs])),
        "bytes_per_keyframe_max": int(max(len(b) for b in blobs)), "bound_bytes": int(MODE_BYTES[mode]),
        "decode_all_s": t_decode, "index_build_s": t_build, "index_nbytes": index.nbytes,
        "brute_force_s": brute_s, "brute_force_per_pair": spread(per_pair.tolist()),
        "query_ms": 1e3 * tq["median_s"], "query_iqr_ms": 1e3 * tq["iqr_s"],
        "speedup": brute_s / tq["median_s"], "last_query": last_query, "many_queries": many,
        "scaling": scaling,
    }


def plot_scaling(results: list[dict], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9.5, 5), dpi=110)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for res, col in zip(results, colours):
        s = np.array([x["size"] for x in res["scaling"]])
        ax.plot(s, [x["query_ms"] for x in res["scaling"]], "o-", color=col, label=f"mode {res['mode']} index")
        ax.plot(s, [x["brute_force_ms"] for x in res["scaling"]], "x--", color=col, alpha=0.6)
    ax.plot([], [], "x--", color="grey", label="brute force (mode's colour)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("keyframes in the map")
    ax.set_ylabel("time to query one keyframe, ms")
    ax.set_title("Index query (solid) vs brute-force local scoring (dashed)")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap)
    ap.add_argument("--map-floor", default="mixed",
                    help="name of the floor to drive on (gravel, grass, brick, herringbone, mixed, printed "
                         "(repeating printed planks, the paper's case), or the stem of a --floor FILE; "
                         "default mixed)")
    ap.add_argument("--keyframes", type=int, default=7154, help="frames along the drive (default 7154, paper)")
    ap.add_argument("--sift-every", type=int, default=20, help="SIFT on every n-th frame (default 20)")
    ap.add_argument("--k", type=int, default=5, help="candidates per query (default 5)")
    ap.add_argument("--shortlist", type=int, default=IndexParams().shortlist,
                    help=f"keyframes scored locally per query (default {IndexParams().shortlist})")
    ap.add_argument("--exclude-recent-s", type=float, default=20.0,
                    help="keyframes younger than this are not candidates (default 20 s, the detector's)")
    ap.add_argument("--queries", type=int, default=200, help="extra queries over the second half (default 200)")
    ap.add_argument("--repeats", type=int, default=7, help="timed index queries (default 7)")
    args = ap.parse_args(argv)
    load_start = load_average()
    blas = one_thread()
    log(f"load average {load_start}; BLAS pools {blas}")
    floors = {bf.name: bf for bf in [*bench_floors(args.floor, args.seed), printed_floor(args.seed)]}
    if args.map_floor not in floors:
        ap.error(f"unknown --map-floor {args.map_floor!r}; known: {', '.join(floors)}")
    bf = floors[args.map_floor]
    sift = SiftBaseline(args.seed)

    log(f"building the map: {args.keyframes} frames on the office route, floor {bf.name}")
    m = build_map(bf.floor, args, sift)
    n = args.keyframes
    dt = float(m["t"][1] - m["t"][0])
    recent = int(np.ceil(args.exclude_recent_s / dt))
    results = []
    for mode in MODES:
        log(f"mode {mode}: decode, index, queries, brute force")
        results.append(bench_mode(mode, m, args, recent))

    sift_feats = float(np.mean(m["sift_counts"]))
    sift_pair_s = statistics.median(m["sift_match_s"])
    sift_brute_s = sift_pair_s * (n - 1)
    print(f"\nMap: {n} keyframes, office route {m['length_m']:.1f} m ({m['length_m'] / (n - 1) * 100:.2f} cm "
          f"per frame at full speed), floor {bf.name}; render {m['render_s']:.0f} s, 6 modes described in "
          f"{m['extract_all_modes_s']:.0f} s")
    print("\nTable V: storage of all keyframes and the last keyframe matched against all previous ones")
    rows = []
    for res in results:
        rows.append([f"mode {res['mode']}", r(res["storage_bytes"] / MB, 2), r(res["index_nbytes"] / MB, 2),
                     r(res["brute_force_s"], 2), r(res["query_ms"], 2), r(res["query_iqr_ms"], 2),
                     r(res["speedup"], 0), res["last_query"]["local_matches_per_query"]])
    rows.append(["SIFT f32 (est.)", r(sift_feats * n * 128 * 4 / MB, 1), "", r(sift_brute_s, 0), "", "", "", ""])
    rows.append(["SIFT u8 (est.)", r(sift_feats * n * 128 / MB, 1), "", "", "", "", "", ""])
    print_table(["descriptor", "storage MB", "index RAM MB", "brute force s", "index ms", "IQR ms",
                 "speedup x", "local/query"], rows)
    print(f"  SIFT: {sift_feats:.0f} keypoints per frame (every {args.sift_every}th frame), "
          f"{sift_pair_s * 1e3:.0f} ms per pair (median of {len(m['sift_match_s'])}) x {n - 1} pairs")

    print(f"\nThe last keyframe's true overlaps (J >= {LOOP_OVERLAP}, older than {args.exclude_recent_s:g} s) "
          "among the index's shortlist and candidates")
    rows = []
    for res in results:
        lq = res["last_query"]
        rows.append([f"mode {res['mode']}", lq["true_overlaps"], lq["visits"], lq["true_in_shortlist"],
                     f"{lq['visits_in_shortlist']}/{lq['visits']}", f"{lq['visits_in_candidates']}/{lq['visits']}",
                     " ".join(f"{c['id']}{'+' if c['true'] else '-'}{c['local']:.0f}" for c in lq["candidates"]),
                     " ".join(f"{c['id']}{'+' if c['true'] else '-'}{c['local']:.0f}" for c in lq["brute_top"])])
    print_table(["mode", "true", "visits", "true in short", "visits short", "visits cand",
                 "candidates id(+true)score", "brute-force top"], rows)
    print(f"\n{args.queries} queries over the second half (k={args.k}, shortlist {args.shortlist}): "
          "queries with a true overlap found")
    rows = [[f"mode {res['mode']}", res["many_queries"]["with_true_overlap"],
             res["many_queries"]["shortlist_hit"], res["many_queries"]["candidates_hit"],
             res["many_queries"]["top1_true"]] for res in results]
    print_table(["mode", "queries with truth", "in shortlist", "in candidates", "top-1 true"], rows)

    print("\nQuery time against map size, ms: index (brute force)")
    sizes = [x["size"] for x in results[0]["scaling"]]
    rows = [[f"mode {res['mode']}", *[f"{x['query_ms']:.2f} ({x['brute_force_ms']:.0f})" for x in res["scaling"]]]
            for res in results]
    print_table(["mode", *[str(s) for s in sizes]], rows)
    rows = [[f"mode {res['mode']}", *[f"{x['global_scan_ms']:.3f}" for x in res["scaling"]]] for res in results]
    print("  of which the global scan over all keyframes, ms")
    print_table(["mode", *[str(s) for s in sizes]], rows)

    args.out.mkdir(parents=True, exist_ok=True)
    png = args.out / "floor_map_scaling.png"
    plot_scaling(results, png)
    payload = header("floor_map", load_start=load_start, settings={
        "threads": 1, "seed": args.seed, "floor": bf.name, "floor_source": bf.source, "route": "office",
        "keyframes": n, "frame_interval_s": dt, "k": args.k, "shortlist": args.shortlist,
        "exclude_recent_s": args.exclude_recent_s, "exclude_recent_keyframes": recent,
        "sift_every": args.sift_every, "queries": args.queries, "repeats": args.repeats, "MB": MB,
        "extrapolated": "SIFT storage (keypoints of sampled frames) and SIFT brute force (median sampled pair "
                        "time x 7153); everything of our descriptor is measured on all keyframes",
    })
    payload.update({
        "route_length_m": m["length_m"], "render_s": m["render_s"], "extract_all_modes_s": m["extract_all_modes_s"],
        "modes": results,
        "sift": {"features_mean": sift_feats, "sampled_frames": len(m["sift_counts"]),
                 "storage_float32_bytes": sift_feats * n * 128 * 4, "storage_uint8_bytes": sift_feats * n * 128,
                 "pair_match": spread(m["sift_match_s"]), "brute_force_s_estimated": sift_brute_s,
                 "features_last": m["sift_features_last"]},
    })
    out = write_json(args.out / "floor_map.json", payload)
    print(f"\nwrote {out} and {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
