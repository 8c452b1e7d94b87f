"""Training rays and their labels, batches, the training loop."""
