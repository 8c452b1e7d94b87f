"""Files the product writes and reads back: the .nbvh model, training checkpoints."""
