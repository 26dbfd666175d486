"""Evaluation against ground truth: trajectory metrics (:mod:`.metrics`), what a run's
pipeline published (:mod:`.observations`) and the judgement of each subsystem by the
truth (:mod:`.groundtruth`).

Pure functions of arrays and messages, no I/O: the demo (:mod:`robotd.app.demo`) and the
benchmarks in ``bench/`` call them alike. The layer sits above the algorithms (it judges
the floor detector's candidates with :mod:`robotd.floor.evaluation`) and below io.
"""
