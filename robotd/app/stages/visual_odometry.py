"""The floor visual odometry stage (paper 003 Sec. IV-D)."""

from __future__ import annotations

import collections
from collections.abc import Mapping

import numpy as np

from robotd.app.pipeline import Handler, Publisher
from robotd.base.geometry import between_error_covariance, compose
from robotd.base.messages import (
    DescribedKeyframe,
    Keyframe,
    MeasuredKeyframe,
    VisualOdometryStep,
    keyframe_as,
)
from robotd.floor.vo import FloorVisualOdometry
from robotd.graph.bias import scale_jacobian
from robotd.odometry.history import EdgeBiasTerms
from robotd.odometry.increments import combine_bias_terms, combine_edges, edge_disagreement


class VisualOdometryStage(Publisher):
    """Floor visual odometry between consecutive keyframes (paper 003 Sec. IV-D).

    It takes ``takes`` (a :class:`~robotd.base.messages.DescribedKeyframe` when the floor
    detector describes keyframes, whose descriptor it reuses; else the bare
    :class:`~robotd.base.messages.Keyframe`) and publishes a
    :class:`~robotd.base.messages.MeasuredKeyframe`.
    ``fused``: each step goes to the odometry filter as a
    :class:`~robotd.base.messages.VisualOdometryStep` (a relative-pose measurement,
    :meth:`robotd.odometry.fusion.OdometryFilter.on_visual_odometry`; a failed step leaves
    the filter alone), and the keyframe's odometry edge becomes the wheel + gyro edge and
    the step combined as two independent measurements
    (:func:`robotd.odometry.increments.combine_edges`; the filter keeps a wheel + gyro twin
    for those edges, ``vo_twin``), counted in ``vo_combined``; a step that disagrees with the
    wheel + gyro edge beyond the filter's chi-square gate (``gate_nis``) is left out of
    the edge (``vo_disagreed``), as the filter leaves it out of its state. In both modes it
    keeps the visual odometry alone dead-reckoned (``MeasuredKeyframe.visual_pose``).
    ``vision_only``: each successful step becomes the keyframe's odometry edge in the map
    (the pose graph's odometry), and a failed one falls back to the filter's increment
    (counted in ``vo_fallback``).
    """

    name = "visual_odometry"
    produces = (MeasuredKeyframe, VisualOdometryStep)

    def __init__(self, vo: FloorVisualOdometry, mode: str, *, gate_nis: float = 16.27,
                 takes: type[Keyframe] = DescribedKeyframe,
                 scale_sigmas: tuple[float, float] | None = None) -> None:
        if mode not in ("fused", "vision_only"):
            raise ValueError(f"visual odometry mode must be 'fused' or 'vision_only', not {mode!r}")
        self.vo = vo
        self.mode = mode
        self.gate_nis = gate_nis
        self.takes = takes
        # [pose_graph] odometry_model "bias_scale_window": the graph's scale prior, (wheel, gyro)
        self.scale_var = None if scale_sigmas is None else np.square(np.asarray(scale_sigmas, float))
        self._prev_stamp_ns: int | None = None
        self._visual_pose: np.ndarray | None = None
        self.steps = 0
        self.ok = 0
        self.fallback = 0
        self.combined = 0
        self.disagreed = 0
        self.failures = collections.Counter[str]()

    def subscriptions(self) -> Mapping[type, Handler]:
        return {self.takes: self.on_keyframe}

    def on_keyframe(self, kf: Keyframe) -> None:
        if isinstance(kf, DescribedKeyframe) and kf.descriptor is not None \
                and kf.descriptor[0] == self.vo.params.descriptor_mode:
            result = self.vo.step(kf.descriptor[1], kf.keypoints_px)
        else:
            result = self.vo.step(kf.frame.image)
        first = self._prev_stamp_ns is None
        if not first:
            self.steps += 1
            if result.ok:
                self.ok += 1
            else:
                self.failures[result.reason] += 1
        step = None
        if result.ok and not first:
            step = (result.delta, between_error_covariance(result.delta, result.covariance))
        edge = kf.odometry_edge
        bias = kf.odometry_bias
        if first or self._visual_pose is None:
            self._visual_pose = kf.pose_xyyaw
        elif step is not None or edge is not None:
            self._visual_pose = compose(self._visual_pose, (step or edge)[0])  # type: ignore[index]
        if self.mode == "fused":
            self._publish(VisualOdometryStep(kf.stamp_ns, self._prev_stamp_ns,
                                             result.delta if result.ok else None,
                                             result.covariance if result.ok else None))
            if step is not None:
                if edge is None:
                    edge = step
                    bias = None
                else:
                    share = None
                    twin = edge
                    if self.scale_var is not None and bias is not None:
                        # the twin's edge as the graph holds it: marginal over the scale too
                        js = scale_jacobian(edge[0])
                        share = (js * self.scale_var) @ js.T
                        twin = (edge[0], edge[1] + share)
                    if edge_disagreement(twin, step) > self.gate_nis:
                        self.disagreed += 1  # a wrong step (a look-alike lattice shift): wheels only
                    else:
                        combined = combine_edges(twin, step)
                        if bias is not None:  # the step does not see the gyro bias: the twin's share keeps it
                            bias = tuple(combine_bias_terms(twin[1], combined[1], EdgeBiasTerms(*bias), share))
                        edge = combined
                        self.combined += 1
        elif not first:  # vision only
            if step is not None:
                edge = step
                bias = None
            else:
                self.fallback += 1
        self._prev_stamp_ns = kf.stamp_ns
        self._publish(keyframe_as(MeasuredKeyframe, kf, odometry_edge=edge, odometry_bias=bias,
                                  visual_pose=self._visual_pose))

    def status_fragment(self) -> str:
        """For STATUS: how many steps the floor measured (a dirty lens or a bare floor shows
        here first)."""
        if not self.steps:
            return ""
        return f"floor VO {100.0 * self.ok / self.steps:.0f} % of {self.steps} steps"

    def counters(self) -> dict[str, int]:
        out = {"vo_steps": self.steps, "vo_ok": self.ok, "vo_fallback": self.fallback,
               "vo_combined": self.combined, "vo_disagreed": self.disagreed}
        out.update({f"vo_failed_{k}": n for k, n in sorted(self.failures.items())})
        return out
