"""Training: the trainer, its setup, hooks, checkpoints, the mode probe, the budget and the model check."""
