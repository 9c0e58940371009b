"""The simulator: traces with ground truth from force models, noise and the instrument."""
