"""The pipeline's stages, one per module (:mod:`robotd.app.pipeline` routes messages to
them by type; :func:`robotd.app.assemble.build_pipeline` registers them).

``odometry``        (:mod:`.odometry`) wheel ticks + gyro -> the filter it owns; publishes
                    ``OdometryUpdate``; fuses ``VisualOdometryStep``.
``keyframes``       (:mod:`.keyframes`) floor frames wait until the odometry has settled
                    past their stamp, take the pose at it; a frame far enough from the last
                    keyframe becomes a ``Keyframe``.
``graph``           (:mod:`.pose_graph`) the pose graph: gates loop candidates, relocalises,
                    owns the localisation over mapped ground.
``forward``         (:mod:`.forward_loops`) the forward camera's loop detector.
``floor``           (:mod:`.floor`) ``Keyframe`` -> ``DescribedKeyframe``; queries the map
                    with each stored keyframe; publishes loop candidates.
``visual_odometry`` (:mod:`.visual_odometry`) -> ``MeasuredKeyframe`` and the step for the
                    filter.
``map``             (:mod:`.map_writer`) stores keyframes and links; publishes
                    ``KeyframeStored``.
``loops_ungated``   (:mod:`.loops_ungated`) without a pose graph: candidates become loops.
"""
