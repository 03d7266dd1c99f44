"""Batched TorchRL environments (batch_size=[N]) for A3CQP training and evaluation."""
