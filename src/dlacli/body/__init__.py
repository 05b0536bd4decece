"""Body model layer: the only package that imports anny."""
