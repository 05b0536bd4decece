"""Command-line interface: parsing and printing only; nothing imports this package."""
