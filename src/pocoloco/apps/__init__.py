"""Applications of a trained PocoLoco model beyond sampling (``pocoloco complete / edit / animate``).

- :mod:`~pocoloco.apps.completion`: fill the holes of a partial scan (a full sample's hole points,
  harmonised by RePaint-style inpainting; or plain RePaint from noise).
- :mod:`~pocoloco.apps.editing`: move a cloud to a new pose (SDEdit renoising, or inpainting the
  parts whose bones moved).
- :mod:`~pocoloco.apps.animation`: clouds for a motion (independent, shared noise, or a chain of
  renoised frames) and a body-warped flicker metric.

All three run the samplers of :mod:`pocoloco.diffusion.samplers` from an intermediate state
(:func:`pocoloco.apps._common.denoise_from`).
"""
