"""Networks and losses: one file per network with its Config dataclass."""


def named_preset(presets: dict, name: str, network: str):
    """A copy of `presets[name]` (a Config dataclass), or a one-line --preset error naming the choices."""
    import dataclasses

    from dlacli.errors import DlaInputError

    if name not in presets:
        raise DlaInputError("--preset", f"unknown {network} preset {name!r}; choose one of {', '.join(presets)}")
    return dataclasses.replace(presets[name])
