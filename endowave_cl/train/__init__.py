"""Host-side building blocks of training: config, losses, densification, checkpoints, init."""
