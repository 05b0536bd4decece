"""Training the learned method (docs/architecture.md, "The method"): synthetic datasets, the loop, DDP via torchrun."""
