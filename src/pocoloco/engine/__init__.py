"""The machinery every method trains and ships with: the one training loop
(:mod:`~pocoloco.engine.trainer`), atomic checkpoints (:mod:`~pocoloco.engine.checkpoint`) and
the registry of shipped models (:mod:`~pocoloco.engine.shipped`)."""
