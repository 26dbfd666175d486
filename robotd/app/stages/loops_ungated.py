"""Loops without a pose graph."""

from __future__ import annotations

from collections.abc import Mapping

from robotd.app.pipeline import Handler, Publisher
from robotd.base.messages import CandidateFate, Link, LoopCandidate, LoopFate


class LoopsUngated(Publisher):
    """Without a pose graph ([pose_graph] enabled = false), every loop candidate at or
    above the threshold becomes a loop link, recorded as accepted without a gate."""

    name = "loops_ungated"
    produces = (CandidateFate, Link)
    optional_inputs = (LoopCandidate,)

    def subscriptions(self) -> Mapping[type, Handler]:
        return {LoopCandidate: self.on_candidate}

    def on_candidate(self, c: LoopCandidate) -> None:
        self._publish(CandidateFate(c.to_id, c.from_id, c.score, LoopFate.ACCEPTED, "no pose graph: not gated"))
        self._publish(Link("loop", c.from_id, c.to_id, c.delta_xyyaw, c.information))
