"""Learn the floor descriptor's tables (``robotd/floor/selection.npz``) on virtual-robot pairs.

Reproduces the shipped file: ``.venv/bin/python tools/train_selection.py`` (``--out``,
``--seed``, ``--pairs``). Deterministic for a seed (the renderer's noise, the poses, the
k-means initialisation and the Hadamard signs all come from it).

Data: floors quilted from each of scikit-image's three texture photographs (gravel,
grass, brick; ``Floor.from_photos``, floor seeds 1000 + i so they differ from the test and
benchmark floors), frame pairs rendered by the virtual floor camera with pose B within
``--max-offset`` metres of A and any heading, so their footprints overlap by J in about
[0, 0.9]. Never the photos under ``../shared/data``.

What is learned (see :mod:`robotd.floor.descriptor`):

* **Selection** (CDVS-style relevance): a keypoint of A counts as matched when the nearest
  neighbour of its descriptor among B's strongest ``--per-image`` keypoints lies within
  ``--match-px`` of where the ground truth puts it (keypoints that leave B's view count as
  unmatched, which is how the distance from the centre earns its weight). Per attribute,
  ``--bins`` quantile bins and log(P(match | bin) / P(match)), Laplace-smoothed.
* **Ternary thresholds**: per transformed element, the ``--tail`` and ``1 - --tail``
  quantiles over the relevant keypoints (balanced trits).
* **Element order**: elements sorted by how much more their trits agree (product
  ``a * b``) on ground-truth correspondences than on random keypoint pairs.
* **Global descriptor**: PCA of the raw descriptors to 32 dimensions, k-means (32
  centroids, k-means++ then Lloyd), random Hadamard signs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from robotd.floor.compression import transform  # noqa: E402
from robotd.floor.descparams import N_ATTRIBUTES, ExtractParams, Learned, load_learned  # noqa: E402
from robotd.floor.keypoints import candidates, raw_descriptors, working  # noqa: E402
from robotd.base.camera import FloorCameraModel, overlap_ratios  # noqa: E402
from robotd.base.geometry import inverse, transform_points  # noqa: E402
from sim.world.floor import Floor  # noqa: E402
from sim.cameras.floor import FloorRenderer, RenderParams  # noqa: E402

FLOORS = ("gravel", "grass", "brick")
PCA_DIM = 32
CENTROIDS = 32


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def render_pairs(photo: str, n: int, max_offset_m: float, seed: int, floor_seed: int):
    """``n`` pairs of frames on a floor of one scikit-image photo: images, poses, J."""
    import skimage.data

    rng = np.random.default_rng(seed)
    floor = Floor.from_photos([getattr(skimage.data, photo)()], seed=floor_seed)
    cam = FloorCameraModel.default()
    renderer = FloorRenderer(floor, cam, RenderParams(), rng)
    pa = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), rng.uniform(-np.pi, np.pi, n)])
    r = max_offset_m * np.sqrt(rng.random(n))
    phi = rng.uniform(-np.pi, np.pi, n)
    pb = np.column_stack([pa[:, 0] + r * np.cos(phi), pa[:, 1] + r * np.sin(phi), rng.uniform(-np.pi, np.pi, n)])
    frames = []
    for poses in (pa, pb):
        v = rng.uniform(0.0, 0.3, n)
        t = rng.uniform(0.0, 600.0, n)
        frames.append([renderer.render(p, float(vi), 0.0, float(ti)) for p, vi, ti in zip(poses, v, t)])
    return frames[0], frames[1], pa, pb, overlap_ratios(cam, pa, pb)


def a_to_b(cam: FloorCameraModel, xy: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Ground truth: where pixels of A land in B, ``(N, 2)`` px."""
    world = transform_points(pa, cam.pixel_to_floor_robot(xy))
    return cam.floor_robot_to_pixel(transform_points(inverse(pb), world))


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iters: int = 40) -> np.ndarray:
    """k-means++ seeding then Lloyd iterations; ``(k, D)`` centroids."""
    c = [x[rng.integers(len(x))]]
    d2 = ((x - c[0]) ** 2).sum(1)
    for _ in range(1, k):
        c.append(x[rng.choice(len(x), p=d2 / d2.sum())])
        d2 = np.minimum(d2, ((x - c[-1]) ** 2).sum(1))
    c = np.array(c)
    for _ in range(iters):
        a = np.argmin((x * x).sum(1)[:, None] - 2 * x @ c.T + (c * c).sum(1), axis=1)
        for j in range(k):
            if np.any(a == j):
                c[j] = x[a == j].mean(0)
    return c


