"""Networks and losses: one file per network with its Config dataclass."""
