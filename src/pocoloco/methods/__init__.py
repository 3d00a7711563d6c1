"""The methods: PocoLoco (the diffusion model this project is about) and its peers POP and CloSET,
each a folder behind one interface (:class:`~pocoloco.methods.base.Method`) and one registry
(:mod:`~pocoloco.methods.registry`).

- :mod:`~pocoloco.methods.pocoloco`: presets, training task, sampling.
- :mod:`~pocoloco.methods.pop`, :mod:`~pocoloco.methods.closet`: losses, batches, training tasks,
  prediction; POP also fits an unseen outfit (:mod:`~pocoloco.methods.pop.fitting`).
- :mod:`~pocoloco.methods.skinned`: what POP and CloSET share (config, outfits, posed bodies).

``load_method(ckpt)`` loads any checkpoint; ``train(config, data, out)`` trains any method.
"""

from pocoloco.methods.base import Method, SampledClouds, SamplerOptions, check_memory, fit_to_memory, predict_clouds
from pocoloco.methods.registry import (
           METHODS,
           checkpoint_kind,
           load_method,
           method_class,
           train,
           train_preset,
)

__all__ = ["METHODS", "Method", "SampledClouds", "SamplerOptions", "check_memory", "fit_to_memory", "checkpoint_kind", "load_method", "method_class",
           "predict_clouds", "train", "train_preset"]
