"""Dream: one photo of a person -> a view folder (the photo and three novel views) and the fitted
body (docs/dream.md).

    views.py         the stage: inputs read, body fitted (stages/fit/photo.py), photo framed, views made, folder written
    backends/        the ways to make the novel views, registered by name: body, shell, diffusion
    texture.py       the body backend: the photo baked onto the body's UV map and rendered
    completion.py    the completion prior: what the photo does not show, learned (nn/completion.py)
    beyond.py        clothes and hair beyond the body: the displaced body the body backend renders
    occluders.py     which baked texels show a limb in front of them: left to the completion
    shell.py         the shell backend's 2.5D shell
    orbit.py         the novel views' cameras: the photo's camera turned about the body
    plausibility.py  sheets and streaks in the dreamed views: recorded in the folder
"""
