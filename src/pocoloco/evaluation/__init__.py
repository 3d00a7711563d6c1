"""Scoring models: metrics (:mod:`~pocoloco.evaluation.metrics`), baselines
(:mod:`~pocoloco.evaluation.baselines`), ``pocoloco eval`` (:mod:`~pocoloco.evaluation.evaluate`) and
``pocoloco bench quality`` (:mod:`~pocoloco.evaluation.quality`)."""
