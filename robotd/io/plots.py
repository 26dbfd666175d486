"""Plots written by the CLI (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from robotd.base.files import replacing


def _figure(size: tuple[float, float]) -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=size, dpi=110)


def _save(fig: Any, path: Path) -> None:
    """Lay out, write the PNG and free the figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    try:
        with replacing(Path(path), "wb") as f:  # a full disk leaves no half-written PNG
            fig.savefig(f, format="png")
    finally:
        plt.close(fig)


def plot_trajectories(path: Path, floor: Any, truth: np.ndarray, estimates: dict[str, np.ndarray],
                      keyframes_xy: np.ndarray | None = None, title: str = "",
                      loop_edges_xy: np.ndarray | None = None) -> None:
    """Ground truth and estimated trajectories drawn over the floor they were driven on.

    ``truth`` and each estimate are ``(N, 3)`` poses in the world frame (metres);
    ``loop_edges_xy`` ``(L, 2, 2)``: the accepted loop edges as segments between the two
    keyframes' positions.
    """
    pts = np.vstack([truth[:, :2]] + [e[:, :2] for e in estimates.values()])
    lo = pts.min(axis=0) - 0.6
    hi = pts.max(axis=0) + 0.6
    span = hi - lo
    fig, ax = _figure((9.0, 9.0 * span[1] / max(span[0], 1e-6) * 0.9 + 1.0))
    if floor is not None:
        px_per_m = min(100.0, 1600.0 / float(max(span)))
        img = floor.render_overview(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]), px_per_m)
        ax.imshow(img, cmap="gray", extent=(lo[0], hi[0], lo[1], hi[1]), origin="upper",
                  vmin=0, vmax=255, alpha=0.55, interpolation="bilinear")
    ax.plot(truth[:, 0], truth[:, 1], color="black", lw=2.2, label="ground truth")
    colours = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#17becf"]
    for (name, est), col in zip(estimates.items(), colours):
        ax.plot(est[:, 0], est[:, 1], color=col, lw=1.4, label=name)
        ax.plot(est[-1, 0], est[-1, 1], "o", color=col, ms=6)
    if keyframes_xy is not None and len(keyframes_xy):
        ax.plot(keyframes_xy[:, 0], keyframes_xy[:, 1], ".", color="#ff7f0e", ms=2.0,
                label=f"keyframes ({len(keyframes_xy)})", alpha=0.7)
    if loop_edges_xy is not None and len(loop_edges_xy):
        from matplotlib.collections import LineCollection

        ax.add_collection(LineCollection(list(loop_edges_xy), colors="#e377c2", linewidths=0.6, alpha=0.6,
                                         label=f"loop edges ({len(loop_edges_xy)})"))
    ax.plot(truth[0, 0], truth[0, 1], "k*", ms=14, label="start")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=9, framealpha=0.9)
    if title:
        ax.set_title(title)
    _save(fig, path)


