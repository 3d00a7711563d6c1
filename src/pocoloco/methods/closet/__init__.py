"""CloSET: losses (paper Eqs. 4-6), batches, training task, prediction."""

from pocoloco.methods.closet.data import (
    CloSETBatch,
    closet_predict,
    closet_train_step,
    make_closet_batch,
    make_closet_optimizer,
)
from pocoloco.methods.closet.losses import CloSETLossWeights, closet_loss, nearest_sq
from pocoloco.methods.closet.method import CloSETMethod, CloSETTask

__all__ = ["CloSETBatch", "CloSETLossWeights", "CloSETMethod", "CloSETTask", "closet_loss", "closet_predict",
           "closet_train_step", "make_closet_batch", "make_closet_optimizer", "nearest_sq"]
