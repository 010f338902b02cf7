"""The pose network: model, loss, augmentations, training loop."""
