"""Training the learned method (DESIGN.md §1): synthetic datasets, the loop, DDP via torchrun."""
