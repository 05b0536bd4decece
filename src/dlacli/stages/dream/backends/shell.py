"""The dream backend "shell" (CPU, no weights; "template" is its legacy name): a 2.5D shell built
from the photo's silhouette and the fitted body's depth, coloured from the photo in front and
from the mirrored front behind, rendered by the triangle rasteriser (stages/dream/shell.py)."""

from __future__ import annotations

from dlacli.stages.dream.backends import Backend, register


def shell_backend_views(rgb, alpha, cam, vertices, loaded, *, frames, steps, seed, say, prior=None):
    from dlacli.stages.dream.shell import template_views

    say("rendering the shell views")
    images, masks, cams = template_views(rgb, alpha, cam, vertices)
    return images, masks, cams, {}


ABOUT = "CPU: the photo on a 2.5D image-space shell"
register(Backend("shell", ABOUT, shell_backend_views))
register(Backend("template", "the legacy name of shell (the default before body)", shell_backend_views))
