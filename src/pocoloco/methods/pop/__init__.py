"""POP: losses (paper Eq. 3-6), training data and task, prediction, unseen-outfit fitting (Eq. 7)."""

from pocoloco.methods.pop.data import (
           POPDataset,
           POPSample,
           collate_pop,
           make_optimizer,
           pop_sample_from_frame,
           train_step,
)
from pocoloco.methods.pop.fitting import POPFit, fit_unseen_outfit
from pocoloco.methods.pop.losses import (
           POPLosses,
           POPLossWeights,
           normal_weight_at,
           pop_losses,
           pop_losses_reference,
)
from pocoloco.methods.pop.method import POPMethod, POPTask, pop_query_for

__all__ = ["POPDataset", "POPFit", "POPLossWeights", "POPLosses", "POPMethod", "POPSample", "POPTask", "collate_pop", "fit_unseen_outfit",
           "make_optimizer", "normal_weight_at", "pop_losses", "pop_losses_reference", "pop_query_for",
           "pop_sample_from_frame", "train_step"]
