"""Training and evaluation: the paper's loss, the (DDP) trainer, ensembles, error tables."""
