"""The authors' TensorFlow reference: its checkpoints read without TensorFlow
(:mod:`emlpack.legacy.tf_checkpoint`) and its weights loaded into :class:`~emlpack.nn.EMLP`
(:mod:`emlpack.legacy.reference_weights`)."""