def plot_similarity(path: Path, overlap: np.ndarray, scores: np.ndarray, stamps_ns: np.ndarray,
                    exclude_recent_s: float, mode: int) -> None:
    """Ground-truth overlap J of every keyframe pair beside the local scores of the
    candidates the map queries returned (paper 003 Fig. 2 style, lower triangle).

    ``overlap`` and ``scores`` are ``(N, N)``; ``scores`` is NaN where a pair was not a
    candidate. Pairs inside the recent-keyframe exclusion window are shaded.
    """
    n = len(overlap)
    lower = np.tril(np.ones((n, n), bool), -1)
    t = np.asarray(stamps_ns) / 1e9
    recent = lower & ((t[:, None] - t[None, :]) < exclude_recent_s)
    fig, axes = _figure((13.0, 6.2))
    fig.clf()
    ax1, ax2 = fig.subplots(1, 2)
    j = np.where(lower, overlap, np.nan)
    im1 = ax1.imshow(j, cmap="viridis", vmin=0, vmax=1, interpolation="nearest")
    ax1.set_title("ground-truth footprint overlap J")
    fig.colorbar(im1, ax=ax1, fraction=0.046)
    ax2.imshow(np.where(recent, 0.15, np.nan), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    qi, ci = np.nonzero(np.isfinite(scores))
    sc = ax2.scatter(ci, qi, c=scores[qi, ci], s=4, cmap="viridis", marker="s")
    ax2.set_xlim(-0.5, n - 0.5)
    ax2.set_ylim(n - 0.5, -0.5)
    ax2.set_aspect("equal")
    ax2.set_title(f"local score of the returned candidates (mode {mode})\n"
                  f"grey: the last {exclude_recent_s:.0f} s, never queried")
    fig.colorbar(sc, ax=ax2, fraction=0.046)
    for ax in (ax1, ax2):
        ax.set_xlabel("earlier keyframe j")
        ax.set_ylabel("keyframe i")
    _save(fig, path)


def plot_loop_curves(path: Path, curves: dict[int, Any], thresholds: dict[int, float | None],
                     confidence: float, title: str = "") -> None:
    """P(loop | local score) per descriptor mode, with each mode's threshold (paper 003 Fig. 5).

    Each curve is drawn through its bins' centres; the shaded band reaches down to the
    lower credible bound; a dotted vertical line marks the mode's threshold."""
    fig, ax = _figure((8.0, 5.0))
    for m, c in curves.items():
        mid = 0.5 * (c.score_lo + c.score_hi)
        t = thresholds.get(m)
        label = f"mode {m}: threshold {t:.1f}" if t is not None else f"mode {m}: no threshold"
        line, = ax.plot(mid, c.probability, "-", lw=1.8, label=label)
        ax.fill_between(mid, c.lower, c.probability, color=line.get_color(), alpha=0.15)
        if t is not None:
            ax.axvline(t, color=line.get_color(), ls=":", lw=1)
    ax.axhline(confidence, color="k", ls="--", lw=0.8, label=f"confidence {confidence}")
    ax.set_xlabel("local score")
    ax.set_ylabel("P(loop | score)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    _save(fig, path)


def plot_stage_times(path: Path, stage_times_s: dict[str, np.ndarray], average_every: int = 5,
                     extra_s: dict[str, np.ndarray] | None = None, title: str = "") -> None:
    """Processing time per image, stage by stage, stacked (paper 000 Fig. 7).

    ``stage_times_s``: per stage (in processing order), ``(N,)`` seconds per image; each
    curve is the cumulative time up to that stage, averaged over blocks of
    ``average_every`` images as in the paper. ``extra_s``: other per-image times drawn as
    dashed lines (a baseline's).
    """
    def block_mean(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.asarray(a, np.float64)
        k = max(1, average_every)
        m = len(a) // k * k
        if m == 0:
            return np.arange(len(a)), a
        xs = np.arange(m).reshape(-1, k).mean(axis=1)
        ys = a[:m].reshape(-1, k).mean(axis=1)
        return xs, ys

    fig, ax = _figure((8.0, 5.0))
    markers = ["^", "o", "s", "D", "v", "x"]
    total: np.ndarray | None = None
    for (name, t), mk in zip(stage_times_s.items(), markers):
        first = total is None
        times = np.asarray(t, np.float64)
        total = times if total is None else total + times
        xs, ys = block_mean(total)
        ax.plot(xs, ys * 1e3, "-" + mk, ms=4, lw=1.2, label=name if first else f"+ {name}")
    for name, t in (extra_s or {}).items():
        xs, ys = block_mean(t)
        ax.plot(xs, ys * 1e3, "--", lw=1.2, label=name)
    ax.set_xlabel("image")
    ax.set_ylabel(f"time per image (ms, mean of {average_every})")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    _save(fig, path)


def plot_likelihood_posterior(path: Path, image_id: int, scores: np.ndarray, virtual_score: float,
                              posterior: np.ndarray, loop_threshold: float,
                              truth: np.ndarray | None = None, title: str = "") -> None:
    """The full posterior and the likelihood of one image's hypotheses (paper 000 Fig. 5).

    ``scores (n,)``: tf-idf votes of the image hypotheses 0 .. n - 1; ``virtual_score``:
    the no-loop image's vote (drawn at -1); ``posterior (1 + n,)``: no-loop first.
    The likelihood panel shows the mean of the scores and mean + standard deviation (the
    level above which a hypothesis is believed). ``truth (n,) bool``: the true matches,
    marked along the axis.
    """
    n = len(scores)
    fig, axes = _figure((9.0, 6.0))
    fig.clf()
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    x = np.arange(-1, n)
    ax1.bar(x, posterior, width=0.8, color="#1f77b4")
    ax1.axhline(loop_threshold, color="r", ls="--", lw=0.8, label=f"threshold {loop_threshold:g}")
    ax1.set_ylabel("posterior")
    ax1.set_ylim(0, 1.02)
    ax1.legend(fontsize=8)
    all_s = np.concatenate([[virtual_score], np.asarray(scores, np.float64)])
    ax2.bar(x, all_s, width=0.8, color="#7f7f7f")
    ax2.bar([-1], [virtual_score], width=0.8, color="#ff7f0e", label="virtual no-loop image")
    mean, std = float(all_s.mean()), float(all_s.std())
    ax2.axhline(mean, color="g", lw=1.2, label="mean")
    ax2.axhline(mean + std, color="b", ls=":", lw=1.2, label="mean + std")
    if truth is not None and np.any(truth):
        ax2.plot(np.flatnonzero(truth), np.zeros(int(np.sum(truth))), "r^", ms=6, label="true match")
    ax2.set_xlabel("hypothesis (past image; -1 = no loop)")
    ax2.set_ylabel("tf-idf score")
    ax2.legend(fontsize=8)
    ax1.set_title(title or f"image {image_id}: posterior and likelihood")
    _save(fig, path)


def plot_pr_curves(path: Path, curves: dict[str, dict[str, list[float]]],
                   points: dict[str, tuple[float, float]], title: str = "") -> None:
    """Precision against recall, one line per method (``curves``: ``{"recall": [...],
    "precision": [...]}`` as :func:`robotd.forward.evaluation.pr_curve` gives), and each
    method's operating point (``points``: name -> (recall, precision)) marked."""
    fig, ax = _figure((6.0, 4.5))
    for name, c in curves.items():
        ax.plot(c["recall"], c["precision"], marker=".", markersize=3, label=name)
    for name, (r, p) in points.items():
        ax.plot([r], [p], "k*", markersize=10, label=f"{name}: operating point")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    _save(fig, path)