def train(args: argparse.Namespace) -> dict[str, np.ndarray]:
    params = ExtractParams(detect_step=args.detect_step)
    cam = FloorCameraModel.default()
    attrs, labels, elems, raws = [], [], [], []
    corr_a, corr_b, rand_a, rand_b = [], [], [], []
    rng = np.random.default_rng(args.seed)
    for i, photo in enumerate(FLOORS):
        t0 = time.perf_counter()
        ims_a, ims_b, pa, pb, j = render_pairs(photo, args.pairs, args.max_offset, args.seed + i, 1000 + i)
        log(f"{photo}: {args.pairs} pairs rendered in {time.perf_counter() - t0:.0f} s, "
            f"J >= 0.33 in {np.mean(j >= 0.33):.0%}")
        for a_img, b_img, p_a, p_b in zip(ims_a, ims_b, pa, pb):
            ca = candidates(working(a_img, params), params, None)
            cb = candidates(working(b_img, params), params, None)
            m = args.per_image
            da, db = raw_descriptors(ca, len(ca.xy), params), raw_descriptors(cb, min(m, len(cb.xy)), params)
            if len(db) < 2 or len(da) < 2:
                continue
            gt = a_to_b(cam, ca.xy.astype(float), p_a, p_b)
            nn = np.argmin(-2 * da @ db.T + (db * db).sum(1), axis=1)
            ok = np.linalg.norm(cb.xy[nn] - gt, axis=1) < args.match_px
            attrs.append(ca.attributes)
            labels.append(ok)
            ea, eb = transform(da[:m]), transform(db)
            elems.append(ea)
            raws.append(da[: m // 4])
            # Ground-truth correspondences among the top keypoints (for the element order),
            # and as many random keypoint pairs.
            d = np.linalg.norm(gt[:m, None, :] - cb.xy[None, :len(db), :], axis=2)
            corr = np.flatnonzero(d.min(1) < 2.0)[:100]
            corr_a.append(ea[corr])
            corr_b.append(eb[d[corr].argmin(1)])
            rand_a.append(ea[rng.integers(len(ea), size=len(corr))])
            rand_b.append(eb[rng.integers(len(eb), size=len(corr))])
    attrs_all, labels_all = np.concatenate(attrs), np.concatenate(labels)
    log(f"{len(labels_all)} keypoints, {labels_all.mean():.1%} matched; {sum(map(len, corr_a))} correspondences")

    edges = np.zeros((N_ATTRIBUTES, args.bins - 1), np.float32)
    logp = np.zeros((N_ATTRIBUTES, args.bins), np.float32)
    base = labels_all.mean()
    for a in range(N_ATTRIBUTES):
        edges[a] = np.quantile(attrs_all[:, a], np.linspace(0, 1, args.bins + 1)[1:-1])
        b = np.searchsorted(edges[a], attrs_all[:, a])
        hit = np.bincount(b, labels_all, args.bins)
        cnt = np.bincount(b, minlength=args.bins)
        logp[a] = np.log((hit + base * 10) / (cnt + 10) / base)
        log(f"attribute {a}: P(match | bin) / P(match) = " + " ".join(f"{v:.2f}" for v in np.exp(logp[a])))

    # Thresholds and element order on the keypoints the selection keeps.
    e = np.concatenate(elems)
    lo = np.quantile(e, args.tail, axis=0).astype(np.float32)
    hi = np.quantile(e, 1 - args.tail, axis=0).astype(np.float32)
    def trits(x: list[np.ndarray]) -> np.ndarray:
        v = np.concatenate(x)
        return (v > hi).astype(np.int8) - (v < lo).astype(np.int8)

    gain = (trits(corr_a) * trits(corr_b)).mean(0) - (trits(rand_a) * trits(rand_b)).mean(0)
    order = np.argsort(-gain, kind="stable").astype(np.int16)
    log("element order (first 24): " + " ".join(str(v) for v in order[:24]))

    raw = np.concatenate(raws)
    mean = raw.mean(0)
    _, _, vt = np.linalg.svd(raw - mean, full_matrices=False)
    basis = vt[:PCA_DIM].T.astype(np.float32)
    z = (raw - mean) @ basis
    sub = z[rng.choice(len(z), min(len(z), 40000), replace=False)]
    centroids = kmeans(sub.astype(np.float64), CENTROIDS, rng).astype(np.float32)
    signs = rng.choice(np.array([-1.0, 1.0], np.float32), PCA_DIM * CENTROIDS)
    return {"rel_edges": edges, "rel_logp": logp, "tern_lo": lo, "tern_hi": hi, "order": order,
            "pca_mean": mean.astype(np.float32), "pca_basis": basis, "centroids": centroids, "signs": signs}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "robotd" / "floor" / "selection.npz")
    ap.add_argument("--seed", type=int, default=20240)
    ap.add_argument("--pairs", type=int, default=60, help="pairs per floor")
    ap.add_argument("--max-offset", type=float, default=0.3, help="largest distance of B from A, metres")
    ap.add_argument("--per-image", type=int, default=600, help="keypoints of B searched for matches")
    ap.add_argument("--match-px", type=float, default=4.0, help="ground-truth tolerance of a correct match")
    ap.add_argument("--bins", type=int, default=12, help="quantile bins per selection attribute")
    ap.add_argument("--tail", type=float, default=1 / 3, help="ternary thresholds at these quantiles")
    ap.add_argument("--detect-step", type=int, default=1, choices=[1, 2],
                    help="ExtractParams.detect_step of the keypoints learned on (2: detection on the image halved)")
    ap.add_argument("--selection-only", type=Path, default=None, metavar="NPZ",
                    help="learn only the selection tables (rel_edges, rel_logp) and take every other table "
                         "from this file: descriptors stay comparable with those made with it")
    args = ap.parse_args(argv)
    tables = train(args)
    if args.selection_only is not None:
        kept = load_learned(args.selection_only)
        tables = {k: (tables[k] if k in ("rel_edges", "rel_logp") else getattr(kept, k))
                  for k in Learned.__dataclass_fields__}
    Learned(**tables)  # every field present
    meta = np.array(f"tools/train_selection.py seed={args.seed} pairs={args.pairs} max_offset={args.max_offset} "
                    f"per_image={args.per_image} match_px={args.match_px} bins={args.bins} tail={args.tail:.4f} "
                    f"floors={','.join(FLOORS)} detect_step={args.detect_step}"
                    + (f" selection_only={args.selection_only.name}" if args.selection_only else ""))
    np.savez_compressed(args.out, meta=meta, **tables)
    log(f"wrote {args.out} ({args.out.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
