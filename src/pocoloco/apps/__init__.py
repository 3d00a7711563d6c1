"""Applications of trained models beyond sampling (``pocoloco complete / edit / animate / fit / mesh``).

- :mod:`~pocoloco.apps.completion`: fill the holes of a partial scan (a full sample's hole points,
  harmonised by RePaint-style inpainting; or plain RePaint from noise).
- :mod:`~pocoloco.apps.editing`: move a cloud to a new pose (SDEdit renoising, or inpainting the
  parts whose bones moved).
- :mod:`~pocoloco.apps.animation`: clouds for a motion (independent, shared noise, or a chain of
  renoised frames) and a body-warped flicker metric.
- :mod:`~pocoloco.apps.fitting`: fit an outfit the model never saw to one scan (POP) and report it.
- :mod:`~pocoloco.apps.meshing`: watertight Poisson meshes of clouds, optionally with the anny
  body's head and hands.

Completion, editing and animation run on any method's generative hook,
``method.point_prior(outfit)`` (:class:`pocoloco.methods.base.PointPrior`: a denoiser under one
pose, its normalisation and schedule), through the SDEdit / RePaint chains of
:mod:`pocoloco.diffusion.chains` (:func:`pocoloco.apps.common.denoise_from`); a method without the
hook (POP, CloSET) answers with a one-line error.
"""
