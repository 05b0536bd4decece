"""The dream backend "body" (the default; CPU, no weights): the photo baked onto the fitted
body's UV map, completed by the completion prior where the photo does not show the body, on the
body displaced where the photo's mask shows clothes or hair beyond it, rendered textured
(stages/dream/texture.py)."""

from __future__ import annotations

from dlacli.stages.dream.backends import Backend, register


def body_backend_views(rgb, alpha, cam, vertices, loaded, *, frames, steps, seed, say, prior=None):
    from dlacli.stages.dream.texture import body_views

    say("baking the photo onto the body and rendering its views")
    return body_views(rgb, alpha, cam, vertices, prior=prior)


register(
    Backend(
        "body",
        "CPU, no weights: the photo baked onto the fitted body's UV map, completed by the completion prior, "
        "rendered from the fitted body with clothes and hair as a bounded thickness",
        body_backend_views,
        takes_prior=True,
    )
)
